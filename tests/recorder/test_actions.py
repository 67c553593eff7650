"""Leader-arm commands (0x155..0x157, 0x159) seen on the bus become the action at a frame's time."""

from __future__ import annotations

import numpy as np
import pytest

from manisplat.drivers.piper import protocol as P
from manisplat.recorder.actions import LeaderCommands
from manisplat.recorder.sync import FLAG_ACTION_STALE


def send(listener: LeaderCommands, frame: P.Frame, t: float) -> None:
    listener.on_message_received(P.to_message(frame, timestamp=t))


def command(listener: LeaderCommands, q: np.ndarray, t: float) -> None:
    send(listener, P.ModeCtrl(P.CtrlMode.CAN, P.MoveMode.J, 100), t)
    for k, frame in enumerate(P.joint_ctrl_frames(q)):
        send(listener, frame, t + (k + 1) * 130e-6)


def test_the_latest_command_at_or_before_the_frame_holds() -> None:
    leader = LeaderCommands(to_mono=lambda t: t - 1000.0, max_age_s=0.1)
    state = np.full(7, 0.5)
    action, from_state, flags = leader.action_at(1.0, state)
    assert flags == FLAG_ACTION_STALE and from_state and np.array_equal(action, state)
    q1, q2 = np.radians([10, 20, -30, 5, 6, 7]), np.radians([11, 21, -31, 6, 7, 8])
    command(leader, q1, 1001.0)
    command(leader, q2, 1001.005)
    send(leader, P.GripperCtrl(0.04, 1.0), 1001.0051)
    assert leader.seen and leader.commands == 2
    action, from_state, flags = leader.action_at(1.003, state)
    np.testing.assert_allclose(action[:6], q1, atol=np.radians(0.0005))
    assert action[6] == 0.5 and from_state and flags == 0  # no gripper command yet: the measured width
    action, from_state, flags = leader.action_at(1.01, state)
    np.testing.assert_allclose(action[:6], q2, atol=np.radians(0.0005))
    assert action[6] == pytest.approx(0.04) and not from_state and flags == 0
    action, _, flags = leader.action_at(1.2, state)  # 0.195 s after the last command
    assert flags == FLAG_ACTION_STALE and np.array_equal(action[:6], state[:6])


def test_an_incomplete_command_is_not_an_action() -> None:
    leader = LeaderCommands(to_mono=lambda t: t)
    frames = P.joint_ctrl_frames(np.zeros(6))
    send(leader, frames[0], 0.0)
    send(leader, frames[2], 0.0003)  # 0x156 lost
    send(leader, P.JointFeedback(0, 0.0, 0.0), 0.0004)  # feedback is no command
    assert not leader.seen
