"""Which arm handles an object: the one that closes its gripper near the object's start, even
when the other arm's TCP passes nearer without closing."""

from __future__ import annotations

import numpy as np

from manisplat.align.acting_arm import acting_arm

T = 60
OPEN, CLOSED = 0.07, 0.03


def closing_at(frame: int) -> np.ndarray:
    """A gripper track [T]: open, closing over 5 frames from ``frame``."""
    return np.interp(np.arange(T), [frame, frame + 5], [OPEN, CLOSED])


def still_at(point) -> np.ndarray:
    return np.tile(np.asarray(point, np.float64), (T, 1))


def test_the_arm_that_closes_at_the_object_handles_it() -> None:
    start = np.array([0.3, 0.1, 0.02])
    tcp = {"left": still_at(start + [0.0, 0.0, 0.003]),  # closes 3 mm above the object
           "right": still_at([0.3, -0.1, 0.02])}  # closes on its own object
    gripper = {"left": closing_at(20), "right": closing_at(30)}
    assert acting_arm(tcp, gripper, start) == "left"
    assert acting_arm(tcp, gripper, np.array([0.3, -0.1, 0.02])) == "right"


def test_an_arm_passing_nearer_without_closing_does_not() -> None:
    start = np.array([0.3, 0.0, 0.02])
    tcp = {"left": still_at(start),  # right over the object, never closes
           "right": still_at(start + [0.0, 0.0, 0.02])}  # 2 cm above, closes
    gripper = {"left": np.full(T, OPEN), "right": closing_at(10)}
    assert acting_arm(tcp, gripper, start) == "right"


def test_without_any_grasp_the_nearest_arm() -> None:
    start = np.array([0.3, 0.0, 0.02])
    tcp = {"left": still_at(start + [0.0, 0.05, 0.0]), "right": still_at(start + [0.0, -0.02, 0.0])}
    gripper = {"left": np.full(T, OPEN), "right": np.full(T, OPEN)}
    assert acting_arm(tcp, gripper, start) == "right"
