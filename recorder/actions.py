"""Teleoperation actions: the leader arm's joint commands seen on the bus.

In a PiPER leader/follower (master/slave) setup the leader sends the follower's commands itself:
0x151 (mode), 0x155..0x157 (joint targets, three frames per cycle) and 0x159 (gripper target).
A read-only recorder sees them like any other frame. :class:`LeaderCommands` assembles the three
joint frames of each cycle (same rule as the feedback: :class:`~manisplat.drivers.piper.JointAssembler`)
and keeps the commands on the monotonic timeline, so the action at a frame's time can be looked up.

The action at ``t`` is the latest command at or before ``t`` (a command holds until the next one;
it is not interpolated). A frame with no joint command within ``max_age_s`` before it is flagged
:data:`~.sync.FLAG_ACTION_STALE` and its action is the measured state (hold where you are). Until
the first gripper command the gripper action is the measured gripper width (counted in
``gripper_from_state``).
"""

from __future__ import annotations

from typing import Callable

import can
import numpy as np

from manisplat.drivers.piper import JointAssembler
from manisplat.drivers.piper import protocol as P
from manisplat.recorder.sync import FLAG_ACTION_STALE, JointHistory

JOINT_CTRL_IDS = frozenset({0x155, 0x156, 0x157})
GRIPPER_CTRL_ID = 0x159


class LeaderCommands(can.Listener):
    """A python-can listener keeping the leader's joint and gripper commands.

    Args:
        to_mono: maps a frame's bus timestamp onto the monotonic timeline (s -> s).
        max_age_s: a joint command older than this at a frame's time is stale.
    """

    def __init__(self, to_mono: Callable[[float], float], max_age_s: float = 0.1) -> None:
        self.to_mono = to_mono
        self.max_age_s = float(max_age_s)
        self.joints = JointHistory(dims=6)
        self.gripper = JointHistory(dims=1)
        self._assembler = JointAssembler()
        self.commands = 0  # complete joint commands seen

    def on_message_received(self, msg: can.Message) -> None:
        can_id = msg.arbitration_id
        if can_id not in JOINT_CTRL_IDS and can_id != GRIPPER_CTRL_ID:
            return
        frame = P.decode_message(msg)
        t = float(msg.timestamp)
        if isinstance(frame, P.JointCtrl):
            done = self._assembler.push(frame.pair, frame.q_a, frame.q_b, t)
            if done is not None and self.joints.append(self.to_mono(done[0]), done[1]):
                self.commands += 1
        elif isinstance(frame, P.GripperCtrl):
            self.gripper.append(self.to_mono(t), np.array([frame.width]))

    @property
    def seen(self) -> bool:
        """Whether any complete joint command was seen."""
        return self.commands > 0

    def action_at(self, t: float, state: np.ndarray) -> tuple[np.ndarray, bool, int]:
        """``(action (7,) a1..a6 rad + a_gripper m, gripper_from_state, flags)`` at ``t``;
        ``state`` (7,) is the synced measured state of the frame (used when stale)."""
        action = np.asarray(state, dtype=np.float64).copy()
        flags = 0
        times, values = self.joints.around(t)
        before = times <= t
        if before.any() and t - times[before][-1] <= self.max_age_s:
            action[:6] = values[before][-1]
        else:
            flags |= FLAG_ACTION_STALE
        g_times, g_values = self.gripper.around(t)
        g_before = g_times <= t
        from_state = not g_before.any()
        if not from_state:
            action[6] = g_values[g_before][-1][0]
        return action, from_state, flags
