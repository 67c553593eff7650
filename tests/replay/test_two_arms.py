"""manisplat-replay on two arms (a version 2 episode): the arm-against-arm check refuses a
trajectory made to collide before anything moves, the arms are streamed in lock-step from one
clock on two simulated PiPERs on two virtual buses, and each arm reports its tracking."""

from __future__ import annotations

import math
import re
import threading
import uuid
from pathlib import Path
from typing import Iterator

import can
import numpy as np
import pytest

from manisplat.drivers.piper import SimConfig, SimulatedPiper
from manisplat.drivers.piper.streamer import CommandAudit, StreamConfig, replay_arms
from manisplat.drivers.piper.trajectory import Trajectory
from manisplat.drivers.replay_cli import SimArm, main
from tests.replay.test_streamer import wait_for
from tests.replay.helpers import NEW_URDF, base_at, smooth_motion, write_arms_episode, write_urdf

BASES = {"left": base_at(0.3), "right": base_at(-0.3)}  # a Cobot Magic: 0.6 m apart, facing +x
READY = np.radians([0.0, 60.0, -60.0, 0.0, 0.0, 0.0])  # reaching forward, TCP 0.35 m ahead
NO_TARGETS = "0 resets (0x150 B0=2), 0 disables (0x471 01), 0 e-stops, 0 joint targets"
RELAXED = ["--feedback-timeout-ms", "2000", "--max-tracking-error-deg", "20"]  # a loaded CI must not trip these
# (a starved simulated arm on the 2-core CI once went 509 ms without feedback)


def swing_in(amplitude_deg: float, duration: float = 3.0, fps: float = 20.0) -> tuple[np.ndarray, dict, dict]:
    """Both arms turn joint1 towards each other by ``amplitude_deg`` and back (1 - cos): 60 deg puts
    their grippers into each other at the middle frame, 20 deg keeps them 25 cm apart."""
    t = np.arange(0.0, duration + 1e-9, 1.0 / fps)
    s = 0.5 * (1 - np.cos(2 * np.pi * t / duration))
    q = {}
    for name, sign in (("left", -1.0), ("right", 1.0)):
        q[name] = np.tile(READY, (len(t), 1))
        q[name][:, 0] += sign * math.radians(amplitude_deg) * s
    return t, q, {name: np.full(len(t), 0.05) for name in q}


@pytest.fixture
def colliding(tmp_path: Path) -> Path:
    t, q, g = swing_in(60.0)
    return write_arms_episode(tmp_path / "colliding", t, q, g, BASES)


@pytest.fixture
def clear(tmp_path: Path) -> Path:
    t, q, g = swing_in(20.0, duration=1.5)
    return write_arms_episode(tmp_path / "clear", t, q, g, BASES)


class BusArm:
    """A simulated PiPER on a named virtual channel, audited: the "real" arm the CLI opens with
    ``--interface virtual --arm NAME=CHANNEL``."""

    def __init__(self, q0: np.ndarray) -> None:
        self.channel = f"test-two-arms-{uuid.uuid4().hex}"
        self.bus = can.Bus(interface="virtual", channel=self.channel, preserve_timestamps=True)
        self.sim = SimulatedPiper(self.bus, config=SimConfig(q0=q0, gripper0=0.05)).start()
        self.audit = CommandAudit()
        self._audit_bus = can.Bus(interface="virtual", channel=self.channel)
        self._notifier = can.Notifier(self._audit_bus, [self.audit], timeout=0.1)

    def close(self) -> None:
        self.sim.stop()
        self._notifier.stop()
        self._audit_bus.shutdown()
        self.bus.shutdown()


@pytest.fixture
def bus_arms() -> Iterator[dict[str, BusArm]]:
    arms = {name: BusArm(READY) for name in ("left", "right")}
    yield arms
    for arm in arms.values():
        arm.close()


