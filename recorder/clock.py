"""One monotonic timeline for everything a recording holds.

SocketCAN (and python-can's virtual, slcan and serial interfaces) stamp frames on the wall clock
(CLOCK_REALTIME, epoch seconds, stepped or slewed by NTP); depthai stamps camera frames on the
host's steady clock (CLOCK_MONOTONIC = ``time.monotonic()`` on Linux). A recording maps both
onto the monotonic clock: ``t_mono = t_wall - offset`` with ``offset = wall - monotonic``
measured by bracketing a wall reading between two monotonic readings (the narrowest of a burst
of tries wins; its width bounds the error). :class:`ClockMap` re-measures during the recording,
maps every CAN stamp with the latest measurement, notices steps of the wall clock, and describes
the whole mapping for ``episode.json``.

Clocks are objects (:class:`Clock`), so tests and benchmarks can run the same code on simulated
time: :class:`SystemClock` (the real clocks), :class:`ManualClock` (advanced by a simulator,
lock-step, deterministic) and :class:`ScaledClock` (real time sped up by a factor).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

log = logging.getLogger(__name__)

STEP_WARN_S = 0.001  # a change of the wall-monotonic offset larger than this is reported as a step


@runtime_checkable
class Clock(Protocol):
    """The two host clocks, in seconds, and a way to wait on the monotonic one."""

    def monotonic(self) -> float:
        """CLOCK_MONOTONIC (the recording's timeline), s."""

    def wall(self) -> float:
        """CLOCK_REALTIME (epoch seconds; what SocketCAN stamps), s."""

    def sleep_until(self, t: float, stop: threading.Event | None = None) -> bool:
        """Wait until ``monotonic() >= t``; False when ``stop`` was set first."""


class SystemClock:
    """The real clocks: ``time.monotonic()`` and ``time.time()``."""

    def monotonic(self) -> float:
        return time.monotonic()

    def wall(self) -> float:
        return time.time()

    def sleep_until(self, t: float, stop: threading.Event | None = None) -> bool:
        stop = stop if stop is not None else threading.Event()
        while (delay := t - time.monotonic()) > 0:
            if stop.wait(min(delay, 0.1)):
                return False
        return True


class ManualClock:
    """Simulated time that only moves when :meth:`advance_to` is called (by a simulator running
    lock-step with its consumers). ``wall = monotonic + wall_offset``.

    Args:
        start: initial monotonic time, s.
        wall_offset: wall minus monotonic, s (a realistic epoch value by default).
    """

    def __init__(self, start: float = 1000.0, wall_offset: float = 1.7e9) -> None:
        self._t = float(start)
        self.wall_offset = float(wall_offset)
        self._cond = threading.Condition()

    def monotonic(self) -> float:
        return self._t

    def wall(self) -> float:
        return self._t + self.wall_offset

    def advance_to(self, t: float) -> None:
        """Move time forward to ``t`` (never backwards) and wake the waiters."""
        with self._cond:
            if t > self._t:
                self._t = float(t)
                self._cond.notify_all()

    def sleep_until(self, t: float, stop: threading.Event | None = None) -> bool:
        with self._cond:
            while self._t < t:
                if stop is not None and stop.is_set():
                    return False
                self._cond.wait(0.05)
        return True


class ScaledClock:
    """Real time sped up ``speed`` times: ``monotonic = start + speed * (time.monotonic() - t_real0)``,
    ``wall = monotonic + wall_offset``. A benchmark runs a simulated arm and camera on it to
    record simulated minutes in less real time."""

    def __init__(self, speed: float, start: float = 1000.0, wall_offset: float = 1.7e9) -> None:
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        self.speed = float(speed)
        self.start = float(start)
        self.wall_offset = float(wall_offset)
        self._real0 = time.monotonic()

    def monotonic(self) -> float:
        return self.start + self.speed * (time.monotonic() - self._real0)

    def wall(self) -> float:
        return self.monotonic() + self.wall_offset

    def sleep_until(self, t: float, stop: threading.Event | None = None) -> bool:
        stop = stop if stop is not None else threading.Event()
        while (delay := (t - self.monotonic()) / self.speed) > 0:
            if stop.wait(min(delay, 0.1)):
                return False
        return True


class RealDeadline:
    """An Event-like stop condition for :meth:`Clock.sleep_until` that is set once ``seconds``
    of real (host) time have passed, or when ``stop`` is set: a wait on a simulated clock that
    has stopped moving still ends."""

    def __init__(self, seconds: float, stop: threading.Event | None = None) -> None:
        self.deadline = time.monotonic() + seconds
        self.stop = stop if stop is not None else threading.Event()

    def is_set(self) -> bool:
        return self.stop.is_set() or time.monotonic() >= self.deadline

    def wait(self, timeout: float | None = None) -> bool:
        remaining = self.deadline - time.monotonic()
        self.stop.wait(max(0.0, remaining if timeout is None else min(timeout, remaining)))
        return self.is_set()


@dataclass(frozen=True)
class OffsetSample:
    """One measurement of ``wall - monotonic``.

    Attributes:
        t_mono: monotonic time of the measurement (the middle of the bracket), s.
        offset: wall minus monotonic, s.
        uncertainty: half the width of the narrowest bracket, s (the error bound).
    """

    t_mono: float
    offset: float
    uncertainty: float


def measure_offset(clock: Clock, tries: int = 15) -> OffsetSample:
    """``wall - monotonic`` from the narrowest of ``tries`` brackets ``mono, wall, mono``."""
    if tries < 1:
        raise ValueError(f"tries must be >= 1, got {tries}")
    best: OffsetSample | None = None
    for _ in range(tries):
        m0 = clock.monotonic()
        w = clock.wall()
        m1 = clock.monotonic()
        mid = 0.5 * (m0 + m1)
        sample = OffsetSample(mid, w - mid, 0.5 * (m1 - m0))
        if best is None or sample.uncertainty < best.uncertainty:
            best = sample
    return best


class ClockMap:
    """Maps wall-clock stamps (CAN) onto the monotonic timeline with a measured offset.

    Thread-safe: :meth:`to_mono` is called from the CAN reader thread, :meth:`remeasure` from
    the recording loop. Every measurement is kept (they are small) for :meth:`describe`.

    Args:
        clock: the host clocks.
        remeasure_s: :meth:`maybe_remeasure` measures again after this long, s.
    """

    def __init__(self, clock: Clock, remeasure_s: float = 1.0) -> None:
        self.clock = clock
        self.remeasure_s = float(remeasure_s)
        self._lock = threading.Lock()
        self.samples: list[OffsetSample] = []
        self.steps: list[tuple[float, float]] = []  # (t_mono, offset change) of wall-clock steps
        self._offset = 0.0
        self.remeasure()

    @property
    def offset(self) -> float:
        """The latest ``wall - monotonic``, s."""
        return self._offset

    def remeasure(self) -> OffsetSample:
        """Measure again; a change above 1 ms is logged as a wall-clock step."""
        sample = measure_offset(self.clock)
        with self._lock:
            if self.samples:
                change = sample.offset - self._offset
                if abs(change) > STEP_WARN_S:
                    self.steps.append((sample.t_mono, change))
                    log.warning("the wall clock moved by %+.3f ms against the monotonic clock (NTP step?); "
                                "CAN stamps are mapped with the new offset from now on", change * 1e3)
            self.samples.append(sample)
            self._offset = sample.offset
        return sample

    def maybe_remeasure(self) -> None:
        """Re-measure when the last measurement is older than ``remeasure_s``."""
        if self.clock.monotonic() - self.samples[-1].t_mono >= self.remeasure_s:
            self.remeasure()

    def to_mono(self, t_wall: float) -> float:
        """A wall-clock stamp on the monotonic timeline, s."""
        return t_wall - self._offset

    def describe(self, since: float = -math.inf) -> dict[str, Any]:
        """The mapping as plain JSON values (measurements at or after ``since``, monotonic s)."""
        with self._lock:
            used = [s for s in self.samples if s.t_mono >= since] or self.samples[-1:]
            offsets = [s.offset for s in used]
            return {
                "timeline": "host CLOCK_MONOTONIC (Python time.monotonic(); depthai's host clock)",
                "wall_minus_monotonic_s": used[0].offset,
                "offset_uncertainty_s": max(s.uncertainty for s in used),
                "offset_measurements": len(used),
                "offset_range_s": [min(offsets), max(offsets)],
                "wall_clock_steps": [{"t_monotonic": t, "change_s": c} for t, c in self.steps if t >= since],
            }
