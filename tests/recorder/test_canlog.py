"""The raw CAN log beside an episode: time zero at the episode start, every frame from then,
readable by python-can; torn logs are cut back to their last whole line."""

from __future__ import annotations

from pathlib import Path

import can
import pytest

from manisplat.recorder.canlog import CanLogSink, repair_can_log

T0 = 1_700_000_000.25


def msg(can_id: int, t: float, channel: object = "virtual-ch-x") -> can.Message:
    return can.Message(arbitration_id=can_id, data=bytes([can_id & 0xFF] * 8), is_extended_id=False, timestamp=t,
                       channel=channel)


def test_log_starts_at_time_zero_with_the_frames_since(tmp_path: Path) -> None:
    sink = CanLogSink()
    sink.on_message_received(msg(0x2A1, T0 - 0.010))  # before the episode: not logged
    sink.on_message_received(msg(0x2A2, T0 + 0.001))  # during the set-up: logged
    sink.open(tmp_path / "can.asc", T0)
    for k in range(5):
        sink.on_message_received(msg(0x2A5, T0 + 0.01 * (k + 1), channel=0))
    assert sink.drain() == 6
    sink.seal()
    sink.on_message_received(msg(0x2A6, T0 + 1.0))  # after the end: not in this log
    sink.close()
    got = list(can.LogReader(tmp_path / "can.asc"))
    assert [m.arbitration_id for m in got] == [0x2A2] + [0x2A5] * 5
    assert [m.timestamp for m in got] == pytest.approx([0.001, 0.01, 0.02, 0.03, 0.04, 0.05], abs=1e-6)
    assert got[-1].data == bytes([0xA5] * 8)
    assert (sink.received, sink.written, sink.dropped) == (6, 6, 0)


def test_a_full_queue_counts_what_it_drops(tmp_path: Path) -> None:
    sink = CanLogSink(max_queued=3)
    sink.open(tmp_path / "can.asc", T0)
    for k in range(5):
        sink.on_message_received(msg(0x2A5, T0 + k))
    assert (sink.received, sink.dropped) == (3, 2)
    sink.close()
    assert len(list(can.LogReader(tmp_path / "can.asc"))) == 3


def test_repair_cuts_a_torn_last_line_and_keeps_it(tmp_path: Path) -> None:
    sink = CanLogSink()
    sink.open(tmp_path / "can.asc", T0)
    for k in range(4):
        sink.on_message_received(msg(0x2A5, T0 + 0.001 * k))
    sink.drain()
    sink.abandon()  # as a killed process leaves it: no end block
    path = tmp_path / "can.asc"
    whole = path.read_bytes()
    path.write_bytes(whole + b" 0.004000 1  2A5             Rx   d 8 00 0")
    assert repair_can_log(path, tmp_path / "backup") == len(b" 0.004000 1  2A5             Rx   d 8 00 0")
    assert path.read_bytes() == whole
    assert (tmp_path / "backup" / "can.asc.torn").read_bytes().startswith(b" 0.004000")
    assert len(list(can.LogReader(path))) == 4
    assert repair_can_log(path, tmp_path / "backup") == 0  # already whole
