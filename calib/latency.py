"""Camera latency: the constant offset between camera timestamps and joint timestamps.

``latency_s`` is defined by ``t_frame = t_exposure + latency_s``: a positive value means the
camera stamps frames late relative to the joint clock; the true exposure time of a frame is
``t - latency_s``.

Method: the image signal is the magnitude-weighted mean optical flow (Farneback, on frames
downscaled to ``flow_width`` px) between consecutive frames ``k, k+1`` (:func:`image_motion`). The robot signal for a candidate
offset ``L`` is built from the displacements of points on the robot (every link origin and the
TCP, each with three points 0.1 m along its axes, from FK of ``joints.csv``) between the times ``t_k - L`` and ``t_{k+1} - L``: the same
interval the flow covers, so no midpoint approximation is needed. With a calibrated camera
(``K``, ``T_base_cam``) the points are projected and the displacements are in pixels, otherwise
in metres. Which parts of the robot the image sees (and how large) is unknown, so the image
signal is fitted as a non-negative combination of the per-point displacements plus a constant
(NNLS); ``L`` maximises the fit's R^2 (the "correlation" reported is its square root): a 1 ms
grid over ``+-max_offset_s``, then a 0.1 ms grid +-3 ms around the best with a parabolic peak
fit. The
uncertainty is the standard deviation over a moving-block bootstrap of the frame intervals
(blocks of about 1 s, 200 resamples).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from scipy.optimize import nnls

from manisplat.calib.errors import CalibrationError, NotEnoughDataError
from manisplat.episode import Episode
from manisplat.robot import load_robot


LEVER_M = 0.1
"""Distance of the extra robot points from each link origin along the link's axes, metres."""


@dataclass
class LatencyEstimate:
    """Result of :func:`estimate_latency`.

    Attributes:
        latency_s: frame timestamp minus true exposure time, s.
        std_s: bootstrap 1-sigma, s.
        correlation: square root of the peak R^2 of the image-motion fit (0..1).
        intervals: frame intervals used.
        signal: ``"pixels"`` (projected through the calibration) or ``"metres"``.
        offsets_s, scores: the coarse correlation curve (for the report).
    """

    latency_s: float
    std_s: float
    correlation: float
    intervals: int
    signal: str
    offsets_s: np.ndarray
    scores: np.ndarray

    def to_dict(self) -> dict:
        return {"latency_s": self.latency_s, "latency_std_s": self.std_s, "correlation": self.correlation,
                "intervals": self.intervals, "signal": self.signal}


def image_motion(frames: list[np.ndarray] | np.ndarray, flow_width: int = 160) -> np.ndarray:
    """(T-1,) magnitude-weighted mean optical flow ``sum |f|^2 / sum |f|`` between consecutive
    frames (pixels at ``flow_width``): the typical displacement of what moves, independent of
    how much of the image it covers (a plain mean would change with the robot's visible area)."""
    out, prev = [], None
    for img in frames:
        g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
        scale = flow_width / g.shape[1]
        g = cv2.resize(g, (flow_width, max(8, int(round(g.shape[0] * scale)))), interpolation=cv2.INTER_AREA)
        if prev is not None:
            flow = cv2.calcOpticalFlowFarneback(prev, g, None, 0.5, 3, 15, 3, 5, 1.2, 0)
            mag = np.linalg.norm(flow, axis=2)
            out.append(float(np.sum(mag ** 2) / (np.sum(mag) + 1e-9)))
        prev = g
    return np.asarray(out)


