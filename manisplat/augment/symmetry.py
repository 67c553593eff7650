"""Objects whose shape is unchanged by a turn about the vertical: a new demonstration grasps them
on the face that keeps the wrist where the source held it.

A square box looks the same turned by 90 deg (order 4), a rectangular one by 180 deg (order 2),
a can by any angle ("round"). Moved rigidly with such an object, the source's grasp turns with the
object's yaw (up to the whole sampled +-45 deg, more with the arm's change of azimuth), where a
person demonstrating would take the pair of faces nearest the way they held it before. Given a
declared symmetry, the pick (and the place) is turned by the multiple of ``360 / order`` deg (any
angle when round) about the object's vertical axis, so that the grasp, seen from the arm's base
(relative to the azimuth of that axis), is the closest to the source's. The axis passes where the
closing pads centred the object along their closing axis and, across it, through the centre of
the reconstructed object's bounding box (:func:`axis_point`): a turn about the point the gripper
closed on would carry a grasp made off-centre across the pads into the new closing direction.
The object's start pose is kept exactly; where it is left differs from the place pose asked for by
a symmetry turn (the same shape, its texture turned), and that is the pose the episode reports.

The shape's symmetry is declared, not detected: from one camera a twin's object holds the sides
that camera saw, and a half-seen box is not square (docs/augment.md: its footprint, turned, can
match itself worse at 90 deg than at 45).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

ROUND = "round"


@dataclass(frozen=True)
class Symmetry:
    """Turns about the vertical that leave an object's shape unchanged.

    Attributes:
        order: the shape repeats every ``360 / order`` deg (1: no symmetry); None: any turn (round).
    """

    order: int | None

    def __post_init__(self) -> None:
        if self.order is not None and (not isinstance(self.order, int) or self.order < 1):
            raise ValueError(f"a symmetry order is a whole number >= 1 or round, got {self.order!r}")

    def nearest_turn(self, wanted: float) -> float:
        """The allowed turn (rad) nearest ``wanted`` (rad, in [-pi, pi])."""
        if self.order is None:
            return wanted
        step = 2 * math.pi / self.order
        return step * round(wanted / step)


def parse_symmetries(items: list[str] | tuple[str, ...]) -> dict[str, Symmetry]:
    """``["box=4", "can=round"]`` -> {name: Symmetry}; raises ValueError naming the bad item."""
    out: dict[str, Symmetry] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name or not value:
            raise ValueError(f"symmetry {item!r}: expected OBJECT=ORDER or OBJECT=round (e.g. box=4, can=round)")
        if value == ROUND:
            out[name] = Symmetry(None)
            continue
        try:
            out[name] = Symmetry(int(value))
        except ValueError:
            raise ValueError(f"symmetry {item!r}: the order must be a whole number >= 1 or round") from None
    return out


def vertical_turn(point: np.ndarray, angle: float) -> np.ndarray:
    """[4, 4] float64: a turn by ``angle`` (rad) about the vertical (base z) through ``point`` [3] (m)."""
    c, s = math.cos(angle), math.sin(angle)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = point - T[:3, :3] @ point
    return T


def yaw_of(R: np.ndarray) -> float:
    """The turn about the vertical (rad) of rotation ``R`` [3, 3] (its x axis' heading)."""
    return math.atan2(R[1, 0], R[0, 0])


def _wrap(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))


def axis_point(T_obj_tcp: np.ndarray, box_centre: np.ndarray, up: np.ndarray) -> np.ndarray:
    """A point [3] (object frame, m) of the object's vertical axis: ``box_centre`` [3] moved along
    the horizontal part of the grasp's closing axis (the TCP's y) to the grasp's TCP.

    Args:
        T_obj_tcp: the TCP at the grasp in the object frame [4, 4].
        up: the vertical in the object frame [3] (unit).
    """
    closing = T_obj_tcp[:3, 1] - (T_obj_tcp[:3, 1] @ up) * up
    norm = float(np.linalg.norm(closing))
    if norm < 1e-6:  # closing along the vertical: nothing centres the object across it
        return np.asarray(box_centre, np.float64).copy()
    closing /= norm
    return box_centre + float((T_obj_tcp[:3, 3] - box_centre) @ closing) * closing


def wrist_keeping_turn(symmetry: Symmetry, T_src: np.ndarray, T_new: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """The symmetry turn ``S`` [4, 4] (object frame) that keeps a skill's grasp nearest the source's.

    The skill moved with its object grasps at ``T_new @ S @ inv(T_src) @ T_tcp``; ``S`` turns about
    the object's vertical through ``axis`` [3] (object frame, m; :func:`axis_point`) by the allowed
    angle nearest the arm's change of azimuth to the axis less the object's change of yaw, so the
    grasp keeps its heading relative to the arm.

    Args:
        T_src, T_new: the object's source and new poses [4, 4] (base frame), both upright.
    """
    p_src = T_src[:3, :3] @ axis + T_src[:3, 3]
    p_new = T_new[:3, :3] @ axis + T_new[:3, 3]
    object_turn = yaw_of(T_new[:3, :3] @ T_src[:3, :3].T)
    azimuth_change = math.atan2(p_new[1], p_new[0]) - math.atan2(p_src[1], p_src[0])
    angle = symmetry.nearest_turn(_wrap(azimuth_change - object_turn))
    return np.linalg.inv(T_new) @ vertical_turn(p_new, angle) @ T_new
