"""The commands of a new demonstration (``action_q``), kept in the relation the source's commands
had to its joints.

A recording's commands are not its joints: a leader arm or a controller leads the follower by part
of a frame, and where the arm is held back (a gripper pressing an object onto the table, two
grippers on one object) the command goes on past where the arm is. Replaying a demonstration's
joints as its commands loses that: in contact physics a place that the recorded commands did
cleanly brushes the surface with a finger. So where the source recorded commands, its offsets
(commanded minus recorded joints) are split into a lead and a press:

* the lead, a fraction of a frame (0..1) fitted to the offsets over the source's moving frames:
  every new command is the new joints led by it, ``q[k] + lead * (q[k+1] - q[k])``;
* the press, what is left of the offset at each source frame: a skill's new frames add the press
  of the source time they play (a skill slowed down keeps its press and leads by its own steps).

Without recorded commands the command is the next frame's joints (a lead of one frame, no press).
"""

from __future__ import annotations

import numpy as np

MOVING = 1e-4
"""rad per frame: a joint stepping less than this does not enter the lead's fit."""


def command_lead(q: np.ndarray, offset: np.ndarray | None) -> float:
    """The fraction of the next frame's step by which commands lead joints ``q`` [T, dof], fitted
    by least squares to ``offset`` [T, dof] (commanded minus recorded) over the moving joints;
    1.0 without offsets or motion, clipped to [0, 1]."""
    if offset is None or len(q) < 2:
        return 1.0
    step = np.diff(np.asarray(q, np.float64), axis=0)
    ahead = np.asarray(offset, np.float64)[:-1]
    moving = np.abs(step) > MOVING
    if not moving.any():
        return 1.0
    return float(np.clip((ahead[moving] * step[moving]).sum() / (step[moving] ** 2).sum(), 0.0, 1.0))


def commanded(q: np.ndarray, source_time: np.ndarray, in_skill: np.ndarray, source_q: np.ndarray,
              source_offset: np.ndarray | None) -> np.ndarray:
    """Commands [T, dof] rad for new joints ``q`` [T, dof] (see the module docstring).

    Args:
        source_time: [T] the source time (fractional frame) each new frame plays, for skill frames.
        in_skill: [T] bool, the frames that replay a skill of the source.
        source_q, source_offset: the source's joints [S, dof] and command offsets [S, dof] (or None).
    """
    q = np.asarray(q, np.float64)
    lead = command_lead(source_q, source_offset)
    out = q + lead * (_following(q) - q)
    if source_offset is not None and np.any(in_skill):
        source_q = np.asarray(source_q, np.float64)
        press = np.asarray(source_offset, np.float64) - lead * (_following(source_q) - source_q)
        frames = np.arange(len(press), dtype=np.float64)
        at = np.asarray(source_time, np.float64)[in_skill]
        out[in_skill] += np.stack([np.interp(at, frames, press[:, j]) for j in range(q.shape[1])], axis=1)
    return out


def _following(q: np.ndarray) -> np.ndarray:
    """Each frame's next frame [T, dof] (the last its own)."""
    return np.concatenate([q[1:], q[-1:]], axis=0)


__all__ = ["MOVING", "command_lead", "commanded"]