class RobotMotion:
    """Trajectories of points on the robot, from FK of a joint stream, interpolated in time.

    Args:
        t: (N,) joint sample times, s (increasing).
        points: (N, M, D) point coordinates (D = 3 metres, or 2 pixels).
    """

    def __init__(self, t: np.ndarray, points: np.ndarray) -> None:
        self.t = np.asarray(t, dtype=np.float64)
        self.points = np.asarray(points, dtype=np.float64)
        if len(self.t) < 4 or not np.all(np.diff(self.t) > 0):
            raise CalibrationError("latency: joints.csv needs at least 4 samples with increasing t")
        self._flat = self.points.reshape(len(self.t), -1)

    def at(self, times: np.ndarray) -> np.ndarray:
        """(len(times), M, D) points at ``times`` (linear interpolation, clamped at the ends)."""
        idx = np.clip(np.searchsorted(self.t, times) - 1, 0, len(self.t) - 2)
        w = np.clip((times - self.t[idx]) / (self.t[idx + 1] - self.t[idx]), 0.0, 1.0)[:, None]
        flat = self._flat[idx] * (1 - w) + self._flat[idx + 1] * w
        return flat.reshape(len(times), *self.points.shape[1:])

    def displacement(self, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
        """(K, M) displacement of every point between times ``t0`` and ``t1`` (K,)."""
        return np.linalg.norm(self.at(t1) - self.at(t0), axis=-1)


def robot_motion(ep: Episode, K: np.ndarray | None = None, T_base_cam: np.ndarray | None = None,
                 scale: float = 1.0) -> tuple[RobotMotion, str]:
    """The robot's point trajectories of an episode's ``joints.csv`` (or ``frames.csv`` if it
    has none); pixels (times ``scale``) when ``K`` and ``T_base_cam`` are given."""
    joints = ep.joints()
    t, q = (joints.t, joints.q) if joints is not None else (ep.frames.t, ep.frames.q)
    robot = load_robot(ep.meta.robot.description, base_dir=ep.path, load_meshes=False)
    poses = robot.forward_kinematics(q).numpy()  # [N, L, 4, 4]
    tcp = robot.tcp_pose(q).numpy()[:, None]
    frames = np.concatenate([poses[:, 1:], tcp], axis=1)  # skip the base link  [N, L, 4, 4]
    # each frame's origin and three points LEVER_M along its axes, so rotations show too
    offsets = np.concatenate([np.zeros((1, 3)), LEVER_M * np.eye(3)])  # [4, 3]
    pts = (frames[:, :, None, :3, :3] @ offsets[None, None, :, :, None])[..., 0] + frames[:, :, None, :3, 3]
    pts = pts.reshape(len(q), -1, 3)  # [N, 4L, 3]
    if K is None or T_base_cam is None:
        return RobotMotion(t, pts), "metres"
    T_cam_base = np.linalg.inv(T_base_cam)
    pc = pts @ T_cam_base[:3, :3].T + T_cam_base[:3, 3]
    z = np.maximum(pc[..., 2:3], 1e-3)
    uv = (pc[..., :2] / z) * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
    return RobotMotion(t, uv * scale), "pixels"


def _fit_scores(D: np.ndarray, s: np.ndarray) -> np.ndarray:
    """R^2 of the NNLS fit ``s ~ D[i] @ a + b`` (a >= 0) for each offset i; D (n_L, K, M), s (K,)."""
    sc = s - s.mean()
    ss = float(sc @ sc)
    out = np.zeros(len(D))
    for i, Di in enumerate(D):
        Dc = Di - Di.mean(axis=0)
        norms = np.linalg.norm(Dc, axis=0)
        if not (norms > 1e-12).any():
            continue
        Dn = Dc[:, norms > 1e-12] / norms[norms > 1e-12]
        _, rnorm = nnls(Dn, sc)
        out[i] = 1.0 - rnorm ** 2 / ss if ss > 0 else 0.0
    return out


def _peak(offsets: np.ndarray, scores: np.ndarray) -> float:
    """Offset of the maximum, refined by a parabola through it and its neighbours."""
    k = int(np.argmax(scores))
    if 0 < k < len(scores) - 1:
        y0, y1, y2 = scores[k - 1], scores[k], scores[k + 1]
        den = y0 - 2 * y1 + y2
        if den < 0:
            return float(offsets[k] + 0.5 * (y0 - y2) / den * (offsets[1] - offsets[0]))
    return float(offsets[k])


def fit_latency(t_frames: np.ndarray, motion_img: np.ndarray, robot: RobotMotion, signal: str = "metres",
                max_offset_s: float = 0.25, bootstrap: int = 200, seed: int = 0) -> LatencyEstimate:
    """Fit the offset between an image-motion signal (T-1,) over frame intervals and the robot.

    Raises:
        NotEnoughDataError: fewer than 8 intervals, or no motion in either signal.
    """
    t_frames = np.asarray(t_frames, dtype=np.float64)
    s = np.asarray(motion_img, dtype=np.float64)
    if len(s) != len(t_frames) - 1 or len(s) < 8:
        raise NotEnoughDataError(f"latency needs at least 9 frames with their image motion; got {len(t_frames)}")
    if not np.isfinite(s).all() or np.std(s) <= 1e-9:
        raise NotEnoughDataError("latency: the images show no motion (or the motion is constant): nothing to align")
    t0, t1 = t_frames[:-1], t_frames[1:]
    inside = (t0 - max_offset_s >= robot.t[0]) & (t1 + max_offset_s <= robot.t[-1])
    if inside.sum() < 8:
        raise NotEnoughDataError(f"latency: only {int(inside.sum())} frame intervals lie within the joint stream "
                                 f"+-{max_offset_s} s")
    t0, t1, s = t0[inside], t1[inside], s[inside]
    coarse = np.arange(-max_offset_s, max_offset_s + 1e-12, 0.001)
    D = np.stack([robot.displacement(t0 - L, t1 - L) for L in coarse])
    if np.std(D) <= 1e-12:
        raise NotEnoughDataError("latency: the robot does not move during the episode: nothing to align")
    scores = _fit_scores(D, s)
    best = float(coarse[int(np.argmax(scores))])
    fine = np.arange(best - 0.003, best + 0.003 + 1e-12, 0.0001)
    Df = np.stack([robot.displacement(t0 - L, t1 - L) for L in fine])
    fs = _fit_scores(Df, s)
    latency = _peak(fine, fs)
    # moving-block bootstrap over intervals (blocks of ~1 s); local grid around the estimate
    rng = np.random.default_rng(seed)
    n = len(s)
    dt = float(np.median(np.diff(t_frames)))
    block = int(max(2, min(n // 4, round(1.0 / max(dt, 1e-3)))))
    local = np.arange(latency - 0.02, latency + 0.02 + 1e-12, 0.0005)
    Dl = np.stack([robot.displacement(t0 - L, t1 - L) for L in local])
    boots = []
    starts_max = n - block
    for _ in range(bootstrap):
        starts = rng.integers(0, starts_max + 1, size=int(np.ceil(n / block)))
        idx = np.concatenate([np.arange(a, a + block) for a in starts])[:n]
        boots.append(_peak(local, _fit_scores(Dl[:, idx], s[idx])))
    std = float(np.std(boots))
    peak = float(np.sqrt(max(fs.max(), 0.0)))
    if not (np.isfinite(latency) and np.isfinite(std)):
        raise CalibrationError("latency: the fit produced a non-finite value")
    if abs(latency) >= max_offset_s - 0.002:
        raise CalibrationError(f"latency: the best offset {latency * 1000:.1f} ms is at the edge of the search range "
                               f"+-{max_offset_s * 1000:.0f} ms; widen it (--max-offset)")
    return LatencyEstimate(latency, std, peak, n, signal, coarse, scores)


def estimate_latency(path, *, use_calibration: bool = True, flow_width: int = 160, max_offset_s: float = 0.25,
                     bootstrap: int = 200) -> LatencyEstimate:
    """Latency of an episode (module docstring). With ``use_calibration`` and an episode whose
    camera is calibrated and fixed to the base, the robot signal is in pixels."""
    ep = Episode.open(path)
    if len(ep) < 9:
        raise NotEnoughDataError(f"{path}: latency needs at least 9 frames; got {len(ep)}")
    frames = [ep.rgb(i) for i in range(len(ep))]
    s = image_motion(frames, flow_width)
    cam = ep.camera
    calibrated = use_calibration and cam.mount == "base" and cam.T_mount_cam is not None
    motion, signal = robot_motion(ep, cam.K if calibrated else None, cam.T_mount_cam if calibrated else None,
                                  scale=flow_width / cam.width)
    return fit_latency(ep.frames.t, s, motion, signal, max_offset_s, bootstrap)
