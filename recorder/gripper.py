"""The gripper's own stream: every 0x2A8 frame with its own bus stamp.

A PiperArm joint sample carries the latest gripper width it had when the sample completed,
which is the previous cycle's (0x2A8 comes after 0x2A5..0x2A7 in a cycle): 5 ms stale in steady
state, and as old as a dropout right after one. The recorder therefore interpolates the gripper
at a frame's time from this stream, like the joints from theirs; the gripper motor's effort
(N*m) with it, which tells when the pads stop squeezing a held object (the release the pseudo
ground truth dates: :func:`manisplat.align.phases.gripper_events`).
"""

from __future__ import annotations

from typing import Callable

import can
import numpy as np

from manisplat.drivers.piper import protocol as P
from manisplat.recorder.sync import JointHistory

GRIPPER_FEEDBACK_ID = 0x2A8


class GripperStream(can.Listener):
    """A python-can listener keeping the gripper width (m) and effort (N*m) on the monotonic timeline.

    Args:
        to_mono: maps a frame's bus timestamp onto the monotonic timeline (s -> s).
    """

    def __init__(self, to_mono: Callable[[float], float]) -> None:
        self.to_mono = to_mono
        self.history = JointHistory(dims=2)  # width, effort

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id != GRIPPER_FEEDBACK_ID:
            return
        frame = P.decode_message(msg)
        if isinstance(frame, P.GripperFeedback):
            self.history.append(self.to_mono(float(msg.timestamp)), np.array([frame.width, frame.effort]))
