"""Solve a recorded calibration episode: detect the board in every frame, pair each usable
view with the FK pose of its frame's joints, and run :func:`.solve.solve_hand_eye`."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from manisplat.calib.board import BoardSpec
from manisplat.calib.camera import CameraModel
from manisplat.calib.detect import BoardDetector, BoardView, require_views
from manisplat.calib.errors import InputError
from manisplat.calib.handeye import is_eye_to_hand
from manisplat.calib.solve import HandEyeResult, solve_hand_eye
from manisplat.episode import Episode
from manisplat.robot import load_robot

log = logging.getLogger(__name__)


@dataclass
class EpisodeSolve:
    """A solved episode: the result, the camera used, the detection outcome per frame.

    Attributes:
        result: the hand-eye solution.
        camera: intrinsics used.
        views: usable board views (frame order).
        rejected: frame index -> why it was not used.
        corner_offset_px: the detector offset subtracted.
        episode: the episode folder.
        spec: the board.
    """

    result: HandEyeResult
    camera: CameraModel
    views: list[BoardView]
    rejected: dict[int, str]
    corner_offset_px: float
    episode: Path
    spec: BoardSpec


def camera_of(ep: Episode) -> CameraModel:
    """The intrinsics ``episode.json`` declares."""
    c = ep.camera
    return CameraModel(K=c.K, dist=c.dist, width=c.width, height=c.height)


MAX_JOINT_SPEED = 0.02
"""rad/s: frames taken while a joint moves faster (within +-0.1 s, from joints.csv) are not used:
the image and the joint reading would not describe the same pose."""


def moving_frames(ep: Episode, max_speed: float = MAX_JOINT_SPEED, window_s: float = 0.1,
                  arm: str | None = None) -> dict[int, str]:
    """Frame index -> reason, for frames where the joint stream of ``arm`` (default: the one arm)
    shows it moving."""
    joints = ep.joints(arm)
    if joints is None or len(joints) < 2:
        return {}
    dt = np.diff(joints.t)
    ok = dt > 0
    speed = np.zeros(len(joints.t))
    speed[1:][ok] = np.abs(np.diff(joints.q, axis=0)[ok] / dt[ok, None]).max(axis=1)
    out = {}
    for i, t in enumerate(ep.frames.t if arm is None else ep.arm_frames(arm).t):
        near = (joints.t >= t - window_s) & (joints.t <= t + window_s)
        if near.any() and speed[near].max() > max_speed:
            out[i] = f"arm moving ({speed[near].max():.3f} rad/s > {max_speed} rad/s)"
    return out


def detect_episode(ep: Episode, detector: BoardDetector, camera: CameraModel, frames: list[int] | None = None,
                   *, name: str | None = None) -> tuple[list[BoardView], dict[int, str]]:
    """Usable views of the camera ``name`` (default: the one camera) and the reasons for every refused frame."""
    views, rejected = [], {}
    for i in (range(len(ep)) if frames is None else frames):
        det = detector.detect(ep.rgb(i, name))
        view, why = detector.view(i, det, camera)
        if view is None:
            rejected[i] = why
        else:
            views.append(view)
    return views, rejected


def solve_episode(path: str | Path, spec: BoardSpec, *, mount: str = "base", link: str = "link6",
                  camera: CameraModel | None = None, corner_offset: float | None = None,
                  use_opencv: bool = True, max_joint_speed: float | None = MAX_JOINT_SPEED) -> EpisodeSolve:
    """Hand-eye calibration of a recorded episode.

    Args:
        path: the episode folder (static poses; frames.csv joints at each frame).
        mount: ``"base"`` (eye-to-hand, board on ``link``) or the camera's link (eye-in-hand).
        link: the board's link for eye-to-hand (default ``link6``); ignored for eye-in-hand.
        camera: intrinsics (default: the episode's); their size must match the images.
        corner_offset: detector offset override (px); None measures it.
        max_joint_speed: skip frames where joints.csv shows a faster joint (rad/s); None keeps all.
    """
    ep = Episode.open(path)
    cam = camera if camera is not None else camera_of(ep)
    if (cam.width, cam.height) != (ep.camera.width, ep.camera.height):
        raise InputError(f"intrinsics are for {cam.width}x{cam.height} but {path} has "
                               f"{ep.camera.width}x{ep.camera.height} images")
    fk_link = link if is_eye_to_hand(mount) else mount
    robot = load_robot(ep.meta.robot.description, base_dir=ep.path, load_meshes=False)
    detector = BoardDetector(spec, corner_offset=corner_offset)
    moving = {} if max_joint_speed is None else moving_frames(ep, max_joint_speed)
    views, rejected = detect_episode(ep, detector, cam, [i for i in range(len(ep)) if i not in moving])
    rejected = dict(sorted({**rejected, **moving}.items()))
    require_views(views, 3, rejected, len(ep))
    q = ep.frames.q[[v.index for v in views]]
    A = robot.link_pose(q, fk_link).numpy().astype(np.float64)
    result = solve_hand_eye(views, A, spec, cam, mount, fk_link, use_opencv=use_opencv)
    log.info("%s: %d views, %d refused, start %s", path, len(views), len(rejected), result.start)
    return EpisodeSolve(result, cam, views, rejected, detector.corner_offset, Path(path), spec)
