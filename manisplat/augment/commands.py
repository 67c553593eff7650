"""The commands of a new demonstration (``action_q``), in the relation the source's commands had to
its joints (:class:`manisplat.twin.commands.CommandRelation`, kept by the twin).

Replaying a demonstration's joints as its commands loses what its commands did: in contact
physics, a place the recorded commands did cleanly brushes the surface with a finger (a simulated
Cobot Magic handover: 98 of 100 new demonstrations). So every new command is the new joints led by
the source's lead, and a skill's frames add the source's press at the source time they play
(:meth:`SourceCommands.press_at`), faded in and out over ``FADE_S`` inside ``CLEAR_FRAMES`` at
the skill's ends, so that the commands join the motions around it where only the joints
accelerate (a motion may leave a skill at its full acceleration limit). The skill's slow-down
(:func:`manisplat.augment.skills.solve_skill`) keeps these commands within the limits too: a
slowed skill stretches its press in time.

Without recorded commands the command is the next frame's joints (a lead of one frame, no press).
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline

from manisplat.twin.commands import CommandRelation, led

FADE_S = 0.15
"""s of source time over which a skill's press fades in and out."""

CLEAR_FRAMES = 2
"""source frames at each end of a skill that press nothing (the fades lie inside them)."""


class SourceCommands:
    """The source's lead and press, ready to command new joints.

    Args:
        relation: the source's :class:`CommandRelation` (None where it recorded no commands);
        dof: joints per frame; fps: the source's frame rate.
    """

    def __init__(self, relation: CommandRelation | None, dof: int, fps: float) -> None:
        self.lead = 1.0 if relation is None else relation.lead
        self.fade = FADE_S * float(fps)  # source frames
        self.dof = dof
        self._press = None
        if relation is not None and len(relation.press) >= 2:
            self._press = CubicSpline(np.arange(len(relation.press), dtype=np.float64), relation.press, axis=0)

    @property
    def recorded(self) -> bool:
        """Whether the source recorded commands (else: next-frame joints, no press)."""
        return self._press is not None

    def press_at(self, s: np.ndarray, first: float, last: float) -> np.ndarray:
        """[n, dof] rad: the press at source times ``s`` [n] of the skill on source frames
        ``first..last``: none within ``CLEAR_FRAMES`` of its ends, faded in and out inside them
        (zeros without recorded commands)."""
        s = np.asarray(s, np.float64)
        if self._press is None:
            return np.zeros((len(s), self.dof))
        return self._press(s) * _fade(s, first + CLEAR_FRAMES, last - CLEAR_FRAMES, self.fade)[:, None]

    def commanded(self, q: np.ndarray, press: np.ndarray) -> np.ndarray:
        """Commands [T, dof] for new joints ``q`` [T, dof]: led by the source's lead, plus ``press``
        [T, dof] (a skill's :meth:`press_at` on its frames, zero elsewhere)."""
        return led(q, self.lead) + press


def _fade(s: np.ndarray, first: float, last: float, width: float) -> np.ndarray:
    """[n] in [0, 1]: 0 up to ``first`` and from ``last``, 1 from ``width`` frames inside them, a
    raised cosine between (zero slope at both ends of each ramp)."""
    width = min(width, 0.5 * (last - first))
    if width <= 0:
        return np.zeros_like(s)
    u = np.clip(np.minimum(s - first, last - s) / width, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * u)


__all__ = ["CLEAR_FRAMES", "FADE_S", "SourceCommands"]
