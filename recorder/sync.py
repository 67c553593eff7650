"""The joint state at each camera frame's time, by interpolation between the joint samples
around it, and the two ways most recorders do it instead (for comparison).

Rules of :func:`sync_joints` (all times on one monotonic timeline, s):
* A frame at ``t`` between two samples ``t_a <= t <= t_b`` gets the linear interpolation of the
  two (:func:`manisplat.geometry.interpolate_joints`), and ``gap = t_b - t_a``. When the gap is
  longer than ``max_gap_s`` the value is still the interpolation but the frame is flagged
  :data:`FLAG_GAP` (the arm may have moved in any way during a dropout).
* A frame after the last sample is never extrapolated: it gets the last sample, flagged
  :data:`FLAG_HELD`, ``gap`` = its distance from that sample. A frame before the first sample
  gets the first one, flagged :data:`FLAG_BEFORE`.

``flags`` is a bit mask (the ``sync_flags`` column of ``frames.csv``); 0 means a trustworthy
interpolation. :data:`FLAG_ACTION_STALE` is used by the action columns (:mod:`.actions`).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import torch

from manisplat.geometry import interpolate_joints

FLAG_GAP = 1
"""Interpolated across a gap between joint samples longer than ``max_gap_s``."""
FLAG_HELD = 2
"""No joint sample after the frame: the last state is repeated (not extrapolated)."""
FLAG_BEFORE = 4
"""No joint sample before the frame: the first state is repeated."""
FLAG_ACTION_STALE = 8
"""No leader-arm command within ``max_action_age_s`` before the frame (actions hold the state)."""

FLAG_NAMES = {FLAG_GAP: "gap", FLAG_HELD: "held", FLAG_BEFORE: "before_first", FLAG_ACTION_STALE: "action_stale"}


@dataclass(frozen=True)
class SyncResult:
    """Joint values at frame times.

    Attributes:
        values: (M, D) float64 (q1..q6 rad, gripper m, ...).
        gap: (M,) s: the interval interpolated across (or the distance to the repeated sample).
        flags: (M,) int bit mask (module docstring).
    """

    values: np.ndarray
    gap: np.ndarray
    flags: np.ndarray


def sync_joints(joint_t: np.ndarray, joint_v: np.ndarray, frame_t: np.ndarray, max_gap_s: float) -> SyncResult:
    """Joint values ``joint_v`` (N, D) sampled at strictly increasing ``joint_t`` (N,) at the
    frame times ``frame_t`` (M,), by the module's rules. Raises ValueError without samples."""
    joint_t = np.asarray(joint_t, dtype=np.float64)
    joint_v = np.asarray(joint_v, dtype=np.float64)
    frame_t = np.atleast_1d(np.asarray(frame_t, dtype=np.float64))
    if joint_t.ndim != 1 or len(joint_t) == 0 or joint_v.shape[0] != len(joint_t) or joint_v.ndim != 2:
        raise ValueError(f"need joint samples t (N,) and values (N, D), N >= 1; got {joint_t.shape}, {joint_v.shape}")
    m, d = len(frame_t), joint_v.shape[1]
    values = np.empty((m, d))
    gap = np.zeros(m)
    flags = np.zeros(m, dtype=np.int64)
    before = frame_t < joint_t[0]
    after = frame_t > joint_t[-1]
    inside = ~(before | after)
    if inside.any():
        res = interpolate_joints(torch.from_numpy(joint_t), torch.from_numpy(joint_v),
                                 torch.from_numpy(frame_t[inside]))
        values[inside] = res.values.numpy()
        gap[inside] = res.gap.numpy()
        flags[inside] = np.where(gap[inside] > max_gap_s, FLAG_GAP, 0)
    values[before] = joint_v[0]
    gap[before] = joint_t[0] - frame_t[before]
    flags[before] = FLAG_BEFORE
    values[after] = joint_v[-1]
    gap[after] = frame_t[after] - joint_t[-1]
    flags[after] = FLAG_HELD
    return SyncResult(values, gap, flags)


