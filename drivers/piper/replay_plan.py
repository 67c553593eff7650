"""What ``manisplat-replay`` will do with each arm of an episode, and the arm-against-arm check.

:func:`plan_arms` maps every arm's joint convention (:mod:`.convention`) and builds its
:class:`~.trajectory.Trajectory`; :func:`arm_clearance` places every arm's link geometry in the
episode's world (:mod:`.clearance`); :func:`trajectory_clearance` and :func:`approach_clearance`
say how close the arms come over the episode's frames and over the simultaneous move to the
start, and :func:`clearance_problem` turns a closest approach below the limit into the refusal.

The arms' links are placed by each arm's own description (the episode's convention) at the
streamed joint targets; the fingers at the episode's recorded opening (its ``gripper`` column),
because a gripper told to close on an object stops at it, as it did when the episode was made.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np

from manisplat.drivers.piper.clearance import ArmBody, ArmClearance, Closest
from manisplat.drivers.piper.convention import JointConvention, convention_for, tcp_discrepancy_mm
from manisplat.drivers.piper.trajectory import Trajectory, approach, trajectory_from_episode
from manisplat.episode import Episode
from manisplat.robot import RobotModel, load_robot

APPROACH_CHECK_STEP_S = 0.02  # the approach is checked every this many seconds of its ramp


@dataclass(frozen=True)
class ArmPlan:
    """One arm's replay.

    Attributes:
        name: the arm's name in the episode.
        description: its ``robot.description``; convention: the map to the arm's angles.
        traj: its targets in the arm's convention.
        tcp_mm: the largest TCP displacement the convention map causes on those targets, mm.
        fingers: (T,) the recorded gripper opening per frame, m (where the check places the fingers).
    """

    name: str
    description: str
    convention: JointConvention
    traj: Trajectory
    tcp_mm: float
    fingers: np.ndarray


def plan_arms(episode: Episode, speed: float, source: str) -> dict[str, ArmPlan]:
    """Every arm's :class:`ArmPlan`. Raises what :func:`convention_for` (ConventionError) and
    :func:`trajectory_from_episode` (ValueError) raise, the message naming the arm when there are several."""
    plans = {}
    for name, info in episode.arms.items():
        try:
            convention = convention_for(info.description, episode.path)
            traj = trajectory_from_episode(episode, convention, speed, source, arm=name)
            tcp_mm = tcp_discrepancy_mm(convention, info.description, episode.path, convention.from_arm(traj.q))
        except ValueError as exc:
            if len(episode.arms) == 1:
                raise
            raise type(exc)(f"arm {name}: {exc}") from None
        plans[name] = ArmPlan(name, info.description, convention, traj, tcp_mm, episode.arm_frames(name).gripper.copy())
    return plans


def arm_clearance(episode: Episode) -> ArmClearance:
    """The arm-against-arm check of ``episode``'s arms (two or more): each arm's description with its
    link geometry, at its ``T_world_base``. ValueError naming an arm without a base or geometry."""
    bodies = {}
    for name, info in episode.arms.items():
        if info.T_world_base is None:
            raise ValueError(f"arm {name} has no T_world_base in {episode.path / 'episode.json'} (not calibrated): "
                             "the arm-against-arm check needs where every arm stands")
        robot: RobotModel = load_robot(info.description, episode.path, load_meshes=True)
        bodies[name] = ArmBody(robot, info.T_world_base)
    return ArmClearance(bodies)


def trajectory_clearance(check: ArmClearance, plans: Mapping[str, ArmPlan]) -> Closest:
    """The closest approach of the arms over every frame of their targets."""
    q = {name: p.convention.from_arm(p.traj.q) for name, p in plans.items()}
    return check.closest(q, {name: p.fingers for name, p in plans.items()})


def approach_clearance(check: ArmClearance, plans: Mapping[str, ArmPlan], current: Mapping[str, np.ndarray],
                       robot: RobotModel, fraction: float) -> tuple[Closest, np.ndarray]:
    """The closest approach of the arms while they all move from ``current`` (arm convention, (6,)
    rad each, clipped into ``robot``'s limits as the streamer does) to their starts at once, as
    :func:`~.trajectory.approach` ramps them at ``fraction`` of the speed limits; and the times
    checked, (K,) s from the approach's start."""
    ramps = {name: approach(np.clip(current[name], robot.lower, robot.upper), p.traj.q[0], robot, fraction)
             for name, p in plans.items()}
    longest = max(duration for duration, _ in ramps.values())
    times = np.linspace(0.0, longest, int(np.ceil(longest / APPROACH_CHECK_STEP_S)) + 1)
    q = {name: plans[name].convention.from_arm(np.stack([at(min(s, duration)) for s in times]))
         for name, (duration, at) in ramps.items()}
    fingers = {name: np.full(len(times), p.fingers[0]) for name, p in plans.items()}
    return check.closest(q, fingers), times


def describe_closest(closest: Closest) -> str:
    """``"left/link8 and right/link8 1.0 mm apart"`` (or ``"... overlap by 3.0 mm"``)."""
    (a, b), (la, lb) = closest.arms, closest.links
    mm = closest.distance_m * 1e3
    return f"{a}/{la} and {b}/{lb} " + (f"{mm:.1f} mm apart" if mm >= 0 else f"overlap by {-mm:.1f} mm")


def clearance_problem(closest: Closest, min_clearance_mm: float, name: Callable[[int], str]) -> str | None:
    """The refusal when the arms come closer than ``min_clearance_mm``; ``name(i)`` names
    configuration ``i`` (``"frame 111 (t 5.55 s)"``). None when they keep clear."""
    close = np.flatnonzero(closest.per_frame_m * 1e3 < min_clearance_mm)
    if not close.size:
        return None
    return (f"the arms come closer than {min_clearance_mm:g} mm (--min-arm-clearance-mm) at {close.size} of "
            f"{len(closest.per_frame_m)} configurations, first at {name(int(close[0]))}; closest at "
            f"{name(closest.frame)}: {describe_closest(closest)}")
