"""What a PiPER reader knows: the latest frame of every kind, complete joint samples, counts,
rates and gaps per ID, and the health of the bus. Pure (no threads, no bus): :class:`PiperArm`
feeds it under a lock, tests and benchmarks feed it directly.

Health rules (``health(now)``, ``now`` on ``time.monotonic()``):
* ``read_error``: the bus's ``recv`` raised after the last valid feedback frame;
* ``bus_off``: a bus-off error frame (socketcan ``CAN_ERR_BUSOFF``) or python-can
  ``bus.state == ERROR`` after the last valid feedback frame;
* ``error_passive``: a controller error frame saying RX/TX passive, after the last valid frame;
* ``waiting``: no valid feedback frame yet; ``silent``: none for ``silence_timeout_s``;
* else ``ok``. Feedback means a valid arm -> host frame; our own and a master arm's commands,
  unknown IDs and invalid frames do not keep the link alive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import can
import numpy as np

from manisplat.drivers.base import ArmHealth, JointState
from manisplat.drivers.piper import protocol as P
from manisplat.drivers.piper.assembler import DEFAULT_WINDOW_S, JointAssembler

F = TypeVar("F")

CAN_ERR_CRTL = 0x04
CAN_ERR_BUSOFF = 0x40
CAN_ERR_RESTARTED = 0x100
CAN_ERR_CRTL_PASSIVE = 0x10 | 0x20  # RX / TX passive, data[1]

#: nominal rates of the periodic feedback (reference §1.4), Hz
NOMINAL_RATE_HZ: dict[int, float] = {**{i: 200.0 for i in range(0x2A1, 0x2A9)},
                                     **{i: 200.0 for i in range(0x251, 0x257)},
                                     **{i: 40.0 for i in range(0x261, 0x267)}}
GAP_FACTOR = 2.5  # an interval longer than this many nominal periods counts as a gap


@dataclass(frozen=True)
class Received(Generic[F]):
    """A decoded frame with its bus timestamp ``t`` and host arrival time ``t_host`` (s)."""

    frame: F
    t: float
    t_host: float


@dataclass(frozen=True)
class IdStats:
    """Counts of one CAN ID. ``rate_hz`` is the mean since the first frame (bus timestamps);
    ``gaps`` counts intervals over 2.5 nominal periods (periodic feedback IDs only)."""

    can_id: int
    count: int
    first_t: float
    last_t: float
    max_gap_s: float
    gaps: int

    @property
    def rate_hz(self) -> float:
        span = self.last_t - self.first_t
        return (self.count - 1) / span if self.count > 1 and span > 0 else float("nan")


@dataclass(frozen=True)
class BusStats:
    """Counts over everything received. ``frames == valid + invalid + unknown + undocumented``;
    ``error_frames`` are among the invalid ones. ``invalid_by_id`` counts invalid frames per ID
    and ``last_invalid`` keeps the latest reason per ID."""

    frames: int
    valid: int
    invalid: int
    unknown: int
    undocumented: int
    error_frames: int
    bus_off_events: int
    read_errors: int
    joint_samples: int
    joint_frames_discarded: int
    per_id: dict[int, IdStats]
    invalid_by_id: dict[int, int]
    last_invalid: dict[int, str]


class _IdCounter:
    __slots__ = ("count", "first_t", "last_t", "max_gap", "gaps", "gap_limit")

    def __init__(self, can_id: int, t: float) -> None:
        self.count, self.first_t, self.last_t, self.max_gap, self.gaps = 0, t, t, 0.0, 0
        rate = NOMINAL_RATE_HZ.get(can_id)
        self.gap_limit = GAP_FACTOR / rate if rate else math.inf

    def add(self, t: float) -> None:
        if self.count:
            gap = t - self.last_t
            if gap > self.max_gap:
                self.max_gap = gap
            if gap > self.gap_limit:
                self.gaps += 1
        self.count += 1
        self.last_t = t


class FeedbackTracker:
    """Ingests python-can messages; see the module docstring.

    Args:
        window_s: joint-cycle window (:mod:`~manisplat.drivers.piper.assembler`).
        silence_timeout_s: no valid feedback for this long means ``silent`` (the SDK's isOk()
            gives up after 5 zero-rate checks at 20 Hz, 0.25 s).
    """

    def __init__(self, window_s: float = DEFAULT_WINDOW_S, silence_timeout_s: float = 0.25) -> None:
        self.assembler = JointAssembler(window_s)
        self.silence_timeout_s = float(silence_timeout_s)
        self._latest: dict[int, Received[Any]] = {}
        self._ids: dict[int, _IdCounter] = {}
        self._invalid_by_id: dict[int, int] = {}
        self._last_invalid: dict[int, str] = {}
        self._joint: JointState | None = None
        self.frames = self.valid = self.invalid = self.unknown = self.undocumented = 0
        self.error_frames = self.bus_off_events = self.read_errors = 0
        self.last_feedback_host = -math.inf
        self._bus_off_host = -math.inf
        self._passive_host = -math.inf
        self._read_error_host = -math.inf
        self._read_error = ""

    # -- input ----------------------------------------------------------------------------

    def ingest(self, msg: can.Message, t_host: float) -> JointState | None:
        """Account for one message; returns the joint sample it completed, if any."""
        self.frames += 1
        frame = P.decode_message(msg)
        t = float(msg.timestamp)
        kind = type(frame)
        if kind is P.InvalidFrame:
            self.invalid += 1
            self._invalid_by_id[frame.id] = self._invalid_by_id.get(frame.id, 0) + 1
            self._last_invalid[frame.id] = frame.reason
            if msg.is_error_frame:
                self._error_frame(msg, t_host)
            return None
        if kind is P.UnknownFrame:
            self.unknown += 1
            return None
        if kind is P.UndocumentedFrame:
            self.undocumented += 1
        else:
            self.valid += 1
        can_id = msg.arbitration_id
        counter = self._ids.get(can_id)
        if counter is None:
            counter = self._ids[can_id] = _IdCounter(can_id, t)
        counter.add(t)
        self._latest[can_id] = Received(frame, t, t_host)
        if not getattr(frame, "COMMAND", True):
            self.last_feedback_host = t_host
        if kind is P.JointFeedback:
            done = self.assembler.push(frame.pair, frame.q_a, frame.q_b, t)
            if done is not None:
                return self._joint_sample(done[0], done[1], t_host)
        return None

    def note_read_error(self, exc: BaseException, t_host: float) -> None:
        """Record that the bus's ``recv`` raised ``exc``."""
        self.read_errors += 1
        self._read_error_host = t_host
        self._read_error = f"{type(exc).__name__}: {exc}"

    def note_bus_off(self, t_host: float) -> None:
        """Record a bus-off reported by the interface (python-can ``bus.state``)."""
        if self._bus_off_host <= self.last_feedback_host:
            self.bus_off_events += 1
        self._bus_off_host = t_host

    def _error_frame(self, msg: can.Message, t_host: float) -> None:
        self.error_frames += 1
        err = msg.arbitration_id
        if err & CAN_ERR_BUSOFF:
            self.bus_off_events += 1
            self._bus_off_host = t_host
        if err & CAN_ERR_CRTL and len(msg.data) > 1 and msg.data[1] & CAN_ERR_CRTL_PASSIVE:
            self._passive_host = t_host

    def _joint_sample(self, t: float, q: np.ndarray, t_host: float) -> JointState:
        grip = self._latest.get(P.CanId.GRIPPER_FEEDBACK)
        effort = np.full(6, np.nan)
        for motor in range(1, 7):
            hs = self._latest.get(0x250 + motor)
            if hs is not None:
                effort[motor - 1] = hs.frame.effort
        seq = self._joint.seq + 1 if self._joint is not None else 0
        self._joint = JointState(t=t, q=q, gripper=grip.frame.width if grip else math.nan, effort=effort,
                                 seq=seq, t_host=t_host)
        return self._joint

    # -- output ---------------------------------------------------------------------------

    def latest(self, can_id: int) -> Received[Any] | None:
        """The latest valid frame with ``can_id``, or None."""
        return self._latest.get(int(can_id))

    def joint_state(self) -> JointState | None:
        return self._joint

    def stats(self) -> BusStats:
        per_id = {i: IdStats(i, c.count, c.first_t, c.last_t, c.max_gap, c.gaps) for i, c in self._ids.items()}
        a = self.assembler
        return BusStats(self.frames, self.valid, self.invalid, self.unknown, self.undocumented, self.error_frames,
                        self.bus_off_events, self.read_errors, a.samples, a.discarded, per_id,
                        dict(self._invalid_by_id), dict(self._last_invalid))

    def health(self, now: float) -> ArmHealth:
        """Health at host time ``now`` (``time.monotonic()``), by the module's rules."""
        last = self.last_feedback_host
        silent = now - last
        if self._read_error_host > last:
            return ArmHealth("read_error", f"CAN read failed: {self._read_error}", silent)
        if self._bus_off_host > last:
            return ArmHealth("bus_off", "the CAN controller is bus-off (wiring, termination, bitrate "
                             "or a powered-off arm); no frames since", silent)
        if self._passive_host > last:
            return ArmHealth("error_passive", "the CAN controller is error-passive; no frames since", silent)
        if last == -math.inf:
            return ArmHealth("waiting", "no PiPER feedback received yet", silent)
        if silent > self.silence_timeout_s:
            return ArmHealth("silent", f"no PiPER feedback for {silent:.3f} s "
                             f"(timeout {self.silence_timeout_s} s)", silent)
        return ArmHealth("ok", "", silent)
