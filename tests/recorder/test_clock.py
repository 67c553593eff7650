"""One monotonic timeline: the wall-monotonic offset, its uncertainty, and wall-clock steps."""

from __future__ import annotations

import threading
import time

import pytest

from manisplat.recorder.clock import ClockMap, ManualClock, RealDeadline, ScaledClock, SystemClock, measure_offset


def test_offset_of_a_manual_clock_is_exact() -> None:
    clock = ManualClock(start=50.0, wall_offset=1.7e9 + 0.123456)
    s = measure_offset(clock)
    assert s.offset == pytest.approx(1.7e9 + 0.123456, abs=1e-6) and s.uncertainty == 0.0 and s.t_mono == 50.0


def test_system_clock_offset_is_bracketed_tightly() -> None:
    s = measure_offset(SystemClock(), tries=50)
    assert s.uncertainty < 1e-3
    assert abs((time.time() - time.monotonic()) - s.offset) < 5e-3


def test_clock_map_follows_a_wall_clock_step_and_reports_it() -> None:
    clock = ManualClock(start=10.0, wall_offset=1000.0)
    cmap = ClockMap(clock, remeasure_s=1.0)
    assert cmap.to_mono(1010.5) == pytest.approx(10.5)
    clock.advance_to(10.5)
    cmap.maybe_remeasure()  # too early: nothing measured
    assert len(cmap.samples) == 1
    clock.wall_offset += 0.25  # an NTP step of +250 ms
    clock.advance_to(11.0)
    cmap.maybe_remeasure()
    assert cmap.to_mono(1011.25 + 1.0) == pytest.approx(12.0)
    info = cmap.describe()
    assert info["wall_clock_steps"] == [{"t_monotonic": 11.0, "change_s": pytest.approx(0.25)}]
    assert info["offset_range_s"] == [pytest.approx(1000.0), pytest.approx(1000.25)]
    assert cmap.describe(since=10.9)["offset_measurements"] == 1


def test_manual_clock_sleep_wakes_on_advance_and_on_stop() -> None:
    clock = ManualClock(start=0.0)
    woke = threading.Event()

    def sleeper() -> None:
        if clock.sleep_until(1.0):
            woke.set()

    thread = threading.Thread(target=sleeper, daemon=True)
    thread.start()
    clock.advance_to(0.5)
    assert not woke.wait(0.1)
    clock.advance_to(1.0)
    assert woke.wait(5.0)
    thread.join(5.0)
    assert not thread.is_alive()
    stop = threading.Event()
    stop.set()
    assert clock.sleep_until(2.0, stop) is False
    assert clock.sleep_until(3.0, RealDeadline(0.05)) is False  # a stopped clock cannot hang a wait
    assert clock.advance_to(0.2) is None and clock.monotonic() == 1.0  # never backwards


def test_scaled_clock_runs_faster_than_real_time() -> None:
    clock = ScaledClock(speed=50.0, start=0.0, wall_offset=10.0)
    real = time.monotonic()
    assert clock.sleep_until(1.0)  # one simulated second
    elapsed = time.monotonic() - real
    assert 0.015 < elapsed < 2.0
    assert clock.wall() - clock.monotonic() == pytest.approx(10.0, abs=0.05)
    with pytest.raises(ValueError):
        ScaledClock(speed=0.0)
