"""Synthetic calibration scenes with exact ground truth: random eye-to-hand / eye-in-hand
poses (board facing the camera, in view), rendered by :mod:`.render`, for tests and benchmarks."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from manisplat.calib.board import BoardSpec
from manisplat.calib.camera import CameraModel
from manisplat.calib.poses import inv_T, make_T, rodrigues
from manisplat.calib.render import render_board


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """``T_base_cam`` (4, 4) of an OpenCV camera at ``eye`` looking at ``target`` (z forward, y down)."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.column_stack([x, y, z]), eye)


@dataclass
class Scene:
    """Ground truth of a synthetic eye-to-hand set-up.

    Attributes:
        camera: intrinsics.
        T_base_cam: (4, 4) camera pose in the base.
        T_link_board: (4, 4) board on the gripper link.
    """

    camera: CameraModel
    T_base_cam: np.ndarray
    T_link_board: np.ndarray


def default_scene(rng: np.random.Generator | None = None, width: int = 1280, height: int = 720,
                  f: float = 900.0) -> Scene:
    """A camera about 1 m in front of and above a PiPER's workspace, with a board 5-10 cm off the
    flange; with ``rng`` both are jittered (±10 cm, ±10 deg)."""
    cam = CameraModel(K=[[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], width=width, height=height)
    eye, target = np.array([0.25, -0.75, 0.55]), np.array([0.25, 0.0, 0.2])
    R_lb = rodrigues([0.0, np.pi / 2, 0.0])
    t_lb = np.array([0.03, -0.1, 0.06])
    if rng is not None:
        eye = eye + rng.uniform(-0.1, 0.1, 3)
        R_lb = R_lb @ rodrigues(rng.normal(0, np.radians(10), 3))
        t_lb = t_lb + rng.uniform(-0.03, 0.03, 3)
    return Scene(cam, look_at(eye, target), make_T(R_lb, t_lb))


def random_board_poses(spec: BoardSpec, camera: CameraModel, n: int, rng: np.random.Generator,
                       dist_range: tuple[float, float] = (0.45, 0.85), max_tilt_deg: float = 40.0,
                       min_tilt_deg: float = 0.0) -> np.ndarray:
    """(n, 4, 4) ``T_cam_board``: the board centre at a random pixel in the middle 60 % of the
    image, at a random distance, facing the camera, tilted up to ``max_tilt_deg`` about a random
    in-plane axis, with a random roll of up to 180 deg; every corner inside the image."""
    out = []
    obj = spec.corners_3d()
    centre = np.array([spec.size_m[0] / 2, spec.size_m[1] / 2, 0.0])
    while len(out) < n:
        u = rng.uniform(0.2, 0.8) * camera.width
        v = rng.uniform(0.2, 0.8) * camera.height
        ray = camera.undistort_normalized(np.array([[u, v]]))[0]
        ray = np.array([ray[0], ray[1], 1.0])
        ray /= np.linalg.norm(ray)
        c = ray * rng.uniform(*dist_range)
        # board z points away from the camera (into the board): align it with the ray, then tilt and roll
        z = ray
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R0 = np.column_stack([x, np.cross(z, x), z])
        roll = rodrigues([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
        phi = rng.uniform(0, 2 * np.pi)
        tilt = rodrigues(np.array([np.cos(phi), np.sin(phi), 0.0]) * np.radians(rng.uniform(min_tilt_deg, max_tilt_deg)))
        R = R0 @ tilt @ roll
        T = make_T(R, c - R @ centre)
        px = camera.project(T, obj)
        m = 0.03 * min(camera.width, camera.height)
        if (px[:, 0] > m).all() and (px[:, 0] < camera.width - m).all() and (px[:, 1] > m).all() \
                and (px[:, 1] < camera.height - m).all():
            out.append(T)
    return np.stack(out)


def robot_poses_for(scene: Scene, T_cam_board: np.ndarray) -> np.ndarray:
    """``T_base_link`` (n, 4, 4) that put the board at ``T_cam_board`` (eye-to-hand)."""
    return scene.T_base_cam @ T_cam_board @ inv_T(scene.T_link_board)


# ----------------------------------------------------------------------------- synthetic episodes
Q_NOMINAL = np.array([0.0, 1.2, -1.0, 0.0, 0.6, 0.0])
"""A built-in PiPER configuration with the flange in front of the base, pointing forward-down."""
T_LINK6_BOARD = make_T(rodrigues([0.0, 0.0, 0.0]), np.array([-0.105, -0.075, 0.06]))
"""Board on the built-in PiPER's link6 for the synthetic episodes (printed face along -z_link6)."""


@dataclass
class EpisodeTruth:
    """What a synthetic episode was made with.

    Attributes:
        T_base_cam, T_link6_board: (4, 4) ground truth.
        camera: intrinsics.
        latency_s: the timestamp offset that was applied (t_frame = t_exposure + latency_s).
    """

    T_base_cam: np.ndarray
    T_link6_board: np.ndarray
    camera: CameraModel
    latency_s: float = 0.0


def _robot():
    from manisplat.robot import builtin_piper
    return builtin_piper(with_geometry=False)


def facing_camera(spec: BoardSpec, T_base_board: np.ndarray, distance: float = 0.6) -> np.ndarray:
    """``T_base_cam`` looking at the board centre straight along the board's z axis, from
    ``distance`` metres in front of its printed face."""
    centre = T_base_board[:3, :3] @ np.array([spec.size_m[0] / 2, spec.size_m[1] / 2, 0.0]) + T_base_board[:3, 3]
    z = T_base_board[:3, 2]
    return look_at(centre - distance * z, centre)


def _board_visible(spec: BoardSpec, camera: CameraModel, T_cam_board: np.ndarray, max_view_deg: float) -> bool:
    obj = spec.corners_3d()
    pc = obj @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
    if (pc[:, 2] < 0.1).any():
        return False
    view = np.degrees(np.arccos(np.clip(T_cam_board[:3, 2] @ (T_cam_board[:3, 3] / np.linalg.norm(T_cam_board[:3, 3])),
                                        -1, 1)))
    if view > max_view_deg:
        return False
    px = camera.project(T_cam_board, obj)
    m = 4.0
    return bool((px[:, 0] > m).all() and (px[:, 0] < camera.width - m).all() and (px[:, 1] > m).all()
                and (px[:, 1] < camera.height - m).all())


def sample_configurations(spec: BoardSpec, truth: EpisodeTruth, n: int, rng: np.random.Generator,
                          spread: np.ndarray = np.array([0.3, 0.25, 0.25, 0.6, 0.45, 0.9]),
                          single_axis: bool = False, max_view_deg: float = 55.0) -> np.ndarray:
    """(n, 6) joint vectors near :data:`Q_NOMINAL` with the whole board in view and facing the
    camera. ``single_axis``: only joint 6 moves (degenerate motion)."""
    robot = _robot()
    lo, hi = robot.lower, robot.upper
    out = []
    for _ in range(200 * n):
        dq = rng.uniform(-1, 1, 6) * spread
        if single_axis:
            dq[:5] = 0.0
        q = np.clip(Q_NOMINAL + dq, lo + 1e-3, hi - 1e-3)
        T_base_link6 = robot.link_pose(q, "link6").numpy()
        T_cam_board = inv_T(truth.T_base_cam) @ T_base_link6 @ truth.T_link6_board
        if _board_visible(spec, truth.camera, T_cam_board, max_view_deg):
            out.append(q)
            if len(out) == n:
                return np.stack(out)
    raise RuntimeError(f"sample_configurations: found only {len(out)} of {n} visible configurations")


def default_truth(spec: BoardSpec, width: int = 640, height: int = 480, f: float = 520.0,
                  distance: float = 0.55, latency_s: float = 0.0) -> EpisodeTruth:
    """A camera facing the board at :data:`Q_NOMINAL` from ``distance`` metres (slightly off-axis)."""
    robot = _robot()
    cam = CameraModel(K=[[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], width=width, height=height)
    T_base_board = robot.link_pose(Q_NOMINAL, "link6").numpy() @ T_LINK6_BOARD
    T_base_cam = facing_camera(spec, T_base_board, distance)
    T_base_cam = T_base_cam @ make_T(rodrigues([0.05, -0.08, 0.3]), np.zeros(3))  # a little off-axis and rolled
    return EpisodeTruth(T_base_cam, T_LINK6_BOARD.copy(), cam, latency_s)


def _camera_info(truth: EpisodeTruth):
    from manisplat.episode import CameraInfo
    c = truth.camera
    return CameraInfo(name="synthetic", width=c.width, height=c.height, K=c.K, dist=c.dist, mount="base")


def write_calibration_episode(path, spec: BoardSpec, truth: EpisodeTruth, q: np.ndarray, *,
                              rng: np.random.Generator, blur_sigma: float = 0.6, noise_std: float = 1.5,
                              supersample: int = 2, gt: bool = True) -> None:
    """A static-pose calibration episode (one frame per row of ``q`` (n, 6)) rendered with
    :func:`render_board`; ``gt.npz`` holds ``T_base_cam`` and ``T_link6_board``."""
    from manisplat.episode import EpisodeWriter, RobotInfo
    robot = _robot()
    with EpisodeWriter(path, _camera_info(truth), RobotInfo(), fps=2.0, source="simulation") as w:
        for k, qk in enumerate(q):
            T_cam_board = inv_T(truth.T_base_cam) @ robot.link_pose(qk, "link6").numpy() @ truth.T_link6_board
            g = render_board(spec, truth.camera, T_cam_board, supersample=supersample, blur_sigma=blur_sigma,
                             noise_std=noise_std, rng=rng)
            w.add_frame(0.5 * k, qk, 0.0, np.repeat(g[..., None], 3, axis=2))
    if gt:
        np.savez(f"{path}/gt.npz", T_base_cam=truth.T_base_cam, T_link6_board=truth.T_link6_board, K=truth.camera.K)


def min_jerk_trajectory(waypoints: np.ndarray, durations: np.ndarray, pauses: np.ndarray, rate: float
                        ) -> tuple[np.ndarray, np.ndarray]:
    """``(t, q)`` sampled at ``rate`` Hz: min-jerk moves between ``waypoints`` (n, 6), each
    move ``durations[k]`` s followed by a pause ``pauses[k]`` s."""
    ts, qs, t0 = [], [], 0.0
    for k in range(len(waypoints) - 1):
        total = durations[k] + pauses[k]
        tt = np.arange(int(round(total * rate))) / rate
        s = np.clip(tt / durations[k], 0, 1)
        s = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
        qs.append(waypoints[k] + s[:, None] * (waypoints[k + 1] - waypoints[k]))
        ts.append(t0 + tt)
        t0 += total
    return np.concatenate(ts), np.concatenate(qs)


def write_latency_episode(path, spec: BoardSpec, truth: EpisodeTruth, *, rng: np.random.Generator,
                          duration_s: float = 8.0, fps: float = 30.0, joint_rate: float = 200.0,
                          blur_sigma: float = 0.5, calibrated: bool = False,
                          move_s: tuple[float, float] = (0.4, 0.9), pause_s: tuple[float, float] = (0.05, 0.4),
                          spread: np.ndarray = np.array([0.2, 0.15, 0.15, 0.3, 0.3, 0.5])) -> None:
    """A moving episode: bursty min-jerk moves with pauses; frame ``k`` shows the scene at
    exposure time ``k / fps`` and is stamped ``k / fps + latency_s``; its frames.csv joints are
    interpolated at the stamped time (as a recorder does); joints.csv holds the true stream."""
    from manisplat.episode import EpisodeWriter, RobotInfo
    robot = _robot()
    n_moves = int(duration_s / (np.mean(move_s) + np.mean(pause_s))) + 2
    way = np.concatenate([Q_NOMINAL[None], sample_configurations(spec, truth, n_moves, rng, spread=spread)])
    t, q = min_jerk_trajectory(way, rng.uniform(*move_s, n_moves), rng.uniform(*pause_s, n_moves), joint_rate)
    t = t + 0.5  # the joint stream starts before the first frame
    t = np.concatenate([[0.0], t])
    q = np.concatenate([Q_NOMINAL[None], q])
    texture = cv2_background(truth.camera, rng)
    info = _camera_info(truth)
    if calibrated:
        info.T_mount_cam = truth.T_base_cam.copy()
    n_frames = int(min(duration_s, t[-1] - 1.0) * fps)
    with EpisodeWriter(path, info, RobotInfo(), fps=fps, source="simulation") as w:
        for ts, qs in zip(t, q):
            w.add_joint_sample(float(ts), qs, 0.0)
        for k in range(n_frames):
            t_exp = 0.6 + k / fps
            q_exp = np.array([np.interp(t_exp, t, q[:, j]) for j in range(6)])
            t_rec = t_exp + truth.latency_s
            q_rec = np.array([np.interp(t_rec, t, q[:, j]) for j in range(6)])
            T_cam_board = inv_T(truth.T_base_cam) @ robot.link_pose(q_exp, "link6").numpy() @ truth.T_link6_board
            g = render_board(spec, truth.camera, T_cam_board, supersample=2, blur_sigma=blur_sigma, background=texture,
                             noise_std=1.0, rng=rng)
            w.add_frame(t_rec, q_rec, 0.0, np.repeat(g[..., None], 3, axis=2))


def cv2_background(camera: CameraModel, rng: np.random.Generator) -> np.ndarray:
    """(H, W) float32 smooth random texture (a static scene behind the board)."""
    import cv2
    small = rng.uniform(40, 160, (camera.height // 16 + 1, camera.width // 16 + 1)).astype(np.float32)
    return cv2.resize(small, (camera.width, camera.height), interpolation=cv2.INTER_CUBIC)


def write_eye_in_hand_episode(path, spec: BoardSpec, n: int, rng: np.random.Generator, *, width: int = 640,
                              height: int = 480, f: float = 520.0) -> tuple[np.ndarray, np.ndarray]:
    """A static-pose eye-in-hand episode (camera on link6, board fixed in the base frame, mount
    ``"link6"``). Returns the truth ``(T_link6_cam, T_base_board)``."""
    from manisplat.episode import CameraInfo, EpisodeWriter, RobotInfo
    robot = _robot()
    cam = CameraModel(K=[[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], width=width, height=height)
    T_link6_cam = make_T(rodrigues([0.0, 0.0, np.pi / 2]) @ rodrigues([0.1, -0.05, 0.0]), [0.06, 0.0, 0.03])
    T_nom = robot.link_pose(Q_NOMINAL, "link6").numpy() @ T_link6_cam
    # the board 0.45 m in front of the nominal camera, facing it
    centre = T_nom[:3, 3] + 0.45 * T_nom[:3, 2]
    R_board = T_nom[:3, :3] @ rodrigues([0.0, 0.0, 0.3])
    T_base_board = make_T(R_board, centre - R_board @ np.array([spec.size_m[0] / 2, spec.size_m[1] / 2, 0.0]))
    qs, lo, hi = [], robot.lower, robot.upper
    spread = np.array([0.25, 0.2, 0.2, 0.5, 0.4, 0.8])
    for _ in range(400 * n):
        q = np.clip(Q_NOMINAL + rng.uniform(-1, 1, 6) * spread, lo + 1e-3, hi - 1e-3)
        T_cam_board = inv_T(robot.link_pose(q, "link6").numpy() @ T_link6_cam) @ T_base_board
        if _board_visible(spec, cam, T_cam_board, 55.0):
            qs.append((q, T_cam_board))
            if len(qs) == n:
                break
    if len(qs) < n:
        raise RuntimeError(f"write_eye_in_hand_episode: found only {len(qs)} of {n} visible configurations")
    info = CameraInfo(name="wrist", width=width, height=height, K=cam.K, mount="link6")
    with EpisodeWriter(path, info, RobotInfo(), fps=2.0, source="simulation") as w:
        for k, (q, T_cam_board) in enumerate(qs):
            g = render_board(spec, cam, T_cam_board, supersample=2, blur_sigma=0.6, noise_std=1.5, rng=rng)
            w.add_frame(0.5 * k, q, 0.0, np.repeat(g[..., None], 3, axis=2))
    return T_link6_cam, T_base_board
