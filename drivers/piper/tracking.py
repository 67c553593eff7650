"""What a replay reports: the outcome, and how each arm tracked its targets (joints and gripper).

:func:`tracking_of` compares the feedback with the targets streamed (both on the host clock):
the error against the target in effect when each feedback sample arrived, and again after removing
the best constant lag (the MOVE J planner follows with a delay). Angles in degrees, openings in
metres (millimetres where the name says so).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Tracking:
    """Tracking error of the streamed part, deg per joint.

    Attributes:
        max_deg, rms_deg: (6,) against the target in effect when each feedback sample arrived.
        lag_s: the constant delay that best explains the error (0..0.5 s).
        lag_rms_deg, lag_max_deg: (6,) what remains after removing that delay.
        gripper: the gripper's own account (its moves are not tracking error).
        samples: feedback samples compared.
    """

    max_deg: np.ndarray
    rms_deg: np.ndarray
    lag_s: float
    lag_rms_deg: np.ndarray
    lag_max_deg: np.ndarray
    gripper: GripperTracking
    samples: int


GRIPPER_SETTLE_S = 0.5  # the gripper crosses its whole 70 mm range in about this time
GRIPPER_BLOCKED_MM = 2.0


@dataclass
class GripperTracking:
    """How the gripper followed its targets once each open or close had time to finish.

    Attributes:
        settled_max_mm: the largest error GRIPPER_SETTLE_S s or more after a target change,
            where nothing stopped the fingers (0 with no such sample).
        held_mm: the widest opening at which it held something it was told to close on (the fingers
            stopped short of the target by more than GRIPPER_BLOCKED_MM), or None.
    """

    settled_max_mm: float
    held_mm: float | None

    @classmethod
    def of(cls, sent_t: np.ndarray, sent_g: np.ndarray, fb_t: np.ndarray, fb_g: np.ndarray) -> GripperTracking:
        """From the targets sent (times s, openings m) and the feedback (times s, openings m, NaN: none)."""
        ok = np.isfinite(fb_g)
        t, measured = fb_t[ok], fb_g[ok] * 1e3
        changed = np.r_[True, np.abs(np.diff(sent_g)) > 1e-4]
        change_t = sent_t[changed]
        k = np.clip(np.searchsorted(sent_t, t, side="right") - 1, 0, len(sent_t) - 1)
        target = sent_g[k] * 1e3
        since = t - change_t[np.clip(np.searchsorted(change_t, t, side="right") - 1, 0, len(change_t) - 1)]
        settled = since >= GRIPPER_SETTLE_S
        blocked = settled & (measured > target + GRIPPER_BLOCKED_MM)
        free = settled & ~blocked
        return cls(float(np.abs(measured - target)[free].max()) if free.any() else 0.0,
                   float(measured[blocked].max()) if blocked.any() else None)

    def __str__(self) -> str:
        text = f"gripper within {self.settled_max_mm:.2f} mm of its targets {GRIPPER_SETTLE_S:g} s after each change"
        return text + (f"; held something at {self.held_mm:.1f} mm when told to close" if self.held_mm else "")


@dataclass
class ReplayReport:
    """The outcome of :func:`replay`.

    Attributes:
        outcome: ``"completed"``, ``"tracking_error"``, ``"feedback_lost"``, ``"interrupted"``
            or ``"error"``.
        detail: a sentence.
        left: how the arm was left.
        planned_s: the trajectory's duration; streamed_s: how much of it was streamed.
        approach_s: duration of the move to the start.
        ticks: targets streamed; late_ticks: ticks more than two periods late (skipped ahead).
        streamed_at_s: (ticks,) the trajectory time each streamed target was sampled at, s: one
            per tick of the replay's clock (every arm of one replay gets the same).
        final_error_deg: (6,) |measured - last target| after settling (None when stopped early).
        tracking: :class:`Tracking` (None when nothing was streamed).
    """

    outcome: str = "error"
    detail: str = ""
    left: str = ""
    planned_s: float = 0.0
    streamed_s: float = 0.0
    approach_s: float = 0.0
    ticks: int = 0
    late_ticks: int = 0
    streamed_at_s: np.ndarray | None = None
    final_error_deg: np.ndarray | None = None
    tracking: Tracking | None = None

    def __str__(self) -> str:
        lines = [f"outcome: {self.outcome}" + (f" ({self.detail})" if self.detail else ""),
                 f"streamed {self.streamed_s:.2f} of {self.planned_s:.2f} s ({self.ticks} targets, "
                 f"{self.late_ticks} late ticks) after a {self.approach_s:.2f} s approach",
                 f"the arm was left {self.left}"]
        tr = self.tracking
        if tr is not None:
            def joints(a: np.ndarray) -> str:
                return " ".join(f"{v:6.2f}" for v in a)
            lines += [f"tracking error, deg (J1..J6), {tr.samples} feedback samples:",
                      f"  max            {joints(tr.max_deg)}",
                      f"  rms            {joints(tr.rms_deg)}",
                      f"  after {tr.lag_s * 1e3:3.0f} ms lag: max {joints(tr.lag_max_deg)}",
                      f"                   rms {joints(tr.lag_rms_deg)}",
                      f"  {tr.gripper}"]
        if self.final_error_deg is not None:
            lines.append(f"final error, deg: {' '.join(f'{v:.3f}' for v in self.final_error_deg)}")
        return "\n".join(lines)


def _held(times: np.ndarray, values: np.ndarray, query: np.ndarray) -> np.ndarray:
    """``values`` as held from each of ``times`` on, at ``query`` times."""
    k = np.clip(np.searchsorted(times, query, side="right") - 1, 0, len(times) - 1)
    return values[k]


def tracking_of(sent_t: np.ndarray, sent_q: np.ndarray, sent_g: np.ndarray, fb_t: np.ndarray, fb_q: np.ndarray,
                fb_g: np.ndarray) -> Tracking | None:
    """The :class:`Tracking` of targets sent at host times ``sent_t`` (K,) s, ``sent_q`` (K, 6) rad,
    ``sent_g`` (K,) m, from feedback at ``fb_t`` (M,) s, ``fb_q`` (M, 6) rad, ``fb_g`` (M,) m (NaN:
    none); None with fewer than two of either."""
    if len(fb_t) < 2 or len(sent_t) < 2:
        return None
    err = np.degrees(np.abs(fb_q - _held(sent_t, sent_q, fb_t)))
    lags = np.arange(0.0, 0.5 + 1e-9, 0.005)
    rms = [np.sqrt(np.mean(np.degrees(fb_q - _held(sent_t, sent_q, fb_t - d)) ** 2)) for d in lags]
    best = float(lags[int(np.argmin(rms))])
    lag_err = np.degrees(np.abs(fb_q - _held(sent_t, sent_q, fb_t - best)))
    return Tracking(err.max(axis=0), np.sqrt((err ** 2).mean(axis=0)), best, np.sqrt((lag_err ** 2).mean(axis=0)),
                    lag_err.max(axis=0), GripperTracking.of(sent_t, sent_g, fb_t, fb_g), len(fb_t))
