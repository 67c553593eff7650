"""Arm against arm: the smallest distance between the links of different arms over a trajectory.

Each arm's links are the convex hulls of its description's geometry (:mod:`manisplat.robot.hulls`:
the built-in PiPER's primitives, a URDF's meshes), placed by that description's forward kinematics
(Pinocchio, :class:`~manisplat.augment.kinematics.PinRobot`, fingers opened by the gripper value)
and the arm's ``T_world_base``. One :class:`pinocchio.GeometryModel` holds every link of every arm
with one collision pair per link of one arm and link of another; per configuration one
``pin.computeDistances`` call runs coal's GJK/EPA on all pairs (negative distances: overlap).
A link never collides with the links of its own arm here (self-collision is not this check's job).

    >>> check = ArmClearance({"left": ArmBody(robot_l, T_l), "right": ArmBody(robot_r, T_r)})
    >>> closest = check.closest({"left": q_l, "right": q_r}, {"left": g_l, "right": g_r})
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
import pinocchio as pin

from manisplat.augment.kinematics import PinRobot
from manisplat.robot import RobotModel
from manisplat.robot.hulls import convex, link_hulls


@dataclass(frozen=True)
class ArmBody:
    """One arm as the check sees it.

    Attributes:
        robot: the model whose joint convention the configurations are in, with link geometry.
        T_world_base: (4, 4) float64 pose of its base in the world, m.
    """

    robot: RobotModel
    T_world_base: np.ndarray


@dataclass(frozen=True)
class Closest:
    """Where two arms come closest over the configurations checked.

    Attributes:
        frame: index of that configuration.
        arms: the two arms' names; links: their two links there.
        distance_m: the distance between those links, m (negative: they overlap by that much).
        per_frame_m: (T,) the smallest arm-to-arm distance at every configuration, m.
    """

    frame: int
    arms: tuple[str, str]
    links: tuple[str, str]
    distance_m: float
    per_frame_m: np.ndarray


class ArmClearance:
    """The links of several arms in one world; :meth:`closest` over a trajectory of all of them."""

    def __init__(self, arms: Mapping[str, ArmBody]) -> None:
        if len(arms) < 2:
            raise ValueError(f"an arm-against-arm check needs two arms or more; got {', '.join(arms) or 'none'}")
        self.names = list(arms)
        self.gm = pin.GeometryModel()
        self._kin: dict[str, PinRobot] = {}
        self._base: dict[str, pin.SE3] = {}
        self._links: dict[str, list[tuple[int, int, pin.SE3]]] = {}  # arm -> (geometry, pin joint, placement)
        self._owner: list[tuple[str, str]] = []  # geometry index -> (arm, link)
        for name, body in arms.items():
            T = np.asarray(body.T_world_base, np.float64)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise ValueError(f"arm {name}: T_world_base must be a finite 4x4 matrix")
            kin = PinRobot(body.robot)
            self._kin[name], self._base[name] = kin, pin.SE3(T[:3, :3].copy(), T[:3, 3].copy())
            try:
                hulls = link_hulls(body.robot)
            except ValueError as exc:
                raise ValueError(f"arm {name}: {exc} (its description {body.robot.name} has no link meshes or "
                                 f"primitives)") from None
            self._links[name] = []
            for link, hull in hulls.items():
                jid, place = kin.link_joint[link]
                g = self.gm.addGeometryObject(pin.GeometryObject(f"{name}/{link}", 0, pin.SE3.Identity(),
                                                                 convex(hull.vertices)))
                self._links[name].append((g, jid, place))
                self._owner.append((name, link))
        for i, a in enumerate(self.names):
            for b in self.names[i + 1:]:
                for ga, _, _ in self._links[a]:
                    for gb, _, _ in self._links[b]:
                        self.gm.addCollisionPair(pin.CollisionPair(ga, gb))
        self.gd = pin.GeometryData(self.gm)

    def _place(self, name: str, q: np.ndarray, gripper: float) -> None:
        """Put arm ``name``'s link geometry at joints ``q`` (6,) rad, fingers opened to ``gripper`` m."""
        kin = self._kin[name]
        pin.forwardKinematics(kin.model, kin.data, kin.full_q(q, gripper))
        base = self._base[name]
        for g, jid, place in self._links[name]:
            self.gd.oMg[g] = base * kin.data.oMi[jid] * place

    def closest(self, q: Mapping[str, np.ndarray], gripper: Mapping[str, np.ndarray]) -> Closest:
        """The closest approach of two arms over T configurations: ``q[arm]`` (T, 6) rad and
        ``gripper[arm]`` (T,) m for every arm, in each arm's robot's convention."""
        missing = [n for n in self.names if n not in q or n not in gripper]
        if missing:
            raise ValueError(f"no configurations for the arm(s) {', '.join(missing)}")
        qs = {n: np.asarray(q[n], np.float64) for n in self.names}
        gs = {n: np.asarray(gripper[n], np.float64) for n in self.names}
        frames = {len(v) for v in qs.values()} | {len(v) for v in gs.values()}
        if len(frames) != 1 or not frames.pop():
            raise ValueError("every arm needs the same number (> 0) of configurations and gripper values")
        per_frame = np.empty(len(qs[self.names[0]]))
        best = (np.inf, 0, 0)
        for i in range(len(per_frame)):
            for n in self.names:
                self._place(n, qs[n][i], gs[n][i])
            k = pin.computeDistances(self.gm, self.gd)
            per_frame[i] = self.gd.distanceResults[k].min_distance
            if per_frame[i] < best[0]:
                best = (per_frame[i], i, k)
        pair = self.gm.collisionPairs[best[2]]
        (arm_a, link_a), (arm_b, link_b) = self._owner[pair.first], self._owner[pair.second]
        return Closest(best[1], (arm_a, arm_b), (link_a, link_b), float(best[0]), per_frame)
