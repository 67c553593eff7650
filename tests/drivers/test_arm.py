"""PiperArm driving the simulated PiPER over a python-can virtual bus (real threads, real
python-can), plus its checks, its log tee, its health reports and how it leaves the arm."""

from __future__ import annotations

import math
import time

import can
import numpy as np
import pytest

from manisplat.drivers.base import Arm
from manisplat.drivers.piper import CommandError, PiperArm, PiperError
from manisplat.drivers.piper import protocol as P

TARGET = np.array([0.3, 0.6, -0.5, 0.2, -0.3, 0.4])


def wait_until(predicate, timeout: float = 5.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.005)


def converge(arm: PiperArm, target: np.ndarray, tol: float = 1e-3, timeout: float = 5.0) -> np.ndarray:
    state = arm.wait_for_joint_state()
    deadline = time.monotonic() + timeout
    while np.abs(state.q - target).max() > tol:
        assert time.monotonic() < deadline, f"did not converge: {state.q} vs {target}"
        state = arm.wait_for_joint_state(state.seq)
    return state.q


def test_enable_mode_move_gripper_estop_resume_disable(arm_on_sim):
    arm, sim = arm_on_sim
    assert isinstance(arm, Arm)
    arm.enable()
    assert all(arm.motors_enabled())
    arm.set_mode(speed_pct=100)
    wait_until(lambda: arm.status is not None and arm.status.ctrl_mode == P.CtrlMode.CAN, what="CAN mode")
    assert arm.status.mode_feed == P.MoveMode.J

    arm.move_joints(TARGET)
    q = converge(arm, TARGET)
    np.testing.assert_allclose(q, TARGET, atol=1e-3)
    wait_until(lambda: arm.status.motion_status == 0, what="motion status 'reached'")

    arm.gripper(0.05, 1.5)
    wait_until(lambda: abs(arm.gripper_state.width - 0.05) < 1e-4, what="gripper")
    assert arm.gripper_state.enabled and arm.gripper_state.effort == pytest.approx(1.5)
    assert arm.joint_state().gripper == pytest.approx(arm.gripper_state.width, abs=2e-3)

    # e-stop in the middle of a move: the arm stops and holds, commands are ignored
    arm.move_joints(np.zeros(6), speed_pct=10)
    arm.wait_for_joint_state(arm.joint_state().seq + 10)
    arm.estop()
    wait_until(lambda: arm.status.arm_status == P.ArmStatusCode.EMERGENCY_STOP, what="e-stop status")
    held = arm.wait_for_joint_state().q
    arm.move_joints(TARGET)
    s = arm.wait_for_joint_state(arm.joint_state().seq + 40)  # 0.2 s later
    np.testing.assert_allclose(s.q, held, atol=1e-9)
    assert np.abs(held).max() > 0.05  # it really stopped on the way

    arm.resume()
    assert all(arm.motors_enabled()) and not sim.state()["estop"]
    arm.set_mode(speed_pct=100)
    arm.move_joints(TARGET)
    converge(arm, TARGET)

    arm.disable()
    wait_until(lambda: not any(arm.motors_enabled()), what="motors disabled")
    before = arm.wait_for_joint_state().q
    arm.move_joints(np.zeros(6))
    after = arm.wait_for_joint_state(arm.joint_state().seq + 20).q
    np.testing.assert_allclose(after, before, atol=1e-9)

    stats = arm.stats()
    assert stats.invalid == 0 and stats.frames == stats.valid
    assert stats.joint_samples > 50
    # the simulated arm's rates, less the cycles a starved thread caught up on without feedback
    joints = stats.per_id[0x2A5]
    sent = 1.0 - sim.missed_cycles / (200.0 * (joints.last_t - joints.first_t))
    assert joints.rate_hz == pytest.approx(200 * sent, rel=0.01)
    assert stats.per_id[0x261].rate_hz == pytest.approx(40 * sent, rel=0.01)
    assert arm.health().ok


def test_leaving_the_context_holds_the_measured_position(channel, sim):
    sim.start()
    with PiperArm(can.Bus(interface="virtual", channel=channel), own_bus=True) as arm:
        arm.enable()
        arm.move_joints(TARGET, speed_pct=5)  # slow: still moving when we leave
        arm.wait_for_joint_state(arm.wait_for_joint_state().seq + 40)
    sim.wait_cycles(2)  # the hold frames are queued on the sim's bus; its next full cycle reads them
    state = sim.state()
    assert np.abs(state["q"] - TARGET).max() > 0.1  # it was still on its way
    assert np.abs(state["target"] - state["q"]).max() < 0.02  # the target became the measured position
    assert state["enabled"].all() and not state["estop"]  # no disable, no reset
    sim.wait_cycles(80)
    np.testing.assert_allclose(sim.state()["q"], state["target"], atol=1e-3)  # and it stopped there


def test_an_exception_inside_the_context_still_holds(channel, sim):
    sim.start()
    with pytest.raises(RuntimeError, match="boom"):
        with PiperArm(can.Bus(interface="virtual", channel=channel), own_bus=True) as arm:
            arm.enable()
            arm.move_joints(TARGET, speed_pct=5)
            arm.wait_for_joint_state(arm.wait_for_joint_state().seq + 20)
            raise RuntimeError("boom")
    sim.wait_cycles(2)  # as above: let the simulated arm read the hold frames
    state = sim.state()
    assert np.abs(state["target"] - state["q"]).max() < 0.02 and state["enabled"].all()


