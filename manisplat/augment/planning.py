"""Collision-free joint-space paths between two configurations: the straight line first, else
OMPL's RRT-Connect within a time limit, shortened by OMPL's path simplifier.

Why OMPL 2.0 (``pip install ompl``): the reference implementation of sampling planners, now with
nanobind wheels for CPython 3.11 that take a plain Python validity callable; RRT-Connect solved
6-D PiPER queries in 11-13 ms in the reference's measurements. mplib (RRT-Connect + FCL +
TOPP-RA in one call) was the alternative, but it pins numpy < 2 and segfaults beside this
project's numpy 2.

Determinism: OMPL draws from a global seed generator; it is re-seeded (``RNG.setSeed``) before
each query from the augmentation seed and the segment, and RRT-Connect's budget is a number of
collision checks (:data:`MAX_CHECKS`), not seconds, so a seed gives the same path on an idle
machine and on a busy one (RRT-Connect stops at its first solution; the simplifier runs its fixed
rounds, not against a clock). A time limit (:data:`SAFETY_TIMEOUT_S`) stays as a safety net only:
with the former 1 s limit a test's motion failed on a loaded 2-core machine that the same seed
planned when it was idle. The same seed on inputs that differ in the last bit (a twin trained with
several threads) may give another path: the search branches on them.

Validity of a configuration: within the joint limits and no active collision pair
(:class:`~manisplat.augment.collision.SceneCollision`, in the state the caller set). Segments are
checked at ``resolution`` rad of the largest joint change, ends included. RRT-Connect samples
:data:`LIMIT_MARGIN` inside the limits (widened to take in the ends): the timed spline through
its waypoints bulges past a waypoint at a corner, and on the built-in sample, where the wrist
(joint 5) works 1.4 deg from its limit, waypoints on the limit itself let 3 of 100 samples around
an obstacle leave it by up to 0.43 deg (benchmarks augment_obstacle).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from manisplat.augment.errors import Rejected

RESOLUTION = 0.01  # rad between collision checks along a joint-space segment
LIMIT_MARGIN = 0.02  # rad the planner's samples keep inside the joint limits
MAX_CHECKS = 50_000  # RRT-Connect's budget of collision checks per query: about 1 s on one idle core
SAFETY_TIMEOUT_S = 30.0  # s: its time limit per query, behind the budget


@dataclass
class PlanResult:
    waypoints: np.ndarray   # [m, dof], first = start, last = goal
    method: str             # "straight" or "rrtconnect"
    seconds: float
    checks: int


def segment_free(checker, a: np.ndarray, b: np.ndarray, width: float, resolution: float = RESOLUTION) -> bool:
    n = max(1, int(np.ceil(np.abs(b - a).max() / resolution)))
    for u in np.linspace(0.0, 1.0, n + 1):
        if checker.collides(a + u * (b - a), width):
            return False
    return True


def path_free(checker, waypoints: np.ndarray, width: float, resolution: float = RESOLUTION) -> bool:
    return all(segment_free(checker, a, b, width, resolution) for a, b in zip(waypoints[:-1], waypoints[1:]))


def plan_path(checker, q_start: np.ndarray, q_goal: np.ndarray, width: float, *, lower: np.ndarray,
              upper: np.ndarray, timeout: float, seed: int, name: str = "motion",
              straight: bool = True, max_checks: int = MAX_CHECKS) -> PlanResult:
    """A collision-free path from ``q_start`` to ``q_goal`` (gripper ``width``): the straight
    segment when it is free (and ``straight``), else RRT-Connect's within ``max_checks`` collision
    checks per query (``timeout`` s: a safety net); raises :class:`Rejected` ("collision" when an
    end collides or no path passes the dense check, "planner_timeout" when the budget ran out)."""
    t0 = time.perf_counter()
    checks0 = checker.checks
    for what, q in (("start", q_start), ("goal", q_goal)):
        if checker.collides(q, width):
            pair = checker.first_collision(q, width)
            raise Rejected("collision", f"{name}: its {what} configuration collides ({pair[0]} with {pair[1]})"
                           if pair else f"{name}: its {what} configuration collides")
    if straight and segment_free(checker, q_start, q_goal, width):
        return PlanResult(np.stack([q_start, q_goal]), "straight", time.perf_counter() - t0, checker.checks - checks0)
    # OMPL checks a segment at its own sample points (spaced in the L2 norm); a sliver of collision
    # between them fails this module's check: plan again with 4x finer checks before giving up
    low = np.minimum(lower + LIMIT_MARGIN, np.minimum(q_start, q_goal))
    high = np.maximum(upper - LIMIT_MARGIN, np.maximum(q_start, q_goal))
    for attempt, resolution in enumerate((RESOLUTION, RESOLUTION / 4)):
        first = checker.checks
        wps = _rrt_connect(checker, q_start, q_goal, width, low, high, timeout, max_checks, seed + attempt, resolution)
        if wps is None:
            spent = (f"{max_checks} collision checks" if checker.checks - first >= max_checks
                     else f"{timeout:g} s (its time limit; {checker.checks - first} collision checks)")
            raise Rejected("planner_timeout", f"{name}: RRT-Connect found no collision-free path in {spent}")
        if path_free(checker, wps, width):
            return PlanResult(wps, "rrtconnect", time.perf_counter() - t0, checker.checks - checks0)
    raise Rejected("collision", f"{name}: the planner's path fails the dense collision check (twice)")


def _rrt_connect(checker, a, b, width, lower, upper, timeout, max_checks, seed, resolution=RESOLUTION) -> np.ndarray | None:
    from ompl import base as ob
    from ompl import geometric as og
    from ompl import util as ou

    ou.setLogLevel(ou.LogLevel.LOG_NONE)
    ou.RNG.setSeed(int(seed) % (2 ** 31 - 1) + 1)
    dof = len(a)
    space = ob.RealVectorStateSpace(dof)
    bounds = ob.RealVectorBounds(dof)
    for i in range(dof):
        bounds.setLow(i, float(lower[i]))
        bounds.setHigh(i, float(upper[i]))
    space.setBounds(bounds)
    ss = og.SimpleSetup(space)

    def valid(state) -> bool:
        q = np.fromiter((state[i] for i in range(dof)), np.float64, dof)
        return not checker.collides(q, width)

    ss.setStateValidityChecker(valid)
    start, goal = space.allocState(), space.allocState()
    for i in range(dof):
        start[i], goal[i] = float(a[i]), float(b[i])
    ss.setStartAndGoalStates(start, goal)
    si = ss.getSpaceInformation()
    si.setStateValidityCheckingResolution(resolution / space.getMaximumExtent())
    ss.setPlanner(og.RRTConnect(si))
    first = checker.checks
    budget = ob.PlannerTerminationCondition(lambda: checker.checks - first >= max_checks)
    solved = ss.solve(ob.plannerOrTerminationCondition(budget, ob.timedPlannerTerminationCondition(float(timeout))))
    if not solved or "Exact" not in str(solved):
        return None
    path = ss.getSolutionPath()
    ss.getPathSimplifier().simplifyMax(path)  # a fixed number of rounds, not a time budget
    return np.array([[path.getState(k)[i] for i in range(dof)] for k in range(path.getStateCount())])
