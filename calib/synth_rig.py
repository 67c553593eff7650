"""A synthetic Cobot Magic calibration episode with exact ground truth: two built-in PiPERs side by
side, a head camera fixed in the world and a camera on each link6, a ChArUco board lying still on
the table between the arms; every camera's view rendered by :func:`.render.render_board`. Written
as a version 2 episode whose ``T_world_base`` and ``T_mount_cam`` are null (uncalibrated), for
:func:`.rig.solve_rig` in tests and benchmarks."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from manisplat.calib.board import BoardSpec
from manisplat.calib.camera import CameraModel
from manisplat.calib.poses import inv_T, make_T, rodrigues
from manisplat.calib.render import render_board
from manisplat.calib.synth import look_at

ARMS = ("left", "right")
HEAD = "cam_high"
WRIST = {"left": "cam_left_wrist", "right": "cam_right_wrist"}


@dataclass
class RigTruth:
    """What a synthetic rig episode was made with (world: the midpoint of the bases, x forward, z up).

    Attributes:
        T_world_base: arm -> (4, 4). T_world_board: (4, 4). T_world_head: (4, 4) the head camera.
        T_link6_cam: arm -> (4, 4) its wrist camera. cameras: camera -> intrinsics.
        q: arm -> (n, 6) joints of each frame.
    """

    T_world_base: dict[str, np.ndarray]
    T_world_board: np.ndarray
    T_world_head: np.ndarray
    T_link6_cam: dict[str, np.ndarray]
    cameras: dict[str, CameraModel]
    q: dict[str, np.ndarray]


def _pinhole(width: int, height: int, f: float) -> CameraModel:
    return CameraModel(K=[[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], width=width, height=height)


def default_rig(spec: BoardSpec, yaw_deg: float = 3.0) -> RigTruth:
    """Bases at y = +-0.3 m turned +-``yaw_deg`` towards each other (their midpoint and mean axes are
    the world), the board flat on the table 0.3 m ahead, the head camera 0.75 m up behind the arms."""
    T_world_base = {"left": make_T(rodrigues([0.0, 0.0, np.radians(-yaw_deg)]), [0.0, 0.3, 0.0]),
                    "right": make_T(rodrigues([0.0, 0.0, np.radians(yaw_deg)]), [0.0, -0.3, 0.0])}
    R_board = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]) @ rodrigues([0.0, 0.0, 0.35])
    centre = np.array([0.3, 0.0, 0.0])
    T_world_board = make_T(R_board, centre - R_board @ np.array([spec.size_m[0] / 2, spec.size_m[1] / 2, 0.0]))
    T_world_head = look_at(np.array([-0.25, 0.02, 0.75]), centre)
    T_link6_cam = {arm: make_T(rodrigues([0.0, 0.0, np.pi / 2]) @ rodrigues([0.1 * s, -0.05, 0.0]), [0.06, 0.0, 0.03])
                   for arm, s in (("left", 1.0), ("right", -1.0))}
    cameras = {HEAD: _pinhole(640, 480, 1000.0), **{WRIST[a]: _pinhole(480, 360, 360.0) for a in ARMS}}
    return RigTruth(T_world_base, T_world_board, T_world_head, T_link6_cam, cameras, {})


def _sees_board(spec: BoardSpec, camera: CameraModel, T_cam_board: np.ndarray, max_view_deg: float = 50.0) -> np.ndarray:
    """(N,) bool: the whole board in view, in front of the camera (0.15-0.7 m), facing it within
    ``max_view_deg``, for poses ``T_cam_board`` (N, 4, 4)."""
    obj = spec.corners_3d()
    pc = np.einsum("nij,kj->nki", T_cam_board[:, :3, :3], obj) + T_cam_board[:, None, :3, 3]
    z = pc[..., 2]
    uv = pc[..., :2] / np.where(z > 1e-6, z, 1e-6)[..., None] * np.diag(camera.K)[:2] + camera.K[:2, 2]
    m = 6.0
    inside = ((uv[..., 0] > m) & (uv[..., 0] < camera.width - m) & (uv[..., 1] > m) & (uv[..., 1] < camera.height - m))
    ray = T_cam_board[:, :3, 3] / np.linalg.norm(T_cam_board[:, :3, 3], axis=1, keepdims=True)
    facing = np.einsum("ni,ni->n", T_cam_board[:, :3, 2], ray) > np.cos(np.radians(max_view_deg))
    return (z > 0.15).all(axis=1) & (z < 0.7).all(axis=1) & inside.all(axis=1) & facing


def sample_rig_joints(spec: BoardSpec, truth: RigTruth, n: int, rng: np.random.Generator,
                      batch: int = 40_000) -> dict[str, np.ndarray]:
    """arm -> (n, 6) random joint vectors within the limits at which its wrist camera sees the whole board."""
    from manisplat.robot import builtin_piper

    robot = builtin_piper(with_geometry=False)
    out = {}
    for arm in ARMS:
        found: list[np.ndarray] = []
        for _ in range(20):
            q = rng.uniform(robot.lower + 1e-3, robot.upper - 1e-3, (batch, 6))
            T_world_cam = truth.T_world_base[arm] @ robot.link_pose(q, "link6").numpy() @ truth.T_link6_cam[arm]
            ok = _sees_board(spec, truth.cameras[WRIST[arm]], inv_T(T_world_cam) @ truth.T_world_board)
            found += list(q[ok])
            if len(found) >= n:
                break
        if len(found) < n:
            raise RuntimeError(f"sample_rig_joints: found only {len(found)} of {n} views of the board for {arm}")
        out[arm] = np.stack(found[:n])
    return out


def write_rig_episode(path: str | Path, spec: BoardSpec, n: int, rng: np.random.Generator, *,
                      truth: RigTruth | None = None, noise_std: float = 1.5, blur_sigma: float = 0.6) -> RigTruth:
    """A still-pose version 2 calibration episode of ``n`` frames (every arm at a new pose in each),
    cameras and arms uncalibrated (null ``T_mount_cam``, ``T_world_base``). Returns the truth."""
    from manisplat.episode import ArmInfo, CameraInfo
    from manisplat.episode.writer_v2 import EpisodeWriterV2
    from manisplat.robot import builtin_piper

    robot = builtin_piper(with_geometry=False)
    truth = truth or default_rig(spec)
    truth.q = sample_rig_joints(spec, truth, n, rng)
    arms = [ArmInfo(name=a, T_world_base=None) for a in ARMS]
    mounts = {HEAD: "world", **{WRIST[a]: f"{a}/link6" for a in ARMS}}
    cameras = [CameraInfo(name=c, width=m.width, height=m.height, K=m.K, mount=mounts[c], T_mount_cam=None)
               for c, m in truth.cameras.items()]
    with EpisodeWriterV2(path, arms, cameras, 2.0, source="simulation") as writer:
        for k in range(n):
            poses = {HEAD: inv_T(truth.T_world_head) @ truth.T_world_board}
            for arm in ARMS:
                T_world_cam = truth.T_world_base[arm] @ robot.link_pose(truth.q[arm][k], "link6").numpy() \
                    @ truth.T_link6_cam[arm]
                poses[WRIST[arm]] = inv_T(T_world_cam) @ truth.T_world_board
            images = {}
            for name, T_cam_board in poses.items():
                gray = render_board(spec, truth.cameras[name], T_cam_board, supersample=2, blur_sigma=blur_sigma,
                                    noise_std=noise_std, rng=rng)
                images[name] = np.repeat(gray[..., None], 3, axis=2)
            writer.add_frame(0.5 * k, {a: [*truth.q[a][k], 0.0] for a in ARMS}, images)
    return truth
