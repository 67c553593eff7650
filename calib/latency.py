"""Camera latency: the constant offset between camera timestamps and joint timestamps.

``latency_s`` is defined by ``t_frame = t_exposure + latency_s``: a positive value means the
camera stamps frames late relative to the joint clock; the true exposure time of a frame is
``t - latency_s``.

Method: the image signal is the magnitude-weighted mean optical flow (Farneback, on frames
downscaled to ``flow_width`` px) between frames ``k`` and ``k + step`` for steps 1 and 2
(:func:`image_motion`): two baselines per frame, so each interval end is seen twice. The robot
signal for a candidate offset ``L`` is built from the displacements of points on the robot
between the times ``t_k - L`` and ``t_{k+step} - L`` (the same interval the flow covers, so no
midpoint approximation is needed): for every link frame and the TCP, a 3 x 3 x 3 grid of points
``LEVER_M`` apart around its origin, from FK of ``joints.csv`` including the gripper width. With
a calibrated camera (``K``, ``T_base_cam``) the points are projected and the displacements are
in pixels, otherwise in metres. Which parts of the robot the image sees (and how large) is
unknown, so the image signal is fitted as a non-negative combination of the per-point
displacement magnitudes plus a constant per step (NNLS): the flow magnitude of a rigid part is
close to a mixture of the magnitudes of points around it, which three points per axis
represent far better than one (on the 10 s benchmark the error fell from 2.4 to 0.6 ms).
``L`` maximises the fit's R^2 (the "correlation" reported is its square root): a 2 ms grid
over ``+-max_offset_s``, then a 0.2 ms grid +-3 ms around the best with a parabolic peak fit.
The uncertainty is the standard deviation over a moving-block bootstrap of the frame
intervals (blocks of about 1 s; each resample's peak on a 1 ms grid +-8 ms, refined the same
way). Episodes longer than ``max_span_s`` (30 s) are analysed over the window of that length
with the most variation of the image signal (where the timing information is), so time and
memory stay bounded (a 60 s clip: 34 s and 0.5 GB, against 69 s and 1 GB in full); 10-20 s
already meet 2 ms.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from scipy.optimize import nnls

from manisplat.calib.errors import CalibrationError, NotEnoughDataError
from manisplat.episode import Episode
from manisplat.robot import load_robot


LEVER_M = 0.1
"""Spacing of the 3 x 3 x 3 grid of robot points around each link origin, metres."""

FLOW_STEPS = (1, 2)
"""Frame baselines of the image signal: flow between frames ``k`` and ``k + step``."""

MAX_SPAN_S = 30.0
"""Longest stretch of an episode that is analysed, s (module docstring)."""


@dataclass
class LatencyEstimate:
    """Result of :func:`estimate_latency`.

    Attributes:
        latency_s: frame timestamp minus true exposure time, s.
        std_s: bootstrap 1-sigma, s.
        correlation: square root of the peak R^2 of the image-motion fit (0..1).
        intervals: frame intervals used.
        window_s: (first, last) frame time of the analysed stretch, s.
        signal: ``"pixels"`` (projected through the calibration) or ``"metres"``.
        offsets_s, scores: the coarse correlation curve (for the report).
    """

    latency_s: float
    std_s: float
    correlation: float
    intervals: int
    signal: str
    window_s: tuple[float, float]
    offsets_s: np.ndarray
    scores: np.ndarray

    def to_dict(self) -> dict:
        return {"latency_s": self.latency_s, "latency_std_s": self.std_s, "correlation": self.correlation,
                "intervals": self.intervals, "signal": self.signal, "window_s": list(self.window_s)}


def image_motion(frames: Iterable[np.ndarray], flow_width: int = 160,
                 steps: tuple[int, ...] = FLOW_STEPS) -> dict[int, np.ndarray]:
    """For each step, the (T-step,) magnitude-weighted mean optical flow ``sum |f|^2 / sum |f|``
    between frames ``k`` and ``k + step`` (pixels at ``flow_width``): the typical displacement
    of what moves, independent of how much of the image it covers (a plain mean would change
    with the robot's visible area). ``frames`` is consumed once (only ``max(steps)`` are kept)."""
    recent: deque[np.ndarray] = deque(maxlen=max(steps) + 1)
    out: dict[int, list[float]] = {step: [] for step in steps}
    for img in frames:
        g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
        scale = flow_width / g.shape[1]
        recent.append(cv2.resize(g, (flow_width, max(8, int(round(g.shape[0] * scale)))),
                                 interpolation=cv2.INTER_AREA))
        for step in steps:
            if len(recent) > step:
                flow = cv2.calcOpticalFlowFarneback(recent[-1 - step], recent[-1], None, 0.5, 3, 15, 3, 5, 1.2, 0)
                mag = np.linalg.norm(flow, axis=2)
                out[step].append(float(np.sum(mag ** 2) / (np.sum(mag) + 1e-9)))
    return {step: np.asarray(values) for step, values in out.items()}


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
                 scale: float = 1.0, chunk: int = 2048) -> tuple[RobotMotion, str]:
    """The robot's point trajectories of an episode's ``joints.csv`` (or ``frames.csv`` if it
    has none), fingers at the recorded gripper width; pixels (times ``scale``) when ``K`` and
    ``T_base_cam`` are given. Computed ``chunk`` samples at a time (bounded temporaries)."""
    joints = ep.joints()
    source = joints if joints is not None else ep.frames
    t, q, width = source.t, source.q, source.gripper
    robot = load_robot(ep.meta.robot.description, base_dir=ep.path, load_meshes=False)
    width = None if robot.gripper is None else np.clip(width, *robot.gripper.width_range)
    axis = np.array([-LEVER_M, 0.0, LEVER_M])
    offsets = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)  # [27, 3]
    projected = K is not None and T_base_cam is not None
    T_cam_base = np.linalg.inv(T_base_cam) if projected else np.eye(4)
    out = None
    for a in range(0, len(q), chunk):
        b = min(a + chunk, len(q))
        poses = robot.forward_kinematics(q[a:b], None if width is None else width[a:b]).numpy()  # [n, L, 4, 4]
        tcp = robot.tcp_pose(q[a:b]).numpy()[:, None]
        frames = np.concatenate([poses[:, 1:], tcp], axis=1)  # skip the base link
        pts = np.einsum("nlij,pj->nlpi", frames[:, :, :3, :3], offsets) + frames[:, :, None, :3, 3]
        pts = pts.reshape(b - a, -1, 3)  # [n, 27 L, 3]
        if projected:
            pc = pts @ T_cam_base[:3, :3].T + T_cam_base[:3, 3]
            z = np.maximum(pc[..., 2:3], 1e-3)
            pts = ((pc[..., :2] / z) * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]) * scale
        if out is None:
            out = np.empty((len(q), *pts.shape[1:]))
        out[a:b] = pts
    return RobotMotion(t, out), "pixels" if projected else "metres"


