"""Which arm handles an object: the one whose tool centre point comes nearest the object's
start while its gripper closes (a Cobot Magic's two arms each pick their own object)."""

from __future__ import annotations

import numpy as np

from manisplat.align.phases import gripper_events


def acting_arm(tcp: dict[str, np.ndarray], gripper: dict[str, np.ndarray], start: np.ndarray) -> str:
    """The arm that handles an object starting at ``start`` [3] (m).

    Args:
        tcp: arm -> TCP positions [T, 3] (m, the frame of ``start``).
        gripper: arm -> gripper opening [T] (m).

    An arm whose gripper closes is preferred, scored by the distance of its TCP to ``start`` at
    its first close; without any close, the arm whose TCP comes nearest over the whole episode.
    """
    if not tcp:
        raise ValueError("acting_arm: no arms")
    start = np.asarray(start, np.float64)
    closing = {}
    for name in tcp:
        events = gripper_events(np.asarray(gripper[name], np.float64))
        if events:
            closing[name] = float(np.linalg.norm(tcp[name][events[0].grasp] - start))
    if closing:
        return min(closing, key=closing.get)
    nearest = {name: float(np.linalg.norm(positions - start, axis=1).min()) for name, positions in tcp.items()}
    return min(nearest, key=nearest.get)


__all__ = ["acting_arm"]
