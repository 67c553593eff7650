"""Calibrate a rig of several arms and cameras (Cobot Magic: two arms, a head camera, a wrist
camera on each gripper) from one version 2 episode in which a ChArUco board lies still in the world.

Each camera on an arm's link is an eye-in-hand problem (:func:`.solve.solve_hand_eye`, mount =
the link): its ``T_link_cam`` and, as the second unknown, the board in that arm's base
``T_base_board``. Each camera fixed in the world sees the same still board in every frame: one
PnP over the corners of all its views gives ``T_cam_board``. The board ties everything together:
each arm's base and each world camera are known in the board frame, and the world is chosen
among them (:func:`world_in_board`): by default the Cobot Magic convention, the midpoint of the
arm bases with their mean z up and mean x forward.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from manisplat.calib.board import BoardSpec
from manisplat.calib.camera import CameraModel
from manisplat.calib.detect import BoardDetector, BoardView, require_views
from manisplat.calib.episode_solve import MAX_JOINT_SPEED, detect_episode, moving_frames
from manisplat.calib.errors import InputError, NotEnoughDataError
from manisplat.calib.poses import inv_T, make_T, pose_difference, project_rotation
from manisplat.calib.solve import HandEyeResult, solve_hand_eye
from manisplat.episode import Episode
from manisplat.episode.format import VERSION_2, WORLD_MOUNT
from manisplat.robot import load_robot

log = logging.getLogger(__name__)

BASES_WORLD = "bases"
"""The default world: origin at the midpoint of the arm bases, z their mean up, x their mean forward."""


@dataclass
class StaticBoardView:
    """A world camera's pose of the still board from all its views at once.

    Attributes:
        T_cam_board: (4, 4) float64, metres.
        rms_px, max_px: corner reprojection error over every view.
        views: usable views; spread_deg, spread_mm: the largest difference of a single view's PnP
            pose from the joint one (a board or camera that moved shows here).
    """

    T_cam_board: np.ndarray
    rms_px: float
    max_px: float
    views: int
    spread_deg: float
    spread_mm: float


@dataclass
class RigCamera:
    """One solved camera: its intrinsics, mount (``world`` or ``<arm>/<link>``), ``T_mount_cam`` (4, 4)
    and how it was found (``hand_eye`` for a wrist camera, ``static`` for a world camera)."""

    name: str
    camera: CameraModel
    mount: str
    T_mount_cam: np.ndarray
    hand_eye: HandEyeResult | None = None
    static: StaticBoardView | None = None
    rejected: dict[int, str] = field(default_factory=dict)


@dataclass
class RigSolve:
    """The solved rig, in the chosen world.

    Attributes:
        world: what the world is (``"bases"``, an arm's or a world camera's name).
        T_world_board: (4, 4) the board in the world.
        T_world_base: arm -> (4, 4) its base in the world.
        base_from: arm -> the wrist camera whose eye-in-hand solve placed it.
        cameras: camera -> :class:`RigCamera` (world cameras' ``T_mount_cam`` is ``T_world_cam``).
        corner_offset_px, episode, spec: provenance.
    """

    world: str
    T_world_board: np.ndarray
    T_world_base: dict[str, np.ndarray]
    base_from: dict[str, str]
    cameras: dict[str, RigCamera]
    corner_offset_px: float
    episode: Path
    spec: BoardSpec


def static_board_pose(views: list[BoardView], spec: BoardSpec, camera: CameraModel) -> StaticBoardView:
    """The pose of a still board from every view of a fixed camera: PnP (Levenberg-Marquardt)
    over all their corners, started from the median-error view."""
    obj = np.concatenate([spec.corners_3d()[v.ids] for v in views]).astype(np.float64)
    img = np.concatenate([v.corners for v in views]).astype(np.float64)
    start = views[int(np.argsort([v.rms_px for v in views])[len(views) // 2])].T_cam_board
    rvec, _ = cv2.Rodrigues(start[:3, :3])
    rvec, tvec = cv2.solvePnPRefineLM(obj.reshape(-1, 1, 3), img.reshape(-1, 1, 2), camera.K, camera.cv_dist,
                                      rvec, start[:3, 3].reshape(3, 1).copy())
    T = make_T(cv2.Rodrigues(rvec)[0], tvec.reshape(3))
    err = np.linalg.norm(camera.project(T, obj) - img, axis=1)
    spread = [pose_difference(T, v.T_cam_board) for v in views]
    return StaticBoardView(T, float(np.sqrt(np.mean(err ** 2))), float(err.max()), len(views),
                           max(s[0] for s in spread), max(s[1] for s in spread))


def world_in_board(world: str, T_board_base: dict[str, np.ndarray], T_board_cam: dict[str, np.ndarray]) -> np.ndarray:
    """``T_board_world`` (4, 4) for ``world``: ``"bases"`` (origin at the mean of the base origins, z the
    mean of their z axes, x the mean of their x axes made orthogonal to z), an arm (its base) or a
    world camera (its optical frame)."""
    if world == BASES_WORLD:
        bases = np.stack(list(T_board_base.values()))
        z = bases[:, :3, 2].mean(axis=0)
        x = bases[:, :3, 0].mean(axis=0)
        x -= (x @ z) * z / max(z @ z, 1e-300)
        if np.linalg.norm(z) < 0.1 or np.linalg.norm(x) < 0.1:
            raise InputError(f"--world {BASES_WORLD}: the bases of {', '.join(T_board_base)} point in opposite "
                             "directions (no mean up or forward axis); choose an arm or a camera as the world")
        z /= np.linalg.norm(z)
        x /= np.linalg.norm(x)
        return make_T(np.column_stack([x, np.cross(z, x), z]), bases[:, :3, 3].mean(axis=0))
    if world in T_board_base:
        return T_board_base[world]
    if world in T_board_cam:
        return T_board_cam[world]
    raise InputError(f"--world {world!r}: not {BASES_WORLD!r}, an arm ({', '.join(T_board_base) or 'none placed'}) "
                     f"or a camera fixed in the world ({', '.join(T_board_cam) or 'none'})")


def _camera_model(ep: Episode, name: str) -> CameraModel:
    c = ep.cameras[name]
    return CameraModel(K=c.K, dist=c.dist, width=c.width, height=c.height)


def _require(views: list[BoardView], needed: int, rejected: dict[int, str], total: int, camera: str) -> None:
    """:func:`require_views`, its message naming ``camera``."""
    try:
        require_views(views, needed, rejected, total)
    except NotEnoughDataError as exc:
        raise NotEnoughDataError(f"camera {camera}: {exc}") from None


def _solve_wrist(ep: Episode, name: str, detector: BoardDetector, spec: BoardSpec, use_opencv: bool,
                 max_joint_speed: float | None) -> RigCamera:
    """Eye-in-hand of the camera ``name`` riding on ``<arm>/<link>``: frames where its arm moves are skipped."""
    info = ep.cameras[name]
    arm, link = info.mount.split("/", 1)
    cam = _camera_model(ep, name)
    moving = {} if max_joint_speed is None else moving_frames(ep, max_joint_speed, arm=arm)
    views, rejected = detect_episode(ep, detector, cam, [i for i in range(len(ep)) if i not in moving], name=name)
    rejected = dict(sorted({**rejected, **moving}.items()))
    _require(views, 3, rejected, len(ep), name)
    robot = load_robot(ep.arms[arm].description, base_dir=ep.path, load_meshes=False)
    A = robot.link_pose(ep.arm_frames(arm).q[[v.index for v in views]], link).numpy().astype(np.float64)
    result = solve_hand_eye(views, A, spec, cam, mount=link, link=link, use_opencv=use_opencv)
    return RigCamera(name, cam, info.mount, result.T_mount_cam, hand_eye=result, rejected=rejected)


def _solve_world(ep: Episode, name: str, detector: BoardDetector, spec: BoardSpec) -> RigCamera:
    cam = _camera_model(ep, name)
    views, rejected = detect_episode(ep, detector, cam, name=name)
    _require(views, 1, rejected, len(ep), name)
    static = static_board_pose(views, spec, cam)
    return RigCamera(name, cam, WORLD_MOUNT, static.T_cam_board, static=static, rejected=rejected)


def solve_rig(path: str | Path, spec: BoardSpec, *, world: str = BASES_WORLD, corner_offset: float | None = None,
              use_opencv: bool = True, max_joint_speed: float | None = MAX_JOINT_SPEED) -> RigSolve:
    """Calibrate every camera and arm base of a version 2 episode with a still board (module docstring).

    Args:
        path: the episode; its cameras' K, dist and mounts are read, ``T_mount_cam`` and
            ``T_world_base`` are not used.
        world: ``"bases"``, an arm or a world camera (:func:`world_in_board`).
        corner_offset: detector offset override (px); None measures it.
        max_joint_speed: a wrist camera's frames in which its arm moves faster (rad/s, from
            ``joints_<arm>.csv``) are skipped; None keeps all.

    Raises:
        InputError: a version 1 episode.
        NotEnoughDataError: an arm carries no camera (its base cannot be placed), or a camera
            has too few usable views (listing why each frame was refused).
        DegenerateMotionError: an arm's poses do not determine its wrist camera.
    """
    ep = Episode.open(path)
    if ep.meta.version != VERSION_2:
        raise InputError(f"{path}: version {ep.meta.version} (one arm, one camera): calibrate it with "
                         "`manisplat-calibrate solve`; solve-rig reads version 2 episodes")
    without = [arm for arm in ep.arms if not any(c.mount.split("/", 1)[0] == arm for c in ep.cameras.values())]
    if without:
        raise NotEnoughDataError(f"{path}: arm {', '.join(without)} carries no camera: with a still board its base "
                                 "is placed through the eye-in-hand calibration of a camera on it (mount "
                                 "'<arm>/<link>')")
    detector = BoardDetector(spec, corner_offset=corner_offset)
    cameras: dict[str, RigCamera] = {}
    for name, info in ep.cameras.items():
        if info.mount == WORLD_MOUNT:
            cameras[name] = _solve_world(ep, name, detector, spec)
        else:
            cameras[name] = _solve_wrist(ep, name, detector, spec, use_opencv, max_joint_speed)
        log.info("%s: %s solved", path, name)
    T_board_base: dict[str, np.ndarray] = {}
    base_from: dict[str, str] = {}
    for arm in ep.arms:  # the arm's wrist camera with the smallest base uncertainty places it
        solved = [c for c in cameras.values() if c.hand_eye is not None and c.mount.split("/", 1)[0] == arm]
        best = min(solved, key=lambda c: c.hand_eye.uncertainty()["other_trans_std_mm"])
        T_board_base[arm], base_from[arm] = inv_T(best.hand_eye.T_other), best.name
    T_board_cam = {name: inv_T(c.static.T_cam_board) for name, c in cameras.items() if c.static is not None}
    T_world_board = inv_T(world_in_board(world, T_board_base, T_board_cam))
    for name, T in T_board_cam.items():
        cameras[name].T_mount_cam = _rigid(T_world_board @ T)
    T_world_base = {arm: _rigid(T_world_board @ T) for arm, T in T_board_base.items()}
    return RigSolve(world, T_world_board, T_world_base, base_from, cameras, detector.corner_offset, Path(path), spec)


def _rigid(T: np.ndarray) -> np.ndarray:
    """``T`` (4, 4) with its rotation re-projected onto SO(3) (products drift by ~1e-16 per step)."""
    return make_T(project_rotation(T[:3, :3]), T[:3, 3])

