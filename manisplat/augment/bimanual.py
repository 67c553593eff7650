"""A new demonstration of a twin of several arms that work on separate objects (a Cobot Magic
picking two things at once): each arm's skills move with the objects it handles and its motions
are re-planned as for one arm (:mod:`manisplat.augment.trajectory`, in the arm's base frame, against
the table, the background and its own objects), then the arms run together from frame 0 and every
frame is checked arm against arm and arm against the other arm's objects (coal, convex link
hulls, object boxes). Where they come closer than ``min_clearance_m``, one arm waits at its start
until the other is out of its way (the shortest of :data:`WAITS_S` that clears, either arm); a
demonstration that no wait clears is rejected.

    >>> planner = BimanualPlanner(twin)                      # raises Rejected("source", ...) for a handover
    >>> targets = planner.sample_targets(np.random.default_rng(3))
    >>> traj = planner.run(targets, AugmentConfig(seed=3))   # raises Rejected

Conventions of :class:`BimanualTrajectory`: frames at ``t = k / fps``; each arm's
:class:`~manisplat.augment.trajectory.NewTrajectory` (its base frame) on that common timeline, an
arm that finishes first holding its last frame (at rest, gripper and command unchanged); object
poses in the twin's world frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import coal
import numpy as np
import torch

from manisplat.augment.arm_view import ArmTwin, arm_twins
from manisplat.augment.collision import CollisionSettings, _object_box
from manisplat.augment.errors import Rejected
from manisplat.augment.sampling import ObjectTarget, sample_targets
from manisplat.augment.source import SourceError
from manisplat.augment.trajectory import AugmentConfig, NewTrajectory, augment_trajectory
from manisplat.robot.hulls import convex, link_hulls

MIN_ARM_CLEARANCE_M = 0.005
"""Arms (and an arm and the other arm's objects) closer than this in any frame: rejected."""
WAITS_S = (0.5, 1.0, 1.5, 2.0, 3.0)
"""When the arms would come too close, one arm waits at its start this long (s) before it moves,
the shortest wait that clears first, either arm (the demonstration is rejected when none does)."""


@dataclass
class BimanualTrajectory:
    """A new demonstration of several arms (see the module docstring).

    Attributes:
        t: [T] s. arms: arm name -> its trajectory (base frame), T frames each.
        object_poses: name -> [T, 4, 4] ``T_world_obj``. validation: per arm and between the arms.
    """

    t: np.ndarray
    arms: dict[str, NewTrajectory]
    object_poses: dict[str, np.ndarray]
    validation: dict

    def joint_state(self, k: int) -> dict[str, tuple[np.ndarray, float]]:
        """Arm name -> (q [6] rad, gripper m) at frame ``k``."""
        return {name: (traj.q[k], float(traj.gripper[k])) for name, traj in self.arms.items()}


def held_to(traj: NewTrajectory, frames: int, fps: float) -> NewTrajectory:
    """``traj`` lengthened to ``frames`` by holding its last frame (joints, gripper, command, objects)."""
    extra = frames - len(traj.t)
    if extra < 0:
        raise ValueError(f"held_to: {len(traj.t)} frames already, more than {frames}")
    if extra == 0:
        return traj

    def hold(a: np.ndarray) -> np.ndarray:
        return np.concatenate([a, np.repeat(a[-1:], extra, axis=0)], axis=0)

    return replace(traj, t=np.arange(frames) / fps, q=hold(traj.q), gripper=hold(traj.gripper),
                   action_q=hold(traj.action_q), action_gripper=hold(traj.action_gripper),
                   object_poses={k: hold(v) for k, v in traj.object_poses.items()})


def waiting(traj: NewTrajectory, frames: int, fps: float) -> NewTrajectory:
    """``traj`` started ``frames`` later: the arm holds its first frame (at rest: joints, gripper,
    objects; the command is the held state), every segment shifted and a ``wait`` segment first."""
    if frames < 0:
        raise ValueError(f"waiting: {frames} frames")
    if frames == 0:
        return traj

    def first(a: np.ndarray) -> np.ndarray:
        return np.concatenate([np.repeat(a[:1], frames, axis=0), a], axis=0)

    shifted = [{**seg, "frames": [seg["frames"][0] + frames, seg["frames"][1] + frames]} for seg in traj.segments]
    wait = {"kind": "wait", "name": "W_wait", "object": None, "frames": [0, frames - 1], "source_frames": None,
            "T": None}
    return replace(traj, t=np.arange(len(traj.t) + frames) / fps, q=first(traj.q), gripper=first(traj.gripper),
                   action_q=np.concatenate([np.repeat(traj.q[:1], frames, axis=0), traj.action_q]),
                   action_gripper=np.concatenate([np.repeat(traj.gripper[:1], frames), traj.action_gripper]),
                   object_poses={k: first(v) for k, v in traj.object_poses.items()}, segments=[wait, *shifted])


class ArmPairCheck:
    """Distances between the arms' convex link hulls, and between each arm's links and the boxes
    of the objects the other arms handle, frame by frame (coal GJK). Pairs whose bounding
    spheres are farther apart than ``reach`` are not measured (they are clear by that much)."""

    def __init__(self, arms: dict[str, ArmTwin], reach: float = 0.05) -> None:
        self.arms, self.reach = arms, reach
        self.hulls: dict[str, dict[str, tuple[coal.ConvexBase, np.ndarray, float]]] = {}
        for name, arm in arms.items():
            self.hulls[name] = {}
            for link, hull in link_hulls(arm.robot, arm.robot_description).items():
                vertices = np.asarray(hull.vertices, np.float64)
                centre = vertices.mean(axis=0)
                self.hulls[name][link] = (convex(vertices), centre, float(np.linalg.norm(vertices - centre, axis=1).max()))
        margin = CollisionSettings().object_margin
        self.boxes: dict[str, tuple[str, coal.Box, np.ndarray, float]] = {}
        for name, arm in arms.items():
            for obj in arm.objects:
                means = arm.graph.objects[obj].params["means"].detach().double().cpu().numpy()
                extents, centre = _object_box(means, margin)
                self.boxes[obj] = (name, coal.Box(*extents), centre, float(np.linalg.norm(extents) / 2))

    def _link_poses(self, arm: str, traj: NewTrajectory) -> dict[str, np.ndarray]:
        """Link name -> [T, 4, 4] ``T_world_link`` of ``arm`` over ``traj``."""
        twin = self.arms[arm]
        poses = twin.robot.forward_kinematics(torch.as_tensor(traj.q), torch.as_tensor(traj.gripper)).numpy()
        index = {link: k for k, link in enumerate(twin.robot.link_names)}
        return {link: twin.T_world_base @ poses[:, index[link]] for link in self.hulls[arm]}

    def closest(self, arms: dict[str, NewTrajectory], object_poses: dict[str, np.ndarray]
                ) -> tuple[float, int | None, str | None]:
        """(smallest distance m, its frame, "what and what") over every frame and pair; the
        distance is ``reach`` (frame and pair None) where nothing came that close."""
        links = {name: self._link_poses(name, traj) for name, traj in arms.items()}
        names = list(arms)
        T = len(next(iter(arms.values())).t)
        best: tuple[float, int | None, str | None] = (self.reach, None, None)
        request, result = coal.DistanceRequest(), coal.DistanceResult()
        for k in range(T):
            shapes = []  # (owner arm, label, geometry, T_world_geom, centre, radius)
            for arm in names:
                for link, (hull, centre, radius) in self.hulls[arm].items():
                    shapes.append((arm, f"{arm}/{link}", hull, links[arm][link][k], centre, radius))
            for obj, (arm, box, centre, radius) in self.boxes.items():
                T_obj = object_poses[obj][k].copy()
                T_obj[:3, 3] += T_obj[:3, :3] @ centre
                shapes.append((arm, f"object {obj}", box, T_obj, np.zeros(3), radius))
            for i, (arm_a, label_a, geom_a, T_a, c_a, r_a) in enumerate(shapes):
                for arm_b, label_b, geom_b, T_b, c_b, r_b in shapes[i + 1:]:
                    if arm_a == arm_b:
                        continue  # an arm against its own links and objects: checked when it was planned
                    gap = np.linalg.norm(T_a[:3, :3] @ c_a + T_a[:3, 3] - T_b[:3, :3] @ c_b - T_b[:3, 3]) - r_a - r_b
                    if gap >= best[0]:
                        continue
                    result.clear()
                    d = coal.distance(geom_a, _transform(T_a), geom_b, _transform(T_b), request, result)
                    if d < best[0]:
                        best = (float(d), k, f"{label_a} and {label_b}")
        return best


class BimanualPlanner:
    """Everything about a twin of several arms that does not depend on the sample: each arm's
    :class:`ArmTwin` and the arm-pair check.

    Raises:
        Rejected: ("source", ...) when the twin cannot be augmented this way (a handover).
    """

    def __init__(self, twin, min_clearance_m: float = MIN_ARM_CLEARANCE_M) -> None:
        try:
            self.arms = arm_twins(twin)
        except SourceError as exc:
            raise Rejected("source", str(exc)) from exc
        self.twin, self.min_clearance_m, self.fps = twin, float(min_clearance_m), float(twin.fps)
        self.check = ArmPairCheck(self.arms)

    def sample_targets(self, rng: np.random.Generator, object_range=(0.08, 0.08, math.radians(45)),
                       target_range=(0.05, 0.05, math.radians(45))) -> dict[str, dict[str, ObjectTarget]]:
        """Arm name -> new start (and place) poses of the objects it handles, in its base frame
        (ranges as :func:`~manisplat.augment.sampling.sample_targets`, about the base's axes)."""
        return {name: sample_targets(arm, rng, object_range, target_range) if arm.objects else {}
                for name, arm in self.arms.items()}

    def run(self, targets: dict[str, dict[str, ObjectTarget]], config: AugmentConfig) -> BimanualTrajectory:
        """Plan every arm, put them on one timeline and check them against each other."""
        planned = {}
        for name, arm in self.arms.items():
            try:
                planned[name] = augment_trajectory(arm, targets.get(name, {}), config)
            except Rejected as exc:
                raise Rejected(exc.reason, f"{name} arm: {exc.detail}") from exc
        together, (distance, frame, pair) = self._together(planned)
        if distance < self.min_clearance_m:  # one arm waits at its start: the shortest wait that clears
            for wait_s in WAITS_S:
                for name in planned:
                    waited = dict(planned, **{name: waiting(planned[name], round(wait_s * self.fps), self.fps)})
                    candidate, clearance = self._together(waited)
                    if clearance[0] >= self.min_clearance_m:
                        candidate.validation["waited"] = {"arm": name, "s": wait_s, "without": {
                            "min_arm_clearance_m": round(distance, 5), "closest": pair, "closest_frame": frame}}
                        return self._validated(candidate, clearance)
            tried = f"; either arm waiting up to {WAITS_S[-1]:g} s did not clear" if WAITS_S else ""
            raise Rejected("arm_collision", f"{pair} come within {distance * 1e3:.1f} mm at frame {frame} "
                                            f"(t = {frame / self.fps:.2f} s; at least {self.min_clearance_m * 1e3:g} "
                                            f"mm required{tried})")
        return self._validated(together, (distance, frame, pair))

    def _together(self, planned: dict[str, NewTrajectory]
                  ) -> tuple[BimanualTrajectory, tuple[float, int | None, str | None]]:
        """The arms' trajectories on one timeline (the one that ends first holds) and their closest
        approach (m, frame, pair) by :meth:`ArmPairCheck.closest`."""
        frames = max(len(traj.t) for traj in planned.values())
        planned = {name: held_to(traj, frames, self.fps) for name, traj in planned.items()}
        object_poses = {obj: self.arms[name].to_world(traj.object_poses[obj])
                        for name, traj in planned.items() for obj in self.arms[name].objects}
        clearance = self.check.closest(planned, object_poses)
        return BimanualTrajectory(np.arange(frames) / self.fps, planned, object_poses, {}), clearance

    def _validated(self, traj: BimanualTrajectory, clearance: tuple[float, int | None, str | None]
                   ) -> BimanualTrajectory:
        """``traj`` with its validation record: every arm's and the closest approach."""
        distance, frame, pair = clearance
        traj.validation.update({"arms": {name: arm.validation for name, arm in traj.arms.items()},
                                "min_arm_clearance_m": round(distance, 5), "closest": pair, "closest_frame": frame,
                                "clearance_measured_up_to_m": self.check.reach,  # farther pairs: at least this
                                "required_arm_clearance_m": self.min_clearance_m})
        return traj


def _transform(T: np.ndarray) -> coal.Transform3s:
    return coal.Transform3s(np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]))


__all__ = ["ArmPairCheck", "BimanualPlanner", "BimanualTrajectory", "MIN_ARM_CLEARANCE_M", "WAITS_S", "held_to",
           "waiting"]