def test_the_arm_arm_check_refuses_a_colliding_trajectory_and_nothing_moves(
        colliding: Path, bus_arms: dict[str, BusArm], capsys: pytest.CaptureFixture) -> None:
    channels = [f"--arm={name}={arm.channel}" for name, arm in bus_arms.items()]
    code = main([str(colliding), "--interface", "virtual", *channels, *RELAXED])
    out, err = capsys.readouterr()
    assert code == 4, out + err
    assert "refused, nothing was sent" in err and "the arms come closer than 10 mm (--min-arm-clearance-mm)" in err
    found = re.search(r"first at frame (\d+) \(t [0-9.]+ s\); closest at frame (\d+) \(t ([0-9.]+) s\): "
                      r"left/link\d and right/link\d overlap by ([0-9.]+) mm", err)
    assert found, err
    first, closest, t_closest, overlap = int(found[1]), int(found[2]), float(found[3]), float(found[4])
    assert 5 < first < closest < 35 and t_closest == pytest.approx(closest / 20) and overlap > 10  # the swing's peak
    for arm in bus_arms.values():
        arm.sim.wait_cycles(20)  # anything sent would have reached the simulated arm by now
        assert arm.audit.joint_targets == 0 and arm.audit.modes == 0 and arm.audit.enables == 0


