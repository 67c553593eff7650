"""The simulated PiPER, stepped by hand (deterministic): it follows targets only when enabled and
in CAN mode, with velocity limits and a lag, honours e-stop / reset / disable, answers queries,
plays back trajectories, and accepts the vendor SDK's exact wire bytes from any host."""

from __future__ import annotations

import math
import time

import can
import numpy as np
import pytest

from manisplat.drivers.piper import PiperModel, SimConfig, SimulatedPiper
from manisplat.drivers.piper import protocol as P
from manisplat.robot import builtin_piper

D = math.pi / 180


def send_raw(bus: can.BusABC, *texts: str) -> None:
    for text in texts:
        can_id, data = P.parse_candump(text)
        bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))


def drain(bus: can.BusABC) -> list[P.AnyFrame]:
    out = []
    while (msg := bus.recv(timeout=0)) is not None:
        out.append(P.decode_message(msg))
    return out


def model(**kwargs) -> PiperModel:
    return PiperModel(config=SimConfig(**kwargs))


def enable_can_j(m: PiperModel, speed: int = 100) -> None:
    m.handle(P.MotorEnable(7, True))
    m.handle(P.ModeCtrl(P.CtrlMode.CAN, P.MoveMode.J, speed))


def test_sdk_wire_bytes_from_another_host_drive_the_arm(sim: SimulatedPiper, host_bus: can.BusABC):
    """Exactly what piper_sdk 0.6.2 puts on the wire (reference §1.6), sent raw."""
    send_raw(host_bus, "471#0702000000000000", "151#0101320000000000", "155#0000271000004E20",
             "156#FFFF8AD000000000", "157#00003A98FFFFFFFF", "159#0000C35003E80100")
    sim.advance(3.0)
    q = sim.state()["q"]
    np.testing.assert_allclose(q, np.array([10, 20, -30, 0, 15, -0.001]) * D, atol=1e-6)
    assert sim.state()["gripper"] == pytest.approx(0.05, abs=1e-6)
    feedback = drain(host_bus)
    last = {type(f).__name__ + str(getattr(f, "pair", "")): f for f in feedback}
    assert last["JointFeedback0"].q_a == pytest.approx(10 * D, abs=1e-7)
    assert last["GripperFeedback"].width == pytest.approx(0.05, abs=1e-6) and last["GripperFeedback"].enabled
    send_raw(host_bus, "150#0100000000000000")  # EmergencyStop(0x01)
    sim.advance(0.02)
    assert sim.state()["estop"] and sim.state()["arm_status"] == P.ArmStatusCode.EMERGENCY_STOP
    send_raw(host_bus, "150#0200000000000000", "471#0701000000000000")  # reset, DisableArm(7)
    sim.advance(0.02)
    assert not sim.state()["estop"] and not sim.state()["enabled"].any()


def test_feedback_rates_and_order(sim: SimulatedPiper, host_bus: can.BusABC):
    sim.advance(1.0)  # 200 cycles
    frames = drain(host_bus)
    ids = [f.can_id for f in frames]
    counts = {i: ids.count(i) for i in set(ids)}
    assert all(counts[i] == 200 for i in [*range(0x2A1, 0x2A9), *range(0x251, 0x257)])
    assert all(counts[i] == 40 for i in range(0x261, 0x267))
    assert len(ids) == 3040
    assert ids[:8] == list(range(0x2A1, 0x2A9))


def test_nothing_moves_unless_enabled_and_in_can_joint_mode():
    m = model()
    target = np.array([0.5, 0.5, -0.5, 0.0, 0.0, 0.0])
    for frame in P.joint_ctrl_frames(target):
        m.handle(frame)
    m.step(1.0)
    assert np.all(m.q == 0)  # standby, disabled
    m.handle(P.MotorEnable(7, True))
    m.step(1.0)
    assert np.all(m.q == 0)  # enabled, but not in CAN control
    m.handle(P.ModeCtrl(P.CtrlMode.CAN, P.MoveMode.J, 100))
    assert np.all(m.target == m.q)  # entering CAN control resets a stale target
    for frame in P.joint_ctrl_frames(target):
        m.handle(frame)
    for _ in range(400):
        m.step(0.005)
    np.testing.assert_allclose(m.q, target, atol=1e-4)