def nearest_sample(joint_t: np.ndarray, joint_v: np.ndarray, frame_t: np.ndarray) -> np.ndarray:
    """Baseline: the sample nearest in time to each frame (M, D)."""
    joint_t = np.asarray(joint_t, dtype=np.float64)
    frame_t = np.asarray(frame_t, dtype=np.float64)
    upper = np.clip(np.searchsorted(joint_t, frame_t), 1, len(joint_t) - 1)
    lower = upper - 1
    pick = np.where(np.abs(frame_t - joint_t[lower]) <= np.abs(joint_t[upper] - frame_t), lower, upper)
    return np.asarray(joint_v)[pick]


def latest_at_arrival(joint_arrival: np.ndarray, joint_v: np.ndarray, frame_arrival: np.ndarray) -> np.ndarray:
    """Baseline (what most recorders do): the latest sample this host had received when the
    frame reached it (both times on the host's clock); the first sample before any."""
    i = np.searchsorted(np.asarray(joint_arrival, dtype=np.float64), np.asarray(frame_arrival, dtype=np.float64),
                        side="right") - 1
    return np.asarray(joint_v)[np.clip(i, 0, len(joint_v) - 1)]


class JointHistory:
    """The recent joint samples (time on the monotonic timeline and a value vector), appended by
    a reader thread and searched by the recording loop. Old samples are dropped beyond
    ``capacity``; a sample not after the previous one is refused.

    Args:
        dims: values per sample (7: q1..q6, gripper).
        capacity: samples kept (8192 = 41 s at 200 Hz).
    """

    def __init__(self, dims: int = 7, capacity: int = 8192) -> None:
        self._t = np.empty(2 * capacity)
        self._v = np.empty((2 * capacity, dims))
        self._start = 0
        self._end = 0
        self.capacity = capacity
        self._lock = threading.Lock()
        self.refused = 0

    def __len__(self) -> int:
        return self._end - self._start

    def append(self, t: float, value: np.ndarray) -> bool:
        """Add one sample; False (and counted in ``refused``) when ``t`` is not after the last."""
        with self._lock:
            if self._end > self._start and not t > self._t[self._end - 1]:
                self.refused += 1
                return False
            if self._end == len(self._t):  # end of the buffer: move the kept samples to its front
                n = self._end - self._start
                self._t[:n] = self._t[self._start:self._end]
                self._v[:n] = self._v[self._start:self._end]
                self._start, self._end = 0, n
            self._t[self._end] = t
            self._v[self._end] = value
            self._end += 1
            if self._end - self._start > self.capacity:
                self._start = self._end - self.capacity
            return True

    def clear(self) -> None:
        """Forget every sample (e.g. when the timeline they were mapped onto was wrong)."""
        with self._lock:
            self._start = self._end = 0

    @property
    def last_t(self) -> float | None:
        """Time of the newest sample (None when empty)."""
        with self._lock:
            return float(self._t[self._end - 1]) if self._end > self._start else None

    @property
    def first_t(self) -> float | None:
        with self._lock:
            return float(self._t[self._start]) if self._end > self._start else None

    def around(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the (at most two) samples bracketing ``t``: the last at or before it and
        the first after it (one of them alone at the ends; empty arrays when empty)."""
        with self._lock:
            times = self._t[self._start:self._end]
            k = int(np.searchsorted(times, t, side="right"))
            lo, hi = max(k - 1, 0), min(k + 1, len(times))
            return times[lo:hi].copy(), self._v[self._start + lo:self._start + hi].copy()

    def since(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the samples at or after ``t``: times (K,) and values (K, D)."""
        with self._lock:
            times = self._t[self._start:self._end]
            k = self._start + int(np.searchsorted(times, t, side="left"))
            return self._t[k:self._end].copy(), self._v[k:self._end].copy()

    def latest(self) -> tuple[float, np.ndarray] | None:
        with self._lock:
            if self._end == self._start:
                return None
            return float(self._t[self._end - 1]), self._v[self._end - 1].copy()

    def sync(self, t: float, max_gap_s: float) -> tuple[np.ndarray, float, int] | None:
        """``(values, gap, flags)`` at ``t`` by :func:`sync_joints`, or None when no sample exists."""
        times, values = self.around(t)
        if len(times) == 0:
            return None
        r = sync_joints(times, values, np.array([t]), max_gap_s)
        return r.values[0], float(r.gap[0]), int(r.flags[0])