def test_a_reading_arm_sends_nothing_on_close(channel, sim, host_bus):
    sim.start()
    with PiperArm(can.Bus(interface="virtual", channel=channel), own_bus=True, read_only=True) as arm:
        arm.wait_for_joint_state(timeout=5.0)
        with pytest.raises(PiperError, match="read-only"):
            arm.enable()
    sim.stop()
    frames = [P.decode_message(m) for m in iter(lambda: host_bus.recv(0), None)]
    assert frames and not any(getattr(f, "COMMAND", False) for f in frames)


def test_commands_are_checked_before_sending(arm_on_sim):
    arm, sim = arm_on_sim
    with pytest.raises(CommandError, match="non-finite"):
        arm.move_joints([0, 0, float("nan"), 0, 0, 0])
    with pytest.raises(CommandError, match=r"shape \(6,\)"):
        arm.move_joints([0, 0, 0])
    with pytest.raises(CommandError, match="joint2 -10.000 deg not in"):
        arm.move_joints(np.radians([0, -10, 0, 0, 0, 0]))
    with pytest.raises(CommandError, match="not a sequence"):
        arm.move_joints("abc")
    with pytest.raises(CommandError, match="speed_pct"):
        arm.move_joints(np.zeros(6), speed_pct=0)
    with pytest.raises(CommandError, match="gripper width"):
        arm.gripper(0.1)
    with pytest.raises(CommandError, match="effort"):
        arm.gripper(0.03, effort_nm=6.0)
    arm.move_joints(np.zeros(6), speed_pct=50)
    with pytest.raises(CommandError, match="speed limit"):
        arm.move_joints([0.1, 0, 0, 0, 0, 0], speed_pct=50, dt=0.01)  # 10 rad/s > 1.57
    arm.move_joints([0.01, 0, 0, 0, 0, 0], speed_pct=50, dt=0.01)  # 1 rad/s is fine
    assert sim.state()["counts"]["invalid"] == 0


def test_tee_writes_every_frame_received_and_sent(channel, sim, tmp_path):
    """The virtual channel's name ends in digits at random (a uuid); BLF channels are small ints."""
    sim.start()
    for suffix in (".blf", ".asc"):
        path = tmp_path / f"tee{suffix}"
        with PiperArm(can.Bus(interface="virtual", channel=channel), own_bus=True, log_path=path) as arm:
            arm.wait_for_joint_state(arm.wait_for_joint_state(timeout=5.0).seq + 20)
            arm.enable()
            received = arm.stats().frames
            assert arm.tee_errors == 0
        with can.LogReader(path) as reader:
            logged = list(reader)
        enables = [m for m in logged if m.arbitration_id == 0x471]
        assert enables and all(not m.is_rx for m in enables) and bytes(enables[0].data) == bytes.fromhex("0702000000000000")
        assert sum(m.is_rx for m in logged) >= received


def test_health_reports_silence_and_bus_off(channel, sim, host_bus):
    changes = []
    sim.start()
    with PiperArm(can.Bus(interface="virtual", channel=channel), own_bus=True, silence_timeout_s=0.1,
                  on_health=changes.append) as arm:
        arm.wait_for_joint_state(timeout=5.0)
        wait_until(lambda: arm.health().ok, what="ok")
        sim.stop()
        wait_until(lambda: "silent" in [h.state for h in changes], what="silent reported")
        assert arm.health().state == "silent" and "no PiPER feedback" in arm.health().detail
        # a bus-off error frame as socketcan delivers it (CAN_ERR_BUSOFF in the ID)
        host_bus.send(can.Message(arbitration_id=0x40, is_error_frame=True, data=bytes(8), is_extended_id=False))
        wait_until(lambda: arm.health().state == "bus_off", what="bus_off")
        assert arm.stats().bus_off_events == 1 and arm.stats().error_frames == 1
        wait_until(lambda: "bus_off" in [h.state for h in changes], what="bus_off reported")
        sim.start()
        wait_until(lambda: arm.health().ok, what="recovery")
        wait_until(lambda: [h.state for h in changes][-1:] == ["ok"], what="callback")
    states = [h.state for h in changes]
    assert states[0] == "ok" and "silent" in states and "bus_off" in states


def test_enable_times_out_without_an_arm(channel):
    with PiperArm(can.Bus(interface="virtual", channel=channel), own_bus=True) as arm:
        t0 = time.monotonic()
        with pytest.raises(PiperError, match="did not report all motors enabled"):
            arm.enable(timeout=0.2)
        assert time.monotonic() - t0 < 2.0
        assert arm.health().state == "waiting"
        with pytest.raises(TimeoutError, match="no joint sample"):
            arm.wait_for_joint_state(timeout=0.05)


def test_open_reports_a_missing_interface_clearly():
    with pytest.raises(PiperError, match="cannot open CAN socketcan 'nosuchcan0'"):
        PiperArm.open("nosuchcan0")


def test_joint_listener_sees_every_sample(arm_on_sim):
    arm, sim = arm_on_sim
    seen = []
    arm.add_joint_listener(seen.append)
    first = arm.wait_for_joint_state()
    arm.wait_for_joint_state(first.seq + 30)
    seqs = [s.seq for s in seen]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))) and len(seqs) >= 30
    assert all(math.isfinite(s.t) and s.q.shape == (6,) for s in seen)