def test_the_same_swing_kept_apart_passes_the_check_on_the_same_arms(
        clear: Path, bus_arms: dict[str, BusArm], capsys: pytest.CaptureFixture) -> None:
    channels = [f"--arm={name}={arm.channel}" for name, arm in bus_arms.items()]
    assert main([str(clear), "--interface", "virtual", *channels, "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "arms' closest approach: left/link" in out and "all checks pass" in out and "nothing was sent" in out
    assert all(arm.audit.joint_targets == 0 for arm in bus_arms.values())


def test_a_move_to_the_start_through_the_other_arm_is_refused_with_the_simulated_arms_untouched(
        clear: Path, capsys: pytest.CaptureFixture) -> None:
    # the simulated arms start turned into each other (a clear trajectory, a colliding start)
    code = main([str(clear), "--sim", "--sim-start", "left=-70,60,-60,0,0,0", "--sim-start", "right=70,60,-60,0,0,0",
                 "--max-start-distance-deg", "80", *RELAXED])
    out, err = capsys.readouterr()
    assert code == 4, out + err
    assert "first at 0.00 s into the move to the start" in err and "overlap by" in err
    assert f"simulated bus of left: {NO_TARGETS}" in out and f"simulated bus of right: {NO_TARGETS}" in out


def test_two_arms_replay_on_two_simulated_arms_with_each_arms_tracking(
        clear: Path, capsys: pytest.CaptureFixture) -> None:
    assert main([str(clear), "--sim", *RELAXED]) == 0
    out = capsys.readouterr().out
    assert out.count("outcome: completed") == 2 and out.count("tracking error, deg (J1..J6)") == 2
    for name in ("left", "right"):
        assert out.count(f"arm {name}:") == 2  # its checks, then its report
        assert f"simulated bus of {name}: 0 resets (0x150 B0=2), 0 disables (0x471 01), 0 e-stops" in out
        block = out.split(f"arm {name}:")[2]
        final = [float(v) for v in block.split("final error, deg:")[1].split("\n")[0].split()]
        assert max(final) <= 0.5


def test_every_arm_is_commanded_at_every_tick_of_one_clock() -> None:
    t, q_l, g = smooth_motion(1.5)
    _, q_r, _ = smooth_motion(1.5, amplitude_deg=-8.0)
    trajs = {"left": Trajectory(t, q_l, g, "joints", 1.0), "right": Trajectory(t, q_r, g, "joints", 1.0)}
    sims = {name: SimArm(tr.q[0] + math.radians(2.0), 0.05) for name, tr in trajs.items()}
    try:
        reports = replay_arms({name: (sims[name].arm, tr) for name, tr in trajs.items()},
                              StreamConfig(feedback_timeout_s=0.5, max_tracking_error_deg=20.0))
    finally:
        for sim in sims.values():
            sim.close()
    left, right = reports["left"], reports["right"]
    assert left.outcome == right.outcome == "completed", (left, right)
    assert left.ticks == right.ticks > 20
    np.testing.assert_array_equal(left.streamed_at_s, right.streamed_at_s)  # the same time, tick by tick
    assert left.streamed_at_s[-1] == pytest.approx(1.5) and np.all(np.diff(left.streamed_at_s) > 0)
    for name, sim in sims.items():
        assert sim.audit.resets == sim.audit.disables == sim.audit.estops == 0
        np.testing.assert_allclose(sim.sim.state()["q"], trajs[name].q[-1], atol=math.radians(0.5))


def test_a_stop_on_one_arm_stops_both_holding() -> None:
    t, q, g = smooth_motion(8.0)
    trajs = {name: Trajectory(t, q, g, "joints", 1.0) for name in ("left", "right")}
    sims = {name: SimArm(q[0] + math.radians(2.0), 0.05) for name in trajs}
    result: dict = {}
    streamed: list[float] = []  # the stream's progress reports, seconds into the trajectory
    # 0.5 s: the silent arm is noticed well before the end; the other's feedback, starved on a
    # loaded machine, must not be the one that goes stale first
    config = StreamConfig(feedback_timeout_s=0.5, max_tracking_error_deg=20.0)
    thread = threading.Thread(target=lambda: result.setdefault(
        "r", replay_arms({name: (sims[name].arm, tr) for name, tr in trajs.items()}, config,
                         on_progress=lambda s, _planned: streamed.append(s))), daemon=True)
    try:
        thread.start()
        wait_for(lambda: streamed and streamed[-1] >= 0.5)  # streaming (on the stream's own clock, not a tick count)
        stopped_at = streamed[-1]
        sims["right"].sim.stop()  # the right arm goes silent
        thread.join(20.0)
    finally:
        for sim in sims.values():
            sim.close()
    reports = result["r"]
    for report in reports.values():
        assert report.outcome == "feedback_lost" and report.detail.startswith("right: no joint feedback"), report
        assert stopped_at <= report.streamed_s < 8.0 - 0.5
    assert reports["left"].left.startswith("holding") and "no fresh feedback" not in reports["left"].left
    assert "last target sent (no fresh feedback" in reports["right"].left
    assert all(sim.audit.resets == sim.audit.disables == sim.audit.estops == 0 for sim in sims.values())


def test_two_arms_need_every_arms_channel(clear: Path, capsys: pytest.CaptureFixture) -> None:
    assert main([str(clear), "--can", "can0"]) == 2
    assert "--arm left=CHANNEL --arm right=CHANNEL" in capsys.readouterr().err
    assert main([str(clear), "--arm", "left=can0"]) == 2
    assert "missing: right" in capsys.readouterr().err


def test_an_arm_without_link_geometry_is_refused_by_name(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    write_urdf(tmp_path / "piper_new.urdf", NEW_URDF)  # joints only: nothing to collide
    t, q, g = swing_in(20.0, duration=1.5)
    ep = write_arms_episode(tmp_path / "ep", t, q, g, BASES, description="../piper_new.urdf")
    assert main([str(ep), "--sim", "--dry-run"]) == 4
    assert "arm left: " in capsys.readouterr().err


def test_three_arms_are_checked_pair_by_pair(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Nothing is special about two: a third arm between them is checked against both."""
    t, q, g = swing_in(40.0, duration=3.0)  # left and right keep 45 mm apart; an arm between them does not
    q["middle"], g["middle"] = np.tile(READY, (len(t), 1)), g["left"]
    ep = write_arms_episode(tmp_path / "ep", t, q, g, {**BASES, "middle": base_at(0.0)})
    assert main([str(ep), "--sim", "--dry-run"]) == 4
    closest = capsys.readouterr().err.split("closest at")[1]
    assert "/link" in closest and "middle/link" in closest and "overlap by" in closest, closest
    far = write_arms_episode(tmp_path / "far", t, q, g, {"left": base_at(0.9), "middle": base_at(0.0),
                                                          "right": base_at(-0.9)})
    assert main([str(far), "--sim", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert all(f"arm {name}:" in out for name in ("left", "middle", "right")) and "all checks pass" in out
    assert out.count(NO_TARGETS) == 3
