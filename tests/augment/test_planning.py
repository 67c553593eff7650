"""Joint-space planning on a 2-D toy scene (a wall with a gap): the straight line when it is
free, else an RRT-Connect path that this module's own dense check accepts."""

from __future__ import annotations

import numpy as np
import pytest

from manisplat.augment.errors import Rejected
from manisplat.augment.planning import LIMIT_MARGIN, RESOLUTION, path_free, plan_path

LOWER, UPPER = np.array([-1.0, -1.0]), np.array([1.0, 1.0])


class WallWithGap:
    """Collides inside a wall ``thickness`` rad thick at q0 in [0, thickness], except where
    |q1| < ``gap`` (a scene given as a function of the configuration, like SceneCollision)."""

    def __init__(self, thickness: float, gap: float = 0.05) -> None:
        self.thickness, self.gap, self.checks = thickness, gap, 0

    def collides(self, q: np.ndarray, width: float) -> bool:
        self.checks += 1
        return bool(0.0 <= q[0] <= self.thickness and abs(q[1]) >= self.gap)

    def first_collision(self, q: np.ndarray, width: float):
        return ("arm", "wall") if self.collides(q, width) else None


def test_the_straight_line_when_it_is_free():
    result = plan_path(WallWithGap(0.1), np.array([-0.5, 0.0]), np.array([0.5, 0.0]), 0.0, lower=LOWER,
                       upper=UPPER, timeout=1.0, seed=0)
    assert result.method == "straight" and len(result.waypoints) == 2


def test_the_planner_when_asked_not_to_go_straight():
    """The re-plan after a timed spline left a straight segment: a planner path (not the same
    straight line again), still collision-free."""
    checker = WallWithGap(0.1)
    result = plan_path(checker, np.array([-0.5, 0.0]), np.array([0.5, 0.0]), 0.0, lower=LOWER,
                       upper=UPPER, timeout=1.0, seed=0, straight=False)
    assert result.method == "rrtconnect" and path_free(checker, result.waypoints, 0.0)


def test_a_wall_is_passed_through_its_gap():
    checker = WallWithGap(0.1)
    result = plan_path(checker, np.array([-0.5, 0.5]), np.array([0.5, 0.5]), 0.0, lower=LOWER, upper=UPPER,
                       timeout=2.0, seed=3)
    assert result.method == "rrtconnect"
    assert path_free(checker, result.waypoints, 0.0)
    dense = np.concatenate([a + np.linspace(0, 1, 200)[:, None] * (b - a)
                            for a, b in zip(result.waypoints[:-1], result.waypoints[1:])])
    crossing = dense[(dense[:, 0] >= 0) & (dense[:, 0] <= 0.1)]
    # checked every RESOLUTION rad: a segment may cut a corner of the gap by less than that
    assert len(crossing) and np.abs(crossing[:, 1]).max() < 0.05 + RESOLUTION


def test_a_path_the_planners_coarser_checks_let_through_is_planned_again_finer():
    """A wall thinner than the collision-check spacing (0.01 rad): OMPL's samples (spaced in the
    L2 norm) step over it where this module's (spaced in the largest joint change) may land in
    it. A path that fails the module's check is planned again with 4x finer checks, which cannot
    step over a 4 mm wall: no seed is rejected."""
    for seed in range(40):
        checker = WallWithGap(0.004)
        result = plan_path(checker, np.array([-0.5, 0.5]), np.array([0.5, 0.5]), 0.0, lower=LOWER, upper=UPPER,
                           timeout=2.0, seed=seed)
        assert path_free(checker, result.waypoints, 0.0)


class WallWithPassageAtTheLimit(WallWithGap):
    """A wall whose only passage is the band q1 in [0.97, 1.0], up to the joint limit (1.0)."""

    def collides(self, q: np.ndarray, width: float) -> bool:
        self.checks += 1
        return bool(0.0 <= q[0] <= self.thickness and q[1] < 0.97)


def test_the_planners_waypoints_keep_a_margin_inside_the_joint_limits():
    """A timed spline bulges past a waypoint at a corner: waypoints on a limit would carry the
    motion past it. The passage reaches the limit; the path keeps LIMIT_MARGIN inside it (without
    the margin 3 of these 8 seeds put a waypoint nearer the limit)."""
    highest = []
    for seed in range(8):
        checker = WallWithPassageAtTheLimit(0.1)
        result = plan_path(checker, np.array([-0.5, 0.5]), np.array([0.5, 0.5]), 0.0, lower=LOWER, upper=UPPER,
                           timeout=60.0, seed=seed, max_checks=1_000_000)  # seed 6 needs 245 403 checks
        assert result.method == "rrtconnect" and path_free(checker, result.waypoints, 0.0)
        highest.append(result.waypoints[:, 1].max())
    assert max(highest) <= UPPER[1] - LIMIT_MARGIN
    # ends beyond the margin are still reached (the sampled box widened to take them in)
    end = np.array([0.5, UPPER[1] - LIMIT_MARGIN / 2])
    result = plan_path(WallWithPassageAtTheLimit(0.1), np.array([-0.5, 0.5]), end, 0.0, lower=LOWER, upper=UPPER,
                       timeout=2.0, seed=0)
    assert np.array_equal(result.waypoints[-1], end)


def test_the_planners_budget_is_collision_checks_not_seconds():
    """A query is given up when its budget of collision checks runs out, whatever the clock says
    (the same seed plans the same way on an idle machine and on a busy one): this passage takes
    seed 6 245 403 checks, within a generous time limit either way."""
    start, goal = np.array([-0.5, 0.5]), np.array([0.5, 0.5])
    with pytest.raises(Rejected) as info:
        plan_path(WallWithPassageAtTheLimit(0.1), start, goal, 0.0, lower=LOWER, upper=UPPER, timeout=60.0, seed=6,
                  max_checks=200_000, name="M_toy")
    assert info.value.reason == "planner_timeout" and "M_toy: RRT-Connect found no collision-free path in 200000 " \
        "collision checks" in str(info.value)
    paths = [plan_path(WallWithPassageAtTheLimit(0.1), start, goal, 0.0, lower=LOWER, upper=UPPER, timeout=60.0,
                       seed=6, max_checks=300_000).waypoints for _ in range(2)]
    assert np.array_equal(paths[0], paths[1])


def test_an_end_inside_the_wall_is_rejected_by_name():
    with pytest.raises(Rejected) as info:
        plan_path(WallWithGap(0.1), np.array([0.05, 0.5]), np.array([0.5, 0.5]), 0.0, lower=LOWER, upper=UPPER,
                  timeout=1.0, seed=0, name="M_toy")
    assert info.value.reason == "collision" and "M_toy: its start configuration collides (arm with wall)" in str(info.value)
