"""Which arm handles an object, and when: the one whose gripper first closes nearest the object's
start, then any arm that takes it over in a handover (closes on it while the holding gripper is
still closed, and the holder opens). :func:`carrier_track` makes one tool track of them that
moves the held object as the arms do, so that alignment treats a handover like one long grasp."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from manisplat.align.phases import gripper_events
from manisplat.align.pseudo_gt import close_end

HANDOVER_REACH = 0.10
"""m: a gripper closing within this distance of the holding TCP while it holds takes the object over."""


@dataclass(frozen=True)
class Hold:
    """``arm`` holds the object from frame ``start`` (its pads closed on it, or it took it over)."""

    arm: str
    start: int


def acting_arm(tcp: dict[str, np.ndarray], gripper: dict[str, np.ndarray], start: np.ndarray) -> str:
    """The arm that first handles an object starting at ``start`` [3] (m).

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


def holds(tcp: dict[str, np.ndarray], gripper: dict[str, np.ndarray], start: np.ndarray) -> list[Hold]:
    """Who holds the object, in order: the :func:`acting_arm` from frame 0, then each arm that
    takes it over: its gripper starts closing while the holder's is closed (between the holder's
    grasp and release), within :data:`HANDOVER_REACH` of the holder's TCP; it holds from the frame
    its pads stopped closing.

    Args: as :func:`acting_arm`, ``tcp`` positions [T, 3].
    """
    first = acting_arm(tcp, gripper, start)
    out = [Hold(first, 0)]
    holder = first
    while True:
        grasp, release = _grasp_after(gripper[holder], out[-1].start)
        if grasp is None:
            return out
        end = len(gripper[holder]) if release is None else release
        taker = None
        for name in tcp:
            if name == holder:
                continue
            for e in gripper_events(np.asarray(gripper[name], np.float64)):
                if grasp < e.grasp < end and np.linalg.norm(tcp[name][e.grasp] - tcp[holder][e.grasp]) < HANDOVER_REACH:
                    taken = close_end(np.asarray(gripper[name], np.float64), e.grasp, e.release)
                    if out[-1].start < taken < end and (taker is None or taken < taker[1]):
                        taker = (name, taken)
                    break
        if taker is None:
            return out
        out.append(Hold(*taker))
        holder = taker[0]


def _grasp_after(width: np.ndarray, frame: int) -> tuple[int | None, int | None]:
    """(grasp, release) of the gripper's first grasp still holding at or after ``frame`` (None, None: none)."""
    for e in gripper_events(np.asarray(width, np.float64)):
        if e.release is None or e.release > frame:
            return e.grasp, e.release
    return None, None


def carrier_track(tcp: dict[str, np.ndarray], gripper: dict[str, np.ndarray], holds: list[Hold]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """One tool track for alignment: (poses [T, 4, 4], opening [T] m). The first holder's TCP and
    opening until the next takes over; from the frame an arm takes over, its TCP motion carried
    on from where the track was (``T_tcp(f) @ inv(T_tcp(s)) @ track(s)``, s its first frame),
    with its opening: an object held at the handover moves with the taker exactly as it moved
    with the giver, as in one long grasp.

    Args:
        tcp: arm -> TCP poses [T, 4, 4]; gripper: arm -> opening [T] (m).
    """
    track = np.array(tcp[holds[0].arm], np.float64)
    for hold in holds[1:]:
        s = hold.start
        own = np.asarray(tcp[hold.arm], np.float64)
        carry = np.linalg.inv(own[s]) @ track[s]  # the track in the taker's TCP frame at s
        track[s:] = own[s:] @ carry
    return track, holders_values(gripper, holds)


def holders_values(values: dict[str, np.ndarray], holds: list[Hold]) -> np.ndarray:
    """[T] each frame's value of the arm holding the object then (``values``: arm -> [T], e.g. its
    gripper's opening or effort): the first holder's until the next takes over, and so on."""
    out = np.array(values[holds[0].arm], np.float64)
    for hold in holds[1:]:
        out[hold.start:] = np.asarray(values[hold.arm], np.float64)[hold.start:]
    return out


__all__ = ["HANDOVER_REACH", "Hold", "acting_arm", "carrier_track", "holders_values", "holds"]
