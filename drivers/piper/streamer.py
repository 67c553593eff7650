"""Replay checked :class:`~.trajectory.Trajectory` objects on one PiPER or several, in lock-step:
move slowly to their starts, stream their targets at the arms' rate from one clock, watch the
feedback, stop safely.

    >>> report = replay(arm, traj, StreamConfig(max_tracking_error_deg=10), stop=stop_event)
    >>> reports = replay_arms({"left": (arm_l, traj_l), "right": (arm_r, traj_r)}, config, stop)

Sequence, for every arm: enable the motors if they are not (0x471, which never drops the arm),
CAN control in MOVE J at ``arm_speed_pct`` (0x151); the approach (a cosine ramp to the first
target at ``approach_fraction`` of the speed limits, every arm at once, then wait until every arm
is within ``settle_tol_deg``); then one target per tick at ``rate_hz`` (0x151 + 0x155..0x157 every
tick, 0x159 every ``gripper_every`` ticks), each step checked against the speed limits by
:meth:`PiperArm.move_joints`, then the last target until every arm settles. One thread and one
clock drive all arms: each tick samples every arm's trajectory at the same time ``s`` and
commands them one after the other (``streamed_at_s`` in the reports records it).

Every tick checks every arm's latest feedback: older than ``feedback_timeout_s`` -> stop
("feedback lost"); joint error against the target in effect when that feedback arrived above
``max_tracking_error_deg`` -> stop ("tracking error"); ``stop`` set (Ctrl-C, SIGTERM) -> stop
("interrupted"); any exception -> stop ("error"). A stop on one arm stops all of them; the detail
names the arm when there are several. Stopping never sends reset (0x150 B0=2: power cut, the arm
drops) or disable (0x471 ``07 01``): every arm is left holding, on its measured position when its
feedback is fresh, else on the last target sent (which it was already moving to).

Each arm's report gives its tracking error per joint (:mod:`.tracking`).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Callable, Mapping

import can
import numpy as np

from manisplat.drivers.piper import protocol as P
from manisplat.drivers.piper.arm import PiperArm
from manisplat.drivers.piper.tracking import GripperTracking, ReplayReport, Tracking, tracking_of
from manisplat.drivers.piper.trajectory import Trajectory, approach, sample

log = logging.getLogger(__name__)

__all__ = ["CommandAudit", "GripperTracking", "ReplayReport", "StreamConfig", "Tracking", "leave_holding", "replay",
           "replay_arms"]


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


class _Stop(Exception):
    """Why the replay stops; ``arm``: the arm it concerns (None: all of them)."""

    def __init__(self, outcome: str, detail: str, arm: str | None = None) -> None:
        super().__init__(detail)
        self.outcome, self.detail, self.arm = outcome, detail, arm


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


class _ArmRun:
    """One arm's part of a replay: its commands, its feedback checks and what they recorded."""

    def __init__(self, name: str, arm: PiperArm, traj: Trajectory, config: StreamConfig,
                 clock: Callable[[], float]) -> None:
        self.name, self.arm, self.traj, self.c, self.clock = name, arm, traj, config, clock
        self.report = ReplayReport(planned_s=traj.duration)
        self.last_target: np.ndarray | None = None
        self.last_send = -np.inf
        self.sent_t: list[float] = []  # host time of each streamed target
        self.sent_q: list[np.ndarray] = []
        self.sent_g: list[float] = []
        self.sent_s: list[float] = []  # trajectory time of each streamed target
        self.fb_t: list[float] = []  # host arrival time of each feedback sample while streaming
        self.fb_q: list[np.ndarray] = []
        self.fb_g: list[float] = []
        self._fb_seq = -1
        self._ticks = 0

    def send(self, q: np.ndarray, gripper: float | None, dt: float | None, *, force_gripper: bool = False) -> None:
        """Command ``q`` (and the gripper every ``gripper_every`` ticks). ``dt``: the planned
        time since the previous target, s (its step is checked against the speed limits; the
        planned time, not the send time, so a late tick cannot fail the check)."""
        self.arm.move_joints(q, self.c.arm_speed_pct, dt=dt if dt is not None and dt > 0 else None)
        self.last_target, self.last_send = np.asarray(q, dtype=np.float64).copy(), self.clock()
        if gripper is not None and (force_gripper or self._ticks % self.c.gripper_every == 0):
            self.arm.gripper(gripper, self.c.gripper_effort_nm)
        self._ticks += 1

    def target(self, s: float) -> tuple[np.ndarray, float]:
        """The trajectory's targets at time ``s``: (6,) rad and the gripper, m, inside the arm's limits.

        :func:`~.trajectory.check_trajectory` lets a value 1e-9 beyond a limit pass (rounding in
        the data: a gripper of 0.07000000000000006 m) and the arm refuses any excess, so the
        targets are clipped into the limits, moving them by at most that much."""
        q, g = sample(self.traj, s)
        robot = self.arm.robot
        lo, hi = robot.gripper.width_range if robot.gripper else (0.0, 0.07)
        return np.clip(q, robot.lower, robot.upper), min(max(g, lo), hi)

    def stream_to(self, s: float, dt: float | None) -> None:
        """Command the trajectory's targets at time ``s`` and record them."""
        q, g = self.target(s)
        self.send(q, g, dt)
        self.sent_t.append(self.last_send)
        self.sent_q.append(self.last_target)
        self.sent_g.append(g)
        self.sent_s.append(s)
        self.report.ticks += 1
        self.report.streamed_s = s

    def check(self, streaming: bool) -> np.ndarray:
        """Stop conditions on the latest feedback; returns the measured q (6,)."""
        state = self.arm.joint_state()
        now = self.clock()
        if state is None or now - state.t_host > self.c.feedback_timeout_s:
            age = "none yet" if state is None else f"last {now - state.t_host:.3f} s ago"
            raise _Stop("feedback_lost", f"no joint feedback within {self.c.feedback_timeout_s} s ({age})", self.name)
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
                                              f"(limit {self.c.max_tracking_error_deg:g} deg)", self.name)
        return state.q

    def _target_at(self, t: float) -> np.ndarray | None:
        """The streamed target in effect at host time ``t`` (the latest sent at or before it)."""
        k = len(self.sent_t) - 1
        while k >= 0 and self.sent_t[k] > t:
            k -= 1
        return self.sent_q[k] if k >= 0 else self.last_target

    def prepare(self) -> np.ndarray:
        """Enable the motors if needed and set MOVE J; returns the measured q (6,) rad."""
        state = self.arm.wait_for_joint_state(timeout=max(1.0, self.c.feedback_timeout_s))
        if not all(self.arm.motors_enabled()):
            log.info("%s: enabling the motors (0x471)", self.name)
            self.arm.enable(self.c.enable_timeout_s)
        self.arm.set_mode(speed_pct=self.c.arm_speed_pct)
        return self.arm.wait_for_joint_state(state.seq, timeout=1.0).q

    def tracking(self) -> Tracking | None:
        """How this arm followed what was streamed to it (None when too little was)."""
        return tracking_of(np.asarray(self.sent_t), np.asarray(self.sent_q), np.asarray(self.sent_g),
                           np.asarray(self.fb_t), np.asarray(self.fb_q), np.asarray(self.fb_g))


