"""Which arm handles an object: the one that closes its gripper near the object's start, even
when the other arm's TCP passes nearer without closing; then any arm that takes it over in a
handover, and one tool track that carries it through."""

from __future__ import annotations

import numpy as np

from manisplat.align.acting_arm import Hold, acting_arm, carrier_track, holders_values, holds

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


def moving(start, velocity, yaw_rate: float = 0.0) -> np.ndarray:
    """TCP poses [T, 4, 4]: from ``start`` at ``velocity`` m/frame, turning about z by ``yaw_rate`` rad/frame."""
    poses = np.tile(np.eye(4), (T, 1, 1))
    for f in range(T):
        c, s = np.cos(yaw_rate * f), np.sin(yaw_rate * f)
        poses[f, :2, :2] = [[c, -s], [s, c]]
        poses[f, :3, 3] = np.asarray(start) + f * np.asarray(velocity)
    return poses


def opening(grasp: int, release: int | None = None) -> np.ndarray:
    """A gripper track [T]: closes over 3 frames from ``grasp``, opens over 3 from ``release``."""
    keys_t, keys_w = [0, grasp, grasp + 3], [OPEN, OPEN, CLOSED]
    if release is not None:
        keys_t, keys_w = keys_t + [release, release + 3], keys_w + [CLOSED, OPEN]
    return np.interp(np.arange(T), keys_t, keys_w)


def handover_scene():
    """Left picks the object at frame 10 and carries it; right meets it, closes at 30 and takes it
    over (its pads stop at 33); left opens at 40; the right arm, turned 90 deg, carries it on."""
    left = moving([0.3, 0.1, 0.02], [0.0, -0.002, 0.001])
    right = moving([0.3, -0.1, 0.05], [0.0, 0.004, 0.0], yaw_rate=0.01)
    right[:, :3, :3] = right[:, :3, :3] @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    right[30:, :3, 3] = left[30, :3, 3] + 0.01 + (right[30:, :3, 3] - right[30, :3, 3])  # 1 cm from left's TCP at 30
    return {"left": left, "right": right}, {"left": opening(10, 40), "right": opening(30)}


def test_a_gripper_closing_on_the_held_object_takes_it_over() -> None:
    tcp, gripper = handover_scene()
    order = holds({a: p[:, :3, 3] for a, p in tcp.items()}, gripper, tcp["left"][0, :3, 3])
    assert order == [Hold("left", 0), Hold("right", 33)]


def test_a_gripper_closing_far_from_the_holder_takes_nothing_over() -> None:
    tcp, gripper = handover_scene()
    tcp["right"][30:, :3, 3] += [0.0, 0.0, 0.2]  # closes 20 cm above the held object
    order = holds({a: p[:, :3, 3] for a, p in tcp.items()}, gripper, tcp["left"][0, :3, 3])
    assert order == [Hold("left", 0)]


def test_the_carrier_track_moves_a_handed_over_object_as_one_grasp() -> None:
    """The object rigid with the left TCP until the take-over, then with the right's: seen from
    the carrier track it never moves, across the handover."""
    tcp, gripper = handover_scene()
    order = [Hold("left", 0), Hold("right", 33)]
    T_tcp_obj = np.eye(4)
    T_tcp_obj[:3, 3] = [0.0, 0.0, 0.02]
    obj = tcp["left"] @ T_tcp_obj
    obj[33:] = tcp["right"][33:] @ np.linalg.inv(tcp["right"][33]) @ obj[33]
    track, width = carrier_track(tcp, gripper, order)
    relative = np.linalg.inv(track) @ obj
    np.testing.assert_allclose(relative, np.broadcast_to(relative[0], relative.shape), atol=1e-12)
    np.testing.assert_array_equal(width[33:], gripper["right"][33:])
    np.testing.assert_array_equal(width[:33], gripper["left"][:33])


def test_each_frame_takes_the_value_of_the_arm_holding_the_object_then() -> None:
    effort = {"left": np.full(T, -1.0), "right": np.full(T, -2.0)}
    spliced = holders_values(effort, [Hold("left", 0), Hold("right", 33)])
    np.testing.assert_array_equal(spliced, np.r_[np.full(33, -1.0), np.full(T - 33, -2.0)])
    np.testing.assert_array_equal(holders_values(effort, [Hold("right", 0)]), effort["right"])
