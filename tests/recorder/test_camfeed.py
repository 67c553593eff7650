"""A camera feed counts each silence longer than its stall limit once, however its reads fall."""

from __future__ import annotations

import time

import numpy as np

from manisplat.drivers.base import CameraFrame
from manisplat.recorder.camfeed import CameraFeed
from manisplat.recorder.clock import ManualClock


class _ScriptedCamera:
    """Reads follow a script on a manual clock: ("frame", dt) moves the clock dt s on and returns a
    frame; ("timeout", dt) moves it on and raises TimeoutError; then the camera ends (None)."""

    def __init__(self, clock: ManualClock, script: list[tuple[str, float]]) -> None:
        self.clock, self.script, self.seq = clock, list(script), 0

    def read(self, timeout: float) -> CameraFrame | None:
        if not self.script:
            return None
        what, dt = self.script.pop(0)
        self.clock.advance_to(self.clock.monotonic() + dt)
        if what == "timeout":
            raise TimeoutError
        self.seq += 1
        return CameraFrame(seq=self.seq, t=self.clock.monotonic(), rgb=np.zeros((4, 4, 3), np.uint8))


def _stalls(script: list[tuple[str, float]]) -> int:
    clock = ManualClock()
    feed = CameraFeed("cam", _ScriptedCamera(clock, script), clock, latency_s=0.0, depth=False, stall_after_s=0.5)
    feed.start(clock.monotonic())
    deadline = time.monotonic() + 30.0
    while not feed.done and time.monotonic() < deadline:  # the thread reads the script to its end
        time.sleep(0.001)
    feed.stop()
    assert feed.ended and feed.error is None
    return feed.stats.stalls


def test_a_silence_is_a_stall_whether_the_reader_saw_it_or_only_its_end():
    steady = [("frame", 0.033)] * 5
    # the read after the silence returned only when the next frame came, 1 s later
    assert _stalls(steady + [("frame", 1.0)] + steady) == 1
    # the reader timed out through the silence: counted while it lasted, not again at its end
    assert _stalls(steady + [("timeout", 0.2)] * 5 + [("frame", 0.05)] + steady) == 1
    # two silences, one of each kind; and a gap under the limit is none
    assert _stalls(steady + [("frame", 1.0)] + steady + [("timeout", 0.3)] * 3 + [("frame", 0.01)]) == 2
    assert _stalls(steady + [("frame", 0.4)] + steady) == 0