class _Run:
    """One replay of every arm from one clock (kept together so the final hold knows each last target)."""

    def __init__(self, arms: dict[str, _ArmRun], config: StreamConfig, stop: threading.Event,
                 clock: Callable[[], float], on_progress: Callable[[float, float], None] | None) -> None:
        self.arms, self.c, self.stop, self.clock, self.on_progress = arms, config, stop, clock, on_progress
        self.period = 1.0 / config.rate_hz
        self.late_ticks = 0

    def check(self, streaming: bool) -> dict[str, np.ndarray]:
        """Stop conditions of every arm; returns each arm's measured q (6,)."""
        if self.stop.is_set():
            raise _Stop("interrupted", "stopped on request (Ctrl-C / SIGTERM)")
        return {name: a.check(streaming) for name, a in self.arms.items()}

    def wait_tick(self, deadline: float) -> float:
        """Sleep until ``deadline``; returns the next deadline (skipping ahead when late)."""
        delay = deadline - self.clock()
        if delay > 0:
            if self.stop.wait(delay):
                raise _Stop("interrupted", "stopped on request (Ctrl-C / SIGTERM)")
        elif delay < -2 * self.period:
            self.late_ticks += 1
            return self.clock() + self.period
        return deadline + self.period

    def approach(self, q_now: dict[str, np.ndarray]) -> None:
        """Every arm from ``q_now`` to its start at once, then settle them all."""
        ramps = {}
        for name, a in self.arms.items():
            q0, g0 = a.target(0.0)
            # an arm resting at a joint limit may read one wire step (0.001 deg) beyond it, and a
            # target there is refused: the ramp starts from the nearest point inside the limits
            start = np.clip(q_now[name], a.arm.robot.lower, a.arm.robot.upper)
            duration, at = approach(start, q0, a.arm.robot, self.c.approach_fraction)
            a.report.approach_s = duration
            ramps[name] = (duration, at, g0)
            log.info("%s: moving to the start: %.1f deg away, %.2f s", name,
                     float(np.degrees(np.abs(q0 - start).max())), duration)
            a.send(start, g0, None)
        longest = max(r[0] for r in ramps.values())
        begin = self.clock()
        deadline = begin
        previous = 0.0
        while True:
            s = min(self.clock() - begin, longest)
            for name, (duration, at, g0) in ramps.items():
                self.arms[name].send(at(min(s, duration)), g0, min(s, duration) - min(previous, duration))
            previous = s
            self.check(streaming=False)
            if s >= longest:
                break
            deadline = self.wait_tick(deadline)
        self.settle({name: a.target(0.0) for name, a in self.arms.items()})

    def settle(self, targets: dict[str, tuple[np.ndarray, float]]) -> dict[str, np.ndarray]:
        """Keep commanding each arm's ``(q, gripper)`` until every joint of every arm is within
        ``settle_tol_deg``; returns each arm's final error (6,) deg."""
        limit = self.clock() + self.c.settle_timeout_s
        deadline = self.clock()
        first = True
        while True:
            for name, (q, g) in targets.items():
                self.arms[name].send(q, g, self.period, force_gripper=first)
            first = False
            measured = self.check(streaming=False)
            errors = {name: np.degrees(np.abs(measured[name] - q)) for name, (q, _) in targets.items()}
            if all(e.max() <= self.c.settle_tol_deg for e in errors.values()):
                return errors
            if self.clock() > limit:
                name = max(errors, key=lambda n: errors[n].max())
                raise _Stop("tracking_error", f"the arm did not settle within {self.c.settle_tol_deg} deg of the "
                                              f"target in {self.c.settle_timeout_s} s (max "
                                              f"{errors[name].max():.2f} deg)", name)
            deadline = self.wait_tick(deadline)

    def stream(self) -> None:
        """Every arm's targets, sampled at one time per tick of the one clock, then settle."""
        end = max(float(a.traj.t[-1]) for a in self.arms.values())
        planned = max(a.traj.duration for a in self.arms.values())
        start = self.clock()
        deadline = start
        next_progress = start
        previous: float | None = None
        while True:
            s = min(self.clock() - start, end)
            for a in self.arms.values():
                a.stream_to(s, None if previous is None else s - previous)
            previous = s
            self.check(streaming=True)
            if self.on_progress is not None and self.clock() >= next_progress:
                next_progress += 0.5
                self.on_progress(s, planned)
            if s >= end:
                break
            deadline = self.wait_tick(deadline)
        errors = self.settle({name: a.target(float(a.traj.t[-1])) for name, a in self.arms.items()})
        for name, a in self.arms.items():
            a.report.final_error_deg = errors[name]


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