@dataclass
class _Rows:
    """The fit's rows for one flow step: interval ends ``t0, t1`` (s), image signal ``s`` and
    the index of each interval's first frame (for the block bootstrap), all (K,)."""

    t0: np.ndarray
    t1: np.ndarray
    s: np.ndarray
    start: np.ndarray


def _designs(robot: RobotMotion, rows: list[_Rows], offset_s: float) -> list[np.ndarray]:
    """Per step, the (K, M) point displacements over each interval shifted by ``-offset_s``."""
    return [robot.displacement(r.t0 - offset_s, r.t1 - offset_s) for r in rows]


def _r2(designs: list[np.ndarray], signals: list[np.ndarray]) -> float:
    """R^2 of the NNLS fit ``s ~ D @ a + b_step`` (a >= 0, one constant per step), stacked."""
    A = np.concatenate([D - D.mean(axis=0) for D in designs])
    x = np.concatenate([s - s.mean() for s in signals])
    ss = float(x @ x)
    norms = np.linalg.norm(A, axis=0)
    keep = norms > 1e-12
    if ss <= 0 or not keep.any():
        return 0.0
    _, rnorm = nnls(A[:, keep] / norms[keep], x)
    return 1.0 - rnorm ** 2 / ss


def _scores(robot: RobotMotion, rows: list[_Rows], offsets: np.ndarray) -> np.ndarray:
    return np.array([_r2(_designs(robot, rows, L), [r.s for r in rows]) for L in offsets])


