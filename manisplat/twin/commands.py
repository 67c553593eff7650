"""How a recording's commands relate to its joints, kept with the twin so that new demonstrations
command their joints the same way (:mod:`manisplat.augment.commands`).

A recording's commands are not its joints: a leader arm or a controller leads the follower, and
where the arm is held back (fingers closing on an object, an object pressed onto the table, two
grippers on one object) the command goes on past where the arm is. The offsets (commanded minus
recorded joints, both as ``frames.csv`` has them at each frame) are split in two:

* the **lead**, a fraction of a frame (0..1) fitted by least squares over the moving joints:
  commands ``led(q, lead) = (1 - lead) q[k] + lead q[k+1]`` (a mix of two frames: its
  accelerations never exceed the joints');
* the **press**, what is left at each frame: ``commands - led(q, lead)`` [T, dof] rad.

The gripper's commands are kept as recorded (``gripper`` [T, arms] m): a leader's fingers close
and open ahead of the follower's, over several frames, and a new demonstration that plays a skill
at source time ``s`` commands what the source commanded at ``s``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MOVING = 1e-4
"""rad per frame: a joint stepping less than this does not enter the lead's fit."""


@dataclass
class CommandRelation:
    """A recording's commands as its joints led by ``lead`` (fraction of a frame) plus ``press``
    [T, dof] rad per frame, and its gripper commands ``gripper`` [T, arms] m (None: not kept, a
    twin written before 2026-11-28)."""

    lead: float
    press: np.ndarray
    gripper: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.lead = float(self.lead)
        self.press = np.asarray(self.press, np.float64)
        if not (0.0 <= self.lead <= 1.0) or self.press.ndim != 2 or not np.isfinite(self.press).all():
            raise ValueError(f"command relation: lead {self.lead} outside [0, 1] or press of shape "
                             f"{self.press.shape} not [T, dof] and finite")
        if self.gripper is not None:
            gripper = np.asarray(self.gripper, np.float64)
            self.gripper = gripper[:, None] if gripper.ndim == 1 else gripper
            if self.gripper.ndim != 2 or len(self.gripper) != len(self.press) or not np.isfinite(self.gripper).all():
                raise ValueError(f"command relation: gripper commands of shape {gripper.shape} not [T, arms] "
                                 f"(T = {len(self.press)}) and finite")


def command_relation(q: np.ndarray, commands: np.ndarray, gripper: np.ndarray | None = None) -> CommandRelation:
    """The lead and press of ``commands`` [T, dof] against joints ``q`` [T, dof] (rad, per frame),
    with the gripper commands ``gripper`` [T, arms] m kept as they are."""
    q, commands = np.asarray(q, np.float64), np.asarray(commands, np.float64)
    if q.shape != commands.shape:
        raise ValueError(f"commands {commands.shape} and joints {q.shape} differ in shape")
    lead = command_lead(q, commands - q)
    return CommandRelation(lead, commands - led(q, lead), gripper)


def command_lead(q: np.ndarray, offset: np.ndarray) -> float:
    """The fraction of the next frame's step by which commands lead joints ``q`` [T, dof], fitted
    to ``offset`` [T, dof] (commanded minus recorded) over the moving joints; 1.0 without motion,
    clipped to [0, 1]."""
    if len(q) < 2:
        return 1.0
    step = np.diff(np.asarray(q, np.float64), axis=0)
    ahead = np.asarray(offset, np.float64)[:-1]
    moving = np.abs(step) > MOVING
    if not moving.any():
        return 1.0
    return float(np.clip((ahead[moving] * step[moving]).sum() / (step[moving] ** 2).sum(), 0.0, 1.0))


def led(q: np.ndarray, lead: float) -> np.ndarray:
    """Commands [T, dof] leading joints ``q`` [T, dof] by ``lead`` of a frame (the last frame its own)."""
    q = np.asarray(q, np.float64)
    following = np.concatenate([q[1:], q[-1:]], axis=0)
    return q + lead * (following - q)


__all__ = ["MOVING", "CommandRelation", "command_lead", "command_relation", "led"]