def replay_arms(arms: Mapping[str, tuple[PiperArm, Trajectory]], config: StreamConfig | None = None,
                stop: threading.Event | None = None, *, clock: Callable[[], float] = time.monotonic,
                on_progress: Callable[[float, float], None] | None = None) -> dict[str, ReplayReport]:
    """Replay every named arm's trajectory (each already checked by
    :func:`~.trajectory.check_trajectory`) in lock-step; see the module docstring. Returns each
    arm's report, all with the same outcome. Never raises for a stop: the reports say what
    happened (a KeyboardInterrupt is reported as ``"interrupted"``)."""
    if not arms:
        raise ValueError("replay_arms needs at least one arm")
    config = config if config is not None else StreamConfig()
    stop = stop if stop is not None else threading.Event()
    runs = {name: _ArmRun(name, arm, traj, config, clock) for name, (arm, traj) in arms.items()}
    run = _Run(runs, config, stop, clock, on_progress)
    outcome, detail, stale = "error", "", set()
    try:
        run.approach({name: a.prepare() for name, a in runs.items()})
        run.stream()
        outcome = "completed"
    except _Stop as s:
        outcome = s.outcome
        detail = f"{s.arm}: {s.detail}" if s.arm is not None and len(runs) > 1 else s.detail
        if s.outcome == "feedback_lost":
            stale = {s.arm} if s.arm is not None else set(runs)
    except KeyboardInterrupt:
        outcome, detail = "interrupted", "KeyboardInterrupt"
    except Exception as exc:
        detail = f"{type(exc).__name__}: {exc}"
        log.exception("replay stopped by an error")
        stale = {name for name, a in runs.items() if not a.arm.health().ok}
    finally:
        for name, a in runs.items():
            a.report.left = leave_holding(a.arm, a.last_target, name not in stale) \
                if a.last_target is not None else "as it was (nothing was commanded)"
    for name, a in runs.items():
        r = a.report
        r.outcome, r.detail, r.late_ticks = outcome, detail, run.late_ticks
        r.streamed_at_s = np.asarray(a.sent_s)
        r.tracking = a.tracking()
        log.info("replay %s: %s; arm %s left %s", outcome, detail, name, r.left)
    return {name: a.report for name, a in runs.items()}


def replay(arm: PiperArm, traj: Trajectory, config: StreamConfig | None = None, stop: threading.Event | None = None,
           *, clock: Callable[[], float] = time.monotonic,
           on_progress: Callable[[float, float], None] | None = None) -> ReplayReport:
    """Replay ``traj`` on one arm: :func:`replay_arms` with that arm alone."""
    return replay_arms({"arm": (arm, traj)}, config, stop, clock=clock, on_progress=on_progress)["arm"]