def _peak(offsets: np.ndarray, scores: np.ndarray) -> float:
    """Offset of the maximum, refined by a parabola through it and its neighbours."""
    k = int(np.argmax(scores))
    if 0 < k < len(scores) - 1:
        y0, y1, y2 = scores[k - 1], scores[k], scores[k + 1]
        den = y0 - 2 * y1 + y2
        if den < 0:
            return float(offsets[k] + 0.5 * (y0 - y2) / den * (offsets[1] - offsets[0]))
    return float(offsets[k])


def _bootstrap_std(robot: RobotMotion, rows: list[_Rows], latency: float, n_frames: int, dt: float,
                   resamples: int, seed: int) -> float:
    """Standard deviation of the peak over a moving-block bootstrap of the frame intervals
    (blocks of about 1 s of first frames; every step's rows that start there come along)."""
    local = latency + np.arange(-0.008, 0.008 + 1e-12, 0.001)
    designs = [_designs(robot, rows, L) for L in local]
    position = []  # per step: frame index -> row, or -1
    for r in rows:
        pos = np.full(n_frames, -1)
        pos[r.start] = np.arange(len(r.start))
        position.append(pos)
    first = np.unique(np.concatenate([r.start for r in rows]))
    n = len(first)
    block = int(max(2, min(n // 4, round(1.0 / max(dt, 1e-3)))))
    rng = np.random.default_rng(seed)
    peaks = []
    for _ in range(resamples):
        starts = rng.integers(0, n - block + 1, size=int(np.ceil(n / block)))
        frames = first[np.concatenate([np.arange(a, a + block) for a in starts])[:n]]
        select = [pos[frames][pos[frames] >= 0] for pos in position]
        signals = [r.s[sel] for r, sel in zip(rows, select)]
        scores = [_r2([D[sel] for D, sel in zip(ds, select)], signals) for ds in designs]
        peaks.append(_peak(local, np.array(scores)))
    return float(np.std(peaks))


def _busiest_window(t: np.ndarray, s: np.ndarray, span_s: float) -> tuple[float, float]:
    """(start, end) of the ``span_s`` stretch of frame times ``t`` (T,) over which the step-1
    image signal ``s`` (T-1,) varies most (sum of ``|s[k+1] - s[k]|``); all of ``t`` if shorter."""
    if t[-1] - t[0] <= span_s:
        return float(t[0]), float(t[-1])
    # variation[k]: the changes between intervals that both end by frame k  (T,)
    variation = np.concatenate([[0.0, 0.0], np.cumsum(np.abs(np.diff(s)))])
    end = np.searchsorted(t, t + span_s, side="right") - 1  # last frame of the window from each frame
    score = variation[end] - variation[np.minimum(np.arange(len(t)) + 1, len(t) - 1)]
    first = int(np.argmax(np.where(t + span_s <= t[-1], score, -np.inf)))
    return float(t[first]), float(t[first] + span_s)


def fit_latency(t_frames: np.ndarray, motion_img: Mapping[int, np.ndarray] | np.ndarray, robot: RobotMotion,
                signal: str = "metres", max_offset_s: float = 0.25, bootstrap: int = 100,
                seed: int = 0, max_span_s: float = MAX_SPAN_S) -> LatencyEstimate:
    """Fit the offset between image-motion signals and the robot (module docstring).

    Args:
        t_frames: (T,) frame timestamps, s.
        motion_img: ``{step: (T-step,) signal}`` as :func:`image_motion` returns it, or one
            (T-1,) array for step 1.
        robot: the robot's point trajectories on the joint clock.
        max_span_s: longest stretch analysed (module docstring).

    Raises:
        NotEnoughDataError: fewer than 8 intervals, or no motion in either signal.
    """
    t_frames = np.asarray(t_frames, dtype=np.float64)
    signals = {1: motion_img} if isinstance(motion_img, np.ndarray) else dict(motion_img)
    rows, window = [], None
    for step, values in sorted(signals.items()):
        s = np.asarray(values, dtype=np.float64)
        if s.shape != (len(t_frames) - step,) or len(s) < 8:
            raise NotEnoughDataError(f"latency needs at least 9 frames with their image motion; got "
                                     f"{len(t_frames)} frames and {len(s)} values for step {step}")
        if not np.isfinite(s).all():
            raise NotEnoughDataError(f"latency: the image motion for step {step} is not finite")
        if window is None:  # from the smallest step
            covered = (t_frames - max_offset_s >= robot.t[0]) & (t_frames + max_offset_s <= robot.t[-1])
            idx = np.flatnonzero(covered)
            window = ((float(t_frames[0]), float(t_frames[0])) if len(idx) < 2 else
                      _busiest_window(t_frames[idx[0]:idx[-1] + 1], s[idx[0]:idx[-1]], max_span_s))
        t0, t1 = t_frames[:-step], t_frames[step:]
        inside = np.flatnonzero((t0 - max_offset_s >= robot.t[0]) & (t1 + max_offset_s <= robot.t[-1])
                                & (t0 >= window[0]) & (t1 <= window[1]))
        rows.append(_Rows(t0[inside], t1[inside], s[inside], inside))
    if not rows or np.std(np.concatenate([r.s for r in rows])) <= 1e-9:
        raise NotEnoughDataError("latency: the images show no motion (or the motion is constant): nothing to align")
    if len(rows[0].s) < 8:
        raise NotEnoughDataError(f"latency: only {len(rows[0].s)} frame intervals lie within the joint stream "
                                 f"+-{max_offset_s} s")
    rows = [r for r in rows if len(r.s) >= 8]
    coarse = np.arange(-max_offset_s, max_offset_s + 1e-12, 0.002)
    if max(np.std(D) for D in _designs(robot, rows, 0.0)) <= 1e-12:
        raise NotEnoughDataError("latency: the robot does not move during the episode: nothing to align")
    scores = _scores(robot, rows, coarse)
    best = float(coarse[int(np.argmax(scores))])
    fine = np.arange(best - 0.003, best + 0.003 + 1e-12, 0.0002)
    fine_scores = _scores(robot, rows, fine)
    latency = _peak(fine, fine_scores)
    dt = float(np.median(np.diff(t_frames)))
    std = _bootstrap_std(robot, rows, latency, len(t_frames), dt, bootstrap, seed)
    if not (np.isfinite(latency) and np.isfinite(std)):
        raise CalibrationError("latency: the fit produced a non-finite value")
    if abs(latency) >= max_offset_s - 0.002:
        raise CalibrationError(f"latency: the best offset {latency * 1000:.1f} ms is at the edge of the search range "
                               f"+-{max_offset_s * 1000:.0f} ms; widen it (--max-offset)")
    peak = float(np.sqrt(max(fine_scores.max(), 0.0)))
    return LatencyEstimate(latency, std, peak, len(rows[0].s), signal, window, coarse, scores)


def estimate_latency(path, *, use_calibration: bool = True, flow_width: int = 160, max_offset_s: float = 0.25,
                     bootstrap: int = 100, max_span_s: float = MAX_SPAN_S) -> LatencyEstimate:
    """Latency of an episode (module docstring). With ``use_calibration`` and an episode whose
    camera is calibrated and fixed to the base, the robot signal is in pixels."""
    ep = Episode.open(path)
    if len(ep) < 9:
        raise NotEnoughDataError(f"{path}: latency needs at least 9 frames; got {len(ep)}")
    s = image_motion((ep.rgb(i) for i in range(len(ep))), flow_width)
    cam = ep.camera
    calibrated = use_calibration and cam.mount == "base" and cam.T_mount_cam is not None
    motion, signal = robot_motion(ep, cam.K if calibrated else None, cam.T_mount_cam if calibrated else None,
                                  scale=flow_width / cam.width)
    return fit_latency(ep.frames.t, s, motion, signal, max_offset_s, bootstrap, max_span_s=max_span_s)