def test_velocity_limit_times_speed_and_first_order_lag():
    m = model(tau_s=0.05)
    enable_can_j(m, speed=50)
    vmax = builtin_piper().velocity_limits
    target = np.array([2.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    for frame in P.joint_ctrl_frames(target):
        m.handle(frame)
    speeds = []
    for _ in range(100):
        m.step(0.005)
        speeds.append(m.qd[0])
    assert max(speeds) == pytest.approx(0.5 * vmax[0], rel=1e-9)  # capped at 50 % of pi rad/s
    # near the target the lag takes over: the error shrinks by exp(-dt / tau) per step
    while target[0] - m.q[0] > 0.01:
        m.step(0.005)
    err0 = target[0] - m.q[0]
    m.step(0.005)
    assert (target[0] - m.q[0]) / err0 == pytest.approx(math.exp(-0.005 / 0.05), rel=1e-6)


def test_target_beyond_limits_is_refused():
    m = model()
    enable_can_j(m)
    m.handle(P.JointCtrl(0, 3.0, 0.0))  # joint 1 limit is 150 deg
    assert m.arm_status == P.ArmStatusCode.TARGET_BEYOND_LIMIT and np.all(m.target == 0)
    m.handle(P.JointCtrl(0, 0.1, 0.2))
    assert m.arm_status == P.ArmStatusCode.NORMAL and m.target[0] == 0.1


def test_estop_holds_and_only_reset_leaves_it():
    m = model()
    enable_can_j(m)
    for frame in P.joint_ctrl_frames([1.0, 1.0, -1.0, 0, 0, 0]):
        m.handle(frame)
    m.step(0.05)
    m.handle(P.MotionCtrl1(P.EStop.STOP))
    held = m.q.copy()
    for frame in P.joint_ctrl_frames([0.2, 0.2, -0.2, 0, 0, 0]):
        assert m.handle(frame) == []
    m.handle(P.MotorEnable(7, True))
    for _ in range(100):
        m.step(0.005)
    assert np.all(m.q == held) and m.estop
    m.handle(P.MotionCtrl1(P.EStop.RESUME))
    assert not m.estop and not m.enabled.any() and m.ctrl_mode == P.CtrlMode.STANDBY
    enable_can_j(m)
    for frame in P.joint_ctrl_frames([0.2, 0.2, -0.2, 0, 0, 0]):
        m.handle(frame)
    for _ in range(400):
        m.step(0.005)
    np.testing.assert_allclose(m.q[:3], [0.2, 0.2, -0.2], atol=1e-4)


def test_disable_stops_following_and_reenable_does_not_jump():
    m = model()
    enable_can_j(m)
    for frame in P.joint_ctrl_frames([1.0, 1.0, -1.0, 0, 0, 0]):
        m.handle(frame)
    m.step(0.05)
    m.handle(P.MotorEnable(7, False))
    where = m.q.copy()
    m.step(0.5)
    assert np.all(m.q == where)
    m.handle(P.MotorEnable(7, True))
    assert np.all(m.target == where)  # the old target is forgotten
    m.step(0.5)
    np.testing.assert_allclose(m.q, where)


def test_queries_and_settings_are_answered():
    m = model()
    [reply] = m.handle(P.MotorParamQuery(1, 1))
    assert isinstance(reply, P.MotorLimitsReply) and reply.max_angle == pytest.approx(2.6179)
    assert isinstance(m.handle(P.MotorParamQuery(2, 2))[0], P.MotorMaxAccReply)
    assert m.handle(P.CollisionConfig((1, 2, 3, 4, 5, 6))) == [P.SettingReply(0x7A, 0)]
    assert m.handle(P.ParamQuery(query=2)) == [P.CollisionReply((1, 2, 3, 4, 5, 6))]
    firmware = m.handle(P.FirmwareData())
    assert b"".join(f.data for f in firmware) == SimConfig().firmware
    assert m.handle(P.JointConfig(1, set_zero=True)) == [P.SettingReply(0x75, 1)]
    # round trip through the wire: every reply encodes
    for frame in firmware + [reply]:
        P.encode(frame)


def test_invalid_and_unknown_frames_are_counted_and_ignored():
    m = model()
    assert m.handle(P.decode(0x151, bytes.fromhex("0909320000000000"))) == []
    assert m.handle(P.decode(0x7FF, b"\x01")) == []
    assert m.handle(P.JointFeedback(0, 1.0, 1.0)) == []  # another arm's feedback is no command
    assert m.counts == {"handled": 0, "ignored": 1, "invalid": 1, "unknown": 1}


def test_playback_of_a_recorded_trajectory(sim: SimulatedPiper, host_bus: can.BusABC):
    t = np.linspace(10.0, 11.0, 11)
    q = np.outer(np.linspace(0.0, 1.0, 11), [0.3, 0.4, -0.5, 0.1, -0.2, 0.6])
    sim.play(t, q, np.linspace(0.0, 0.07, 11))
    sim.advance(0.5)
    np.testing.assert_allclose(sim.state()["q"], q[5], atol=1e-12)
    sim.advance(1.0)  # held at the end
    np.testing.assert_allclose(sim.state()["q"], q[-1], atol=1e-12)
    assert sim.state()["gripper"] == pytest.approx(0.07)
    with pytest.raises(ValueError, match="increasing"):
        sim.play(t[::-1], q)
    with pytest.raises(ValueError, match=r"\(N, 6\)"):
        sim.play(t, q[:, :5])


def test_end_pose_feedback_is_the_sdk_forward_kinematics():
    m = model()
    m.q = np.array([0.2, 0.5, -0.5, 0.3, -0.2, 0.5])
    xyz, rpy = m.flange_pose()
    # piper_sdk's printed FK for this configuration (reference §1.9), mm and deg
    np.testing.assert_allclose(xyz * 1000, [104.836, 15.8, 360.983], atol=2e-3)
    np.testing.assert_allclose(np.degrees(rpy), [68.511, 41.469, 83.347], atol=2e-3)


def test_threaded_cycles_with_an_injected_clock(sim_bus: can.BusABC, host_bus: can.BusABC):
    sim = SimulatedPiper(sim_bus, rate_hz=400.0)
    with sim:
        sim.wait_cycles(20, timeout=5.0)
    assert sim.cycles >= 20 and sim.period == 1 / 400
    frames = drain(host_bus)
    assert len(frames) >= 20 * 14


class OffsetClock:
    """time.monotonic plus an offset the test moves: the simulator's thread sees time pass that it
    did not run (as when a loaded machine starves it)."""

    def __init__(self) -> None:
        self.offset = 0.0

    def __call__(self) -> float:
        return time.monotonic() + self.offset


def test_a_starved_simulator_keeps_up_with_the_clock_like_a_real_arm(sim_bus: can.BusABC, host_bus: can.BusABC):
    clock = OffsetClock()
    sim = SimulatedPiper(sim_bus, clock=clock)
    with sim:
        send_raw(host_bus, "471#0702000000000000", "151#0101320000000000", "155#0000271000004E20",
                 "156#FFFF8AD000000000", "157#00003A98FFFFFFFF")  # enable, CAN/J at 50 %, targets
        sim.wait_cycles(5, timeout=5.0)
        before = sim.state()["time"]
        clock.offset += 3.0  # 3 s the thread did not run
        sim.wait_cycles(5, timeout=5.0)
        state = sim.state()
    assert state["time"] - before >= 3.0
    # the arm reached its targets meanwhile (3 s of dynamics; the same move as stepped by hand above)
    np.testing.assert_allclose(state["q"], np.array([10, 20, -30, 0, 15, -0.001]) * D, atol=1e-6)
    assert sim.missed_cycles >= 590 and sim.overruns >= 1
