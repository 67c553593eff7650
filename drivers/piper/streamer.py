"""Replay a checked :class:`~.trajectory.Trajectory` on a PiPER: move slowly to its start, stream
its targets at the arm's rate, watch the feedback, stop safely.

    >>> report = replay(arm, traj, StreamConfig(max_tracking_error_deg=10), stop=stop_event)

Sequence: enable the motors if they are not (0x471, which never drops the arm), CAN control in
MOVE J at ``arm_speed_pct`` (0x151), the approach (a cosine ramp to the first target at
``approach_fraction`` of the speed limits, then wait until within ``settle_tol_deg``), then one
target per tick at ``rate_hz`` (0x151 + 0x155..0x157 every tick, 0x159 every ``gripper_every``
ticks), each step checked against the speed limits by :meth:`PiperArm.move_joints`, then the
last target until the arm settles.

Every tick checks the latest feedback: older than ``feedback_timeout_s`` -> stop ("feedback
lost"); joint error against the target in effect when that feedback arrived above
``max_tracking_error_deg`` -> stop ("tracking error"); ``stop`` set (Ctrl-C, SIGTERM) -> stop
("interrupted"); any exception -> stop ("error"). Stopping never sends reset (0x150 B0=2: power
cut, the arm drops) or disable (0x471 ``07 01``): the arm is left holding, on its measured
position when the feedback is fresh, else on the last target sent (which it was already moving to).

The report gives the tracking error per joint (max and RMS, deg) against the commanded targets,
and again after removing the best constant lag (the MOVE J planner follows with a delay).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Callable

import can
import numpy as np

from manisplat.drivers.piper import protocol as P
from manisplat.drivers.piper.arm import PiperArm
from manisplat.drivers.piper.trajectory import Trajectory, approach, sample

log = logging.getLogger(__name__)


@dataclass
class StreamConfig:
    """Settings of :func:`replay` (SI units; angles in degrees where the name says so)."""

    rate_hz: float = 200.0
    arm_speed_pct: int = 100
    max_tracking_error_deg: float = 10.0
    feedback_timeout_s: float = 0.1
    approach_fraction: float = 0.1
    settle_tol_deg: float = 0.5
    settle_timeout_s: float = 5.0
    gripper_effort_nm: float = 1.0
    gripper_every: int = 4
    enable_timeout_s: float = 2.0

    def __post_init__(self) -> None:
        for name in ("rate_hz", "max_tracking_error_deg", "feedback_timeout_s", "approach_fraction",
                     "settle_tol_deg", "settle_timeout_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 1 <= self.arm_speed_pct <= 100:
            raise ValueError(f"arm_speed_pct must be in 1..100, got {self.arm_speed_pct}")


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
    final_error_deg: np.ndarray | None = None
    tracking: Tracking | None = None

    def __str__(self) -> str:
        lines = [f"outcome: {self.outcome}" + (f" ({self.detail})" if self.detail else ""),
                 f"streamed {self.streamed_s:.2f} of {self.planned_s:.2f} s ({self.ticks} targets, "
                 f"{self.late_ticks} late ticks) after a {self.approach_s:.2f} s approach",
                 f"arm left {self.left}"]
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


class _Stop(Exception):
    def __init__(self, outcome: str, detail: str) -> None:
        super().__init__(detail)
        self.outcome = outcome
        self.detail = detail


class CommandAudit(can.Listener):
    """Counts the commands seen on a bus (for a simulated arm's bus: proof of what was sent).

    Attributes: ``resets`` (0x150 B0=2), ``estops`` (0x150 B0=1), ``disables`` (0x471 B1=0x01),
    ``enables``, ``joint_targets`` (0x155 frames), ``modes`` (0x151), and
    ``last_joint_target_stamp``: the bus timestamp of the latest 0x155 (s, or None).
    """

    def __init__(self) -> None:
        self.resets = self.estops = self.disables = self.enables = self.joint_targets = self.modes = 0
        self.last_joint_target_stamp: float | None = None

    def on_message_received(self, msg: can.Message) -> None:
        frame = P.decode_message(msg)
        if isinstance(frame, P.MotionCtrl1):
            self.resets += frame.emergency_stop == P.EStop.RESUME
            self.estops += frame.emergency_stop == P.EStop.STOP
        elif isinstance(frame, P.MotorEnable):
            self.enables += bool(frame.enable)
            self.disables += not frame.enable
        elif isinstance(frame, P.JointCtrl) and frame.pair == 0:
            self.joint_targets += 1
            self.last_joint_target_stamp = msg.timestamp
        elif isinstance(frame, P.ModeCtrl):
            self.modes += 1


class _Run:
    """One replay's state (kept together so the final hold knows the last target)."""

    def __init__(self, arm: PiperArm, traj: Trajectory, config: StreamConfig, stop: threading.Event,
                 clock: Callable[[], float], on_progress: Callable[[float, float], None] | None) -> None:
        self.arm, self.traj, self.c, self.stop, self.clock = arm, traj, config, stop, clock
        self.on_progress = on_progress
        self.period = 1.0 / config.rate_hz
        self.report = ReplayReport(planned_s=traj.duration)
        self.last_target: np.ndarray | None = None
        self.last_send = -math.inf
        self.sent_t: list[float] = []  # host time of each streamed target
        self.sent_q: list[np.ndarray] = []
        self.sent_g: list[float] = []
        self.fb_t: list[float] = []  # host arrival time of each feedback sample while streaming
        self.fb_q: list[np.ndarray] = []
        self.fb_g: list[float] = []
        self._fb_seq = -1
        self._ticks = 0

    # -- commands -------------------------------------------------------------------------------

    def send(self, q: np.ndarray, gripper: float | None, dt: float | None, *, force_gripper: bool = False) -> None:
        """Command ``q`` (and the gripper every ``gripper_every`` ticks). ``dt``: the planned
        time since the previous target, s (its step is checked against the speed limits; the
        planned time, not the send time, so a late tick cannot fail the check)."""
        self.arm.move_joints(q, self.c.arm_speed_pct, dt=dt if dt is not None and dt > 0 else None)
        self.last_target, self.last_send = np.asarray(q, dtype=np.float64).copy(), self.clock()
        if gripper is not None and (force_gripper or self._ticks % self.c.gripper_every == 0):
            self.arm.gripper(gripper, self.c.gripper_effort_nm)
        self._ticks += 1

    def check(self, streaming: bool) -> np.ndarray:
        """Stop conditions on the latest feedback; returns the measured q (6,)."""
        if self.stop.is_set():
            raise _Stop("interrupted", "stopped on request (Ctrl-C / SIGTERM)")
        state = self.arm.joint_state()
        now = self.clock()
        if state is None or now - state.t_host > self.c.feedback_timeout_s:
            age = "none yet" if state is None else f"last {now - state.t_host:.3f} s ago"
            raise _Stop("feedback_lost", f"no joint feedback within {self.c.feedback_timeout_s} s ({age})")
        if streaming and state.seq != self._fb_seq:
            self._fb_seq = state.seq
            self.fb_t.append(state.t_host)
            self.fb_q.append(state.q)
            self.fb_g.append(state.gripper)
        target = self._target_at(state.t_host) if streaming else self.last_target
        if target is not None:
            err = np.degrees(np.abs(state.q - target))
            if err.max() > self.c.max_tracking_error_deg:
                j = int(np.argmax(err))
                raise _Stop("tracking_error", f"joint{j + 1} is {err[j]:.2f} deg from its target "
                                              f"(limit {self.c.max_tracking_error_deg:g} deg)")
        return state.q

    def _target_at(self, t: float) -> np.ndarray | None:
        """The streamed target in effect at host time ``t`` (the latest sent at or before it)."""
        k = len(self.sent_t) - 1
        while k >= 0 and self.sent_t[k] > t:
            k -= 1
        return self.sent_q[k] if k >= 0 else self.last_target

    def wait_tick(self, deadline: float) -> float:
        """Sleep until ``deadline``; returns the next deadline (skipping ahead when late)."""
        delay = deadline - self.clock()
        if delay > 0:
            if self.stop.wait(delay):
                raise _Stop("interrupted", "stopped on request (Ctrl-C / SIGTERM)")
        elif delay < -2 * self.period:
            self.report.late_ticks += 1
            return self.clock() + self.period
        return deadline + self.period

    # -- phases ---------------------------------------------------------------------------------

    def prepare(self) -> np.ndarray:
        state = self.arm.wait_for_joint_state(timeout=max(1.0, self.c.feedback_timeout_s))
        if not all(self.arm.motors_enabled()):
            log.info("enabling the motors (0x471)")
            self.arm.enable(self.c.enable_timeout_s)
        self.arm.set_mode(speed_pct=self.c.arm_speed_pct)
        return self.arm.wait_for_joint_state(state.seq, timeout=1.0).q

    def approach(self, q_now: np.ndarray) -> None:
        q0, g0 = sample(self.traj, 0.0)
        # an arm resting at a joint limit may read one wire step (0.001 deg) beyond it, and a
        # target there is refused: the ramp starts from the nearest point inside the limits
        q_now = np.clip(q_now, self.arm.robot.lower, self.arm.robot.upper)
        duration, at = approach(q_now, q0, self.arm.robot, self.c.approach_fraction)
        self.report.approach_s = duration
        log.info("moving to the start: %.1f deg away, %.2f s", float(np.degrees(np.abs(q0 - q_now).max())), duration)
        start = self.clock()
        deadline = start
        self.send(q_now, g0, None)
        previous = 0.0
        while True:
            s = min(self.clock() - start, duration)
            self.send(at(s), g0, s - previous)
            previous = s
            self.check(streaming=False)
            if s >= duration:
                break
            deadline = self.wait_tick(deadline)
        self.settle(q0, g0)

    def settle(self, target: np.ndarray, gripper: float) -> np.ndarray:
        """Keep commanding ``target`` until every joint is within ``settle_tol_deg``."""
        limit = self.clock() + self.c.settle_timeout_s
        deadline = self.clock()
        first = True
        while True:
            self.send(target, gripper, self.period, force_gripper=first)
            first = False
            q = self.check(streaming=False)
            err = np.degrees(np.abs(q - target))
            if err.max() <= self.c.settle_tol_deg:
                return err
            if self.clock() > limit:
                raise _Stop("tracking_error", f"the arm did not settle within {self.c.settle_tol_deg} deg of the "
                                              f"target in {self.c.settle_timeout_s} s (max {err.max():.2f} deg)")
            deadline = self.wait_tick(deadline)

    def stream(self) -> None:
        traj = self.traj
        start = self.clock()
        deadline = start
        next_progress = start
        previous = 0.0
        while True:
            s = min(self.clock() - start, float(traj.t[-1]))
            q, g = sample(traj, s)
            self.send(q, g, s - previous if self.report.ticks else None)
            previous = s
            self.sent_t.append(self.last_send)
            self.sent_q.append(self.last_target)
            self.sent_g.append(g)
            self.report.ticks += 1
            self.report.streamed_s = s
            self.check(streaming=True)
            if self.on_progress is not None and self.clock() >= next_progress:
                next_progress += 0.5
                self.on_progress(self.report.streamed_s, traj.duration)
            if s >= traj.t[-1]:
                break
            deadline = self.wait_tick(deadline)
        q_end, g_end = sample(traj, traj.t[-1])
        self.report.final_error_deg = self.settle(q_end, g_end)

    # -- the report -----------------------------------------------------------------------------

    def tracking(self) -> Tracking | None:
        if len(self.fb_t) < 2 or len(self.sent_t) < 2:
            return None
        st = np.asarray(self.sent_t)
        sq = np.asarray(self.sent_q)
        sg = np.asarray(self.sent_g)
        ft = np.asarray(self.fb_t)
        fq = np.asarray(self.fb_q)
        fg = np.asarray(self.fb_g)

        def held(times: np.ndarray, values: np.ndarray, query: np.ndarray) -> np.ndarray:
            k = np.clip(np.searchsorted(times, query, side="right") - 1, 0, len(times) - 1)
            return values[k]

        err = np.degrees(np.abs(fq - held(st, sq, ft)))
        lags = np.arange(0.0, 0.5 + 1e-9, 0.005)
        rms = [np.sqrt(np.mean(np.degrees(fq - held(st, sq, ft - d)) ** 2)) for d in lags]
        best = float(lags[int(np.argmin(rms))])
        lag_err = np.degrees(np.abs(fq - held(st, sq, ft - best)))
        return Tracking(err.max(axis=0), np.sqrt((err ** 2).mean(axis=0)), best,
                        np.sqrt((lag_err ** 2).mean(axis=0)), lag_err.max(axis=0), GripperTracking.of(st, sg, ft, fg),
                        len(ft))


def leave_holding(arm: PiperArm, last_target: np.ndarray | None, feedback_fresh: bool) -> str:
    """Leave the arm holding (never reset nor disable): its measured position when the feedback
    is fresh, else the last target sent. Returns how it was left."""
    if feedback_fresh:
        try:
            if arm.hold():
                return "holding its measured position (MOVE J target = feedback)"
        except Exception as exc:  # then try the last target
            log.error("holding the measured position failed: %s", exc)
    if last_target is not None:
        try:
            arm.move_joints(last_target)
            return "holding the last target sent" + ("" if feedback_fresh else " (no fresh feedback to hold on)")
        except Exception as exc:
            log.error("re-sending the last target failed: %s", exc)
            return f"with its last target (sending failed: {exc})"
    return "as it was (nothing was commanded)"


def replay(arm: PiperArm, traj: Trajectory, config: StreamConfig | None = None, stop: threading.Event | None = None,
           *, clock: Callable[[], float] = time.monotonic,
           on_progress: Callable[[float, float], None] | None = None) -> ReplayReport:
    """Replay ``traj`` (already checked by :func:`~.trajectory.check_trajectory`) on ``arm``; see
    the module docstring. Never raises for a stop: the report says what happened (a
    KeyboardInterrupt is reported as ``"interrupted"``)."""
    config = config if config is not None else StreamConfig()
    stop = stop if stop is not None else threading.Event()
    run = _Run(arm, traj, config, stop, clock, on_progress)
    report = run.report
    fresh = True
    try:
        run.approach(run.prepare())
        run.stream()
        report.outcome, report.detail = "completed", ""
    except _Stop as s:
        report.outcome, report.detail = s.outcome, s.detail
        fresh = s.outcome != "feedback_lost"
    except KeyboardInterrupt:
        report.outcome, report.detail = "interrupted", "KeyboardInterrupt"
    except Exception as exc:
        report.outcome, report.detail = "error", f"{type(exc).__name__}: {exc}"
        log.exception("replay stopped by an error")
        fresh = arm.health().ok
    finally:
        report.left = leave_holding(arm, run.last_target, fresh) if run.last_target is not None else \
            "as it was (nothing was commanded)"
    report.tracking = run.tracking()
    log.info("replay %s: %s; arm left %s", report.outcome, report.detail, report.left)
    return report
