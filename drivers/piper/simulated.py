"""SimulatedPiper: a PiPER on any python-can bus, for tests and dry runs.

    >>> import can
    >>> arm_bus = can.Bus(interface="virtual", channel="sim")
    >>> with SimulatedPiper(can.Bus(interface="virtual", channel="sim", preserve_timestamps=True)):
    ...     ...   # a PiperArm on arm_bus (or the vendor SDK on a real adapter bridge) drives it

Every cycle (200 Hz by default) the simulator reads all pending commands from its bus, applies
them to :class:`~.sim_model.PiperModel` (behaviour documented there), advances the dynamics by
one period and sends the feedback of that cycle: 0x2A1..0x2A8 and 0x251..0x256 every cycle,
0x261..0x266 every fifth (40 Hz), i.e. 3040 frames/s like the real arm. Frames carry the
simulated time as timestamp (``t0`` + model time, 130 us apart within a cycle like frames at
1 Mbit/s); create the simulator's bus with ``preserve_timestamps=True`` so receivers see them
(a virtual bus otherwise stamps its own send time).

Timing: :meth:`start` runs cycles on a thread scheduled by ``clock`` (default
``time.monotonic``); when that thread is starved (a loaded machine), the model time still keeps
up with the clock, as a real arm's would: the missed cycles' dynamics are run at once, their
feedback is not sent (receivers see a gap, as after lost frames). :meth:`step` / :meth:`advance`
run cycles synchronously, for deterministic tests without the thread.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

import can
import numpy as np

from manisplat.drivers.piper import protocol as P
from manisplat.drivers.piper.sim_model import FEEDBACK_RATE_HZ, PiperModel, SimConfig
from manisplat.robot import RobotModel

log = logging.getLogger(__name__)

FRAME_SPACING_S = 130e-6  # one 8-byte standard frame at 1 Mbit/s, stuff bits included
MAX_CATCH_UP_STEPS = 200  # a longer stall (a suspended machine) is caught up in longer steps


class SimulatedPiper:
    """A simulated PiPER on ``bus``. See the module docstring.

    Args:
        bus: the simulator's own bus (e.g. virtual, ``preserve_timestamps=True``).
        robot: the model for limits and kinematics (default: built-in PiPER).
        config: dynamics and reported values (:class:`~.sim_model.SimConfig`).
        rate_hz: feedback cycle rate.
        clock: monotonic seconds for the thread's schedule.
        t0: timestamp of model time 0 on the frames (default: ``time.time()`` now).
    """

    def __init__(self, bus: can.BusABC, *, robot: RobotModel | None = None, config: SimConfig | None = None,
                 rate_hz: float = FEEDBACK_RATE_HZ, clock: Callable[[], float] = time.monotonic,
                 t0: float | None = None) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        self.bus = bus
        self.model = PiperModel(robot, config)
        self.period = 1.0 / rate_hz
        self.clock = clock
        self.t0 = time.time() if t0 is None else float(t0)
        self.cycles = 0
        self.overruns = 0  # times the thread fell behind the clock
        self.missed_cycles = 0  # cycles advanced then without feedback
        self.frames_sent = 0
        self.send_errors = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cycle_done = threading.Condition(self._lock)

    # -- running --------------------------------------------------------------------------------

    def step(self) -> None:
        """One cycle: read pending commands, advance by one period, send the feedback."""
        with self._lock:
            self._read_commands()
            self.model.step(self.period)
            t = self.t0 + self.model.time
            for i, frame in enumerate(self.model.feedback()):
                self._send(frame, t + i * FRAME_SPACING_S)
            self.cycles += 1
            self._cycle_done.notify_all()

    def _read_commands(self) -> None:
        """Apply every command pending on the bus, sending the model's replies (lock held)."""
        while (msg := self.bus.recv(timeout=0)) is not None:
            for reply in self.model.handle(P.decode_message(msg)):
                self._send(reply, self.t0 + self.model.time)

    def advance(self, seconds: float) -> None:
        """Run ``round(seconds * rate)`` cycles now, synchronously."""
        for _ in range(round(seconds / self.period)):
            self.step()

    def _send(self, frame: P.Frame, timestamp: float) -> None:
        try:
            self.bus.send(P.to_message(frame, timestamp=timestamp))
            self.frames_sent += 1
        except can.CanError as exc:
            self.send_errors += 1
            log.warning("SimulatedPiper: send failed: %s", exc)

    def start(self) -> SimulatedPiper:
        """Run cycles on a background thread until :meth:`stop`."""
        if self._thread is not None:
            raise RuntimeError("SimulatedPiper already started")
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="SimulatedPiper", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        deadline = self.clock()
        while not self._stop.is_set():
            try:
                self.step()
                deadline += self.period
                missed = int((self.clock() - deadline) / self.period)
                if missed > 0:
                    self._catch_up(missed)
                    deadline += missed * self.period
            except Exception:
                log.exception("SimulatedPiper: cycle failed; stopping")
                return
            delay = deadline - self.clock()
            if delay > 0:
                self._stop.wait(delay)

    def _catch_up(self, cycles: int) -> None:
        """The thread was starved (a loaded machine) for ``cycles`` periods: a real arm moved on
        meanwhile, so advance the dynamics by them (commands read first), without their feedback."""
        with self._lock:
            self._read_commands()
            steps = min(cycles, MAX_CATCH_UP_STEPS)
            for _ in range(steps):
                self.model.step(cycles * self.period / steps)
            self.overruns += 1
            self.missed_cycles += cycles

    def stop(self) -> None:
        """Stop the thread (the bus stays open: it belongs to the caller)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def wait_cycles(self, n: int, timeout: float = 2.0) -> None:
        """Block until ``n`` more cycles have run (TimeoutError otherwise)."""
        with self._lock:
            target = self.cycles + n
            if not self._cycle_done.wait_for(lambda: self.cycles >= target, timeout):
                raise TimeoutError(f"SimulatedPiper ran {self.cycles - target + n} of {n} cycles in {timeout} s")

    def __enter__(self) -> SimulatedPiper:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- state ----------------------------------------------------------------------------------

    def play(self, t: np.ndarray, q: np.ndarray, gripper: np.ndarray | None = None) -> None:
        """Play a recorded joint trajectory as the arm's feedback (see ``PiperModel.play``)."""
        with self._lock:
            self.model.play(t, q, gripper)

    def state(self) -> dict[str, object]:
        """A consistent copy of the model state: q, qd, target (rad), enabled, ctrl_mode,
        move_mode, speed_pct, estop, arm_status, gripper, gripper_target (m), time (s)."""
        m = self.model
        with self._lock:
            return {"q": m.q.copy(), "qd": m.qd.copy(), "target": m.target.copy(), "enabled": m.enabled.copy(),
                    "ctrl_mode": m.ctrl_mode, "move_mode": m.move_mode, "speed_pct": m.speed_pct,
                    "estop": m.estop, "arm_status": m.arm_status, "gripper": m.gripper,
                    "gripper_target": m.gripper_target, "gripper_enabled": m.gripper_enabled, "time": m.time,
                    "counts": dict(m.counts)}
