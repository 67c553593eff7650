"""CAN replay: a python-can log (BLF, ASC, candump .log, CSV) played onto a virtual bus, with the
recorded timing or as fast as possible, read by an unchanged PiperArm; and 100k fuzzed frames
through the reader."""

from __future__ import annotations

import time
import uuid
from pathlib import Path

import can
import numpy as np
import pytest

from manisplat.drivers.piper import PiperArm, SimulatedPiper
from manisplat.drivers.piper import protocol as P
from manisplat.drivers.piper.logdecode import CanArrays, decode_arrays
from manisplat.drivers.replay import CanLogPlayer

SECONDS = 1.0


def trajectory() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.linspace(0.0, SECONDS, 51)
    s = np.sin(2 * np.pi * t)[:, None]
    q = s * np.array([0.3, 0.2, -0.25, 0.5, -0.4, 0.6]) + np.array([0.0, 0.8, -0.8, 0.0, 0.0, 0.0])
    return t, q, 0.035 + 0.03 * s[:, 0]


def record_log(path: Path, seconds: float = SECONDS, extra: list[can.Message] = ()) -> list[can.Message]:
    """A log of a simulated PiPER playing :func:`trajectory`, written by python-can's writer."""
    channel = f"rec-{uuid.uuid4().hex}"
    sim_bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    rx = can.Bus(interface="virtual", channel=channel)
    sim = SimulatedPiper(sim_bus, t0=1_700_000_000.0)
    sim.play(*trajectory())
    sim.advance(seconds)
    messages = list(iter(lambda: rx.recv(0), None)) + list(extra)
    with can.Logger(path) as writer:
        for msg in messages:
            msg.channel = 0
            writer.on_message_received(msg)
    sim_bus.shutdown()
    rx.shutdown()
    return messages


@pytest.mark.parametrize("suffix", [".blf", ".asc", ".log", ".csv"])
def test_piper_arm_reads_a_replayed_log_exactly(tmp_path, suffix):
    path = tmp_path / f"run{suffix}"
    record_log(path)
    file_frames = CanArrays.read(path)
    t_log, q_log, _ = decode_arrays(file_frames).joint_samples()
    assert len(t_log) == 200  # 1 s at 200 Hz
    seen = []
    with PiperArm.open_log(path, realtime=False, on_joint_state=seen.append) as arm:
        assert arm.replay_done(timeout=20.0), arm.health()
        stats = arm.stats()
        assert arm.health().state == "ended"
    assert stats.frames == len(file_frames) == 3040 and stats.invalid == 0
    q = np.array([s.q for s in seen])
    t = np.array([s.t for s in seen])
    np.testing.assert_array_equal(q, q_log)  # bit for bit what the file holds
    np.testing.assert_array_equal(t, t_log)
    # and it is the simulated trajectory, to half the protocol's 0.001 deg, plus what the float
    # resolution of epoch timestamps (2.4e-7 s at 1.7e9 s) makes of a 4 rad/s motion
    tt, qq, _ = trajectory()
    expected = np.array([np.interp(t - t[0] + 0.005, tt, qq[:, j]) for j in range(6)]).T
    np.testing.assert_allclose(q, expected, rtol=0, atol=np.radians(0.0005) + 2e-6)


def test_realtime_replay_keeps_the_recorded_timing(tmp_path):
    path = tmp_path / "run.blf"
    record_log(path, seconds=0.5)
    for speed, expected in ((1.0, 0.5), (4.0, 0.125)):
        t0 = time.monotonic()
        with PiperArm.open_log(path, realtime=True, speed=speed) as arm:
            assert arm.replay_done(timeout=10.0)
            elapsed = time.monotonic() - t0
            assert arm.stats().joint_samples == 100
            assert arm.stats().per_id[0x2A5].rate_hz == pytest.approx(200.0, rel=1e-3)  # recorded stamps
        assert expected * 0.9 < elapsed < expected + 1.0


def test_player_on_a_bus_of_ones_own(tmp_path):
    path = tmp_path / "run.asc"
    messages = record_log(path, seconds=0.2)
    with CanLogPlayer(path, realtime=False) as player:
        rx = player.open_bus()
        player.start()
        assert player.wait(5.0) and player.error is None
        got = list(iter(lambda: rx.recv(0.5), None))
        rx.shutdown()
    assert player.sent == len(messages) == len(got)
    assert [m.arbitration_id for m in got] == [m.arbitration_id for m in messages]
    assert [bytes(m.data) for m in got] == [bytes(m.data) for m in messages]
    assert got[0].timestamp == pytest.approx(0.0, abs=1e-9)  # ASC logs start at 0
    with pytest.raises(FileNotFoundError):
        CanLogPlayer(tmp_path / "missing.blf")


def fuzz_messages(n: int, seed: int = 0) -> list[can.Message]:
    rng = np.random.default_rng(seed)
    known = np.array(sorted(P.REGISTRY) + sorted(P.UNDOCUMENTED_IDS))
    out = []
    for i in range(n):
        r = rng.random()
        extended = rng.random() < 0.03
        can_id = int(known[rng.integers(len(known))] if r < 0.6 else rng.integers(0, 1 << 11))
        if extended and rng.random() < 0.5:
            can_id = int(rng.integers(0, 1 << 29))
        fd = rng.random() < 0.01
        length = int(rng.choice([12, 16, 64])) if fd else int(8 if rng.random() < 0.7 else rng.integers(0, 9))
        out.append(can.Message(timestamp=1e-4 * i, arbitration_id=can_id, is_extended_id=extended,
                               data=rng.integers(0, 256, length, dtype=np.uint8).tobytes(), is_fd=fd,
                               is_remote_frame=not fd and rng.random() < 0.02,
                               is_error_frame=rng.random() < 0.02, check=False))
    return out


def test_100k_fuzzed_frames_through_the_reader(channel):
    messages = fuzz_messages(100_000)
    expected = decode_arrays(CanArrays.from_messages(messages)).counts()
    arm = PiperArm(can.Bus(interface="virtual", channel=channel), own_bus=True, read_only=True)
    sender = can.Bus(interface="virtual", channel=channel)
    try:
        for msg in messages:
            sender.send(msg)
        arm.wait_for_frames(len(messages), timeout=60.0)
        stats = arm.stats()
    finally:
        sender.shutdown()
        arm.close()
    assert stats.frames == 100_000
    assert stats.valid + stats.invalid + stats.unknown + stats.undocumented == 100_000
    assert {"valid": stats.valid, "invalid": stats.invalid, "unknown": stats.unknown,
            "undocumented": stats.undocumented} == expected
    assert stats.read_errors == 0 and min(expected.values()) > 1000
    assert sum(stats.invalid_by_id.values()) == stats.invalid
