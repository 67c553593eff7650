"""The holds at a skill's ends: the still frames where the source arrived at a skill and left it.

A recorded skill begins where the source's own motion came to (near) rest above the object and
ends where the next one set off: its first and last frames are often a hold, the arm and gripper
still (on the shared pick-and-place, 3-5 frames under 0.1 rad/s before the descent). A new
demonstration re-plans those motions, and they arrive and leave at the skill's own velocity, so
played as recorded the hold follows a second arrival (and is stretched when the skill is slowed
for the joint limits): up to 8 frames of a still arm above the object where a scripted
demonstration has 5. A policy cannot tell from a still picture how long it has held, so a hold
teaches it to wait without knowing when to go on (closed loop it creeps on: the benchmark's
"stall at the hover").

:func:`moving_span` gives the skill's frames without those holds, for the ends a re-planned motion
joins; what the skill does between them (descend, close, lift) is played as recorded.
"""

from __future__ import annotations

import numpy as np

#: a frame interval in which every joint moves slower than this (rad/s) ...
HOLD_JOINT_SPEED = 0.1
#: ... and the gripper slower than this (m/s) is still
HOLD_GRIPPER_SPEED = 0.005


def moving_span(q: np.ndarray, gripper: np.ndarray, fps: float, first: int, last: int, *, lead: bool,
                trail: bool) -> tuple[int, int]:
    """The source frames ``(first', last')`` of the skill on frames ``first..last`` without the still
    intervals at its start (``lead``) and end (``trail``), from joints ``q`` [T, dof] (rad) and the
    gripper [T] (m) at ``fps``; the skill as it is where it never moves."""
    joint = np.abs(np.diff(q[first:last + 1], axis=0)).max(axis=1) * fps
    fingers = np.abs(np.diff(gripper[first:last + 1])) * fps
    still = (joint < HOLD_JOINT_SPEED) & (fingers < HOLD_GRIPPER_SPEED)  # [last - first]: interval k -> k + 1
    if still.all():
        return first, last
    a, b = first, last
    while lead and still[a - first]:
        a += 1
    while trail and still[b - first - 1]:
        b -= 1
    return a, b
