"""A new demonstration of a twin of several arms that work on separate objects (a Cobot Magic
picking two things at once): each arm's skills move with the objects it handles and its motions
are re-planned as for one arm (:mod:`manisplat.augment.trajectory`, in the arm's base frame, against
the table, the background and its own objects), then the arms run together from frame 0 and every
frame is checked arm against arm and arm against the other arm's objects (coal, convex link
hulls, object boxes). Where they come closer than ``min_clearance_m``, one arm waits at its start
until the other is out of its way (the shortest of :data:`WAITS_S` that clears, either arm); a
demonstration that no wait clears is rejected.

An object handed from one arm to the other (:mod:`manisplat.augment.handover`) is planned by each
arm for its half; the arm that would reach the shared handover skill first waits at its start until
both enter it at the same frame (no other wait then), and inside that skill the link pairs that the
source demonstration itself brought closer than the clearance (the two grippers on one object) are
not measured.

    >>> planner = BimanualPlanner(twin)                      # raises Rejected("source", ...)
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

from manisplat.augment.arm_view import ArmTwin, arm_twins, handling
from manisplat.augment.collision import CollisionSettings, _object_box
from manisplat.augment.draws import Draws
from manisplat.augment.errors import Rejected
from manisplat.augment.handover import (HANDOVER_RANGE, HANDOVER_SKILL, Handover, entry_delays, handed_track,
                                        moved_handover, output_frame, skill_segment)
from manisplat.augment.sampling import ObjectTarget, sample_targets
from manisplat.augment.source import SourceError
from manisplat.augment.trajectory import AugmentConfig, NewTrajectory, augment_trajectory, augmenter_for
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


@dataclass(frozen=True)
class HandoverWindow:
    """Frames ``first..last`` (inclusive) of the common timeline where ``giver`` and ``taker`` share
    the handover skill of ``object``: there the link pairs in ``allowed`` (frozensets of two
    "<arm>/<link>" labels) are not measured, and the object belongs to both arms; before, to the
    giver; after, to the taker."""

    object: str
    giver: str
    taker: str
    first: int
    last: int
    allowed: frozenset

    def owners(self, k: int) -> frozenset[str]:
        if k < self.first:
            return frozenset({self.giver})
        return frozenset({self.giver, self.taker}) if k <= self.last else frozenset({self.taker})


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
        self.boxes: dict[str, tuple[frozenset[str], coal.Box, np.ndarray, float]] = {}
        for name, arm in arms.items():
            for obj in arm.objects:
                owners = frozenset({name}) | (self.boxes[obj][0] if obj in self.boxes else frozenset())
                means = arm.graph.objects[obj].params["means"].detach().double().cpu().numpy()
                extents, centre = _object_box(means, margin)
                self.boxes[obj] = (owners, coal.Box(*extents), centre, float(np.linalg.norm(extents) / 2))

    def _link_poses(self, arm: str, q: np.ndarray, gripper: np.ndarray) -> dict[str, np.ndarray]:
        """Link name -> [T, 4, 4] ``T_world_link`` of ``arm`` at joints ``q`` [T, 6] and ``gripper`` [T]."""
        twin = self.arms[arm]
        poses = twin.robot.forward_kinematics(torch.as_tensor(q), torch.as_tensor(gripper)).numpy()
        index = {link: k for k, link in enumerate(twin.robot.link_names)}
        return {link: twin.T_world_base @ poses[:, index[link]] for link in self.hulls[arm]}

    def _candidates(self, k: int, links: dict[str, dict[str, np.ndarray]], object_poses: dict[str, np.ndarray],
                    windows: tuple[HandoverWindow, ...]):
        """Yield the pairs to measure at frame ``k``: (bounding-sphere gap m, label, geometry,
        T_world_geom, label, geometry, T_world_geom)."""
        window = next((w for w in windows if w.first <= k <= w.last), None)
        shapes = []  # (owner arms, label, geometry, T_world_geom, centre, radius)
        for arm, poses in links.items():
            for link, (hull, centre, radius) in self.hulls[arm].items():
                shapes.append((frozenset({arm}), f"{arm}/{link}", hull, poses[link][k], centre, radius))
        for obj, (owners, box, centre, radius) in self.boxes.items():
            owners = next((w.owners(k) for w in windows if w.object == obj), owners)
            T_obj = object_poses[obj][k].copy()
            T_obj[:3, 3] += T_obj[:3, :3] @ centre
            shapes.append((owners, f"object {obj}", box, T_obj, np.zeros(3), radius))
        for i, (own_a, label_a, geom_a, T_a, c_a, r_a) in enumerate(shapes):
            for own_b, label_b, geom_b, T_b, c_b, r_b in shapes[i + 1:]:
                if own_a & own_b:
                    continue  # an arm against its own links and objects: checked when it was planned
                if window is not None and frozenset({label_a, label_b}) in window.allowed:
                    continue  # as close as the source demonstration brought them in its handover
                gap = np.linalg.norm(T_a[:3, :3] @ c_a + T_a[:3, 3] - T_b[:3, :3] @ c_b - T_b[:3, 3]) - r_a - r_b
                yield gap, label_a, geom_a, T_a, label_b, geom_b, T_b

    def closest(self, arms: dict[str, NewTrajectory], object_poses: dict[str, np.ndarray],
                windows: tuple[HandoverWindow, ...] = ()) -> tuple[float, int | None, str | None]:
        """(smallest distance m, its frame, "what and what") over every frame and pair; the
        distance is ``reach`` (frame and pair None) where nothing came that close."""
        links = {name: self._link_poses(name, traj.q, traj.gripper) for name, traj in arms.items()}
        best: tuple[float, int | None, str | None] = (self.reach, None, None)
        request, result = coal.DistanceRequest(), coal.DistanceResult()
        for k in range(len(next(iter(arms.values())).t)):
            for gap, label_a, geom_a, T_a, label_b, geom_b, T_b in self._candidates(k, links, object_poses, windows):
                if gap >= best[0]:
                    continue
                result.clear()
                d = coal.distance(geom_a, _transform(T_a), geom_b, _transform(T_b), request, result)
                if d < best[0]:
                    best = (float(d), k, f"{label_a} and {label_b}")
        return best

    def within(self, joints: dict[str, tuple[np.ndarray, np.ndarray]], object_poses: dict[str, np.ndarray],
               frames: range, distance: float, windows: tuple[HandoverWindow, ...] = ()) -> set[frozenset[str]]:
        """The pairs (frozensets of two labels) nearer than ``distance`` in any of ``frames``, at
        joints arm name -> (q [T, 6], gripper [T])."""
        links = {name: self._link_poses(name, q, g) for name, (q, g) in joints.items()}
        found: set[frozenset[str]] = set()
        request, result = coal.DistanceRequest(), coal.DistanceResult()
        for k in frames:
            for gap, label_a, geom_a, T_a, label_b, geom_b, T_b in self._candidates(k, links, object_poses, windows):
                if gap >= distance or frozenset({label_a, label_b}) in found:
                    continue
                result.clear()
                if coal.distance(geom_a, _transform(T_a), geom_b, _transform(T_b), request, result) < distance:
                    found.add(frozenset({label_a, label_b}))
        return found


class BimanualPlanner:
    """Everything about a twin of several arms that does not depend on the sample: each arm's
    :class:`ArmTwin`, the handover (if any) and the arm-pair check.

    Raises:
        Rejected: ("source", ...) when the twin cannot be augmented this way (e.g. an object that
            changes hands twice, or two handovers).
    """

    def __init__(self, twin, min_clearance_m: float = MIN_ARM_CLEARANCE_M) -> None:
        try:
            handled, self.handovers = handling(twin)
            self.arms = arm_twins(twin, handled, self.handovers)
        except SourceError as exc:
            raise Rejected("source", str(exc)) from exc
        if len(self.handovers) > 1:
            raise Rejected("source", f"{len(self.handovers)} objects change hands "
                                     f"({', '.join(h.object for h in self.handovers)}): augmentation handles one handover")
        self.twin, self.min_clearance_m, self.fps = twin, float(min_clearance_m), float(twin.fps)
        self.check = ArmPairCheck(self.arms)
        self.allowed = {h.object: self._source_contacts(h) for h in self.handovers}

    def _source_contacts(self, handover: Handover) -> frozenset[frozenset[str]]:
        """The link pairs of the two arms that the source demonstration itself brings closer than
        the clearance during its handover skill (the grippers on one object)."""
        tracks = self.twin.arm_tracks()
        joints = {name: tracks[name] for name in self.arms}
        whole = HandoverWindow(handover.object, handover.giver, handover.taker, 0, self.twin.n_frames, frozenset())
        pairs = self.check.within(joints, {obj: self.twin.object_poses[obj] for obj in self.check.boxes},
                                  range(handover.skill.start, handover.skill.end), self.min_clearance_m, (whole,))
        return frozenset(p for p in pairs if not any(label.startswith("object ") for label in p))

    def sample_targets(self, rng: Draws, object_range=(0.08, 0.08, math.radians(45)),
                       target_range=(0.05, 0.05, math.radians(45)), handover_range=HANDOVER_RANGE
                       ) -> dict[str, dict[str, ObjectTarget]]:
        """Arm name -> new start (and place) poses of the objects it handles, in its base frame
        (ranges as :func:`~manisplat.augment.sampling.sample_targets`, about the base's axes); a
        handed object's new handover pose (:func:`~manisplat.augment.handover.moved_handover`,
        ``handover_range`` m along the world's axes) is where the giver leaves it and the taker
        finds it."""
        out = {name: sample_targets(arm, rng, object_range, target_range) if arm.objects else {}
               for name, arm in self.arms.items()}
        for h in self.handovers:
            T_world_handover = moved_handover(h.T_world_obj, rng, handover_range)
            giver, taker = out[h.giver][h.object], out[h.taker][h.object]
            out[h.giver][h.object] = ObjectTarget(giver.T_start,
                                                  np.linalg.inv(self.arms[h.giver].T_world_base) @ T_world_handover)
            out[h.taker][h.object] = ObjectTarget(np.linalg.inv(self.arms[h.taker].T_world_base) @ T_world_handover,
                                                  taker.T_place)
        return out

    def sample_starts(self, rng: Draws, half_range: float) -> dict[str, np.ndarray]:
        """Arm name -> its first joints (rad) for a new demonstration: the source's moved by up to
        +-``half_range`` rad each, within the limits the augmentation plans in (arms in the twin's
        order, one draw each)."""
        return {name: augmenter_for(arm).sample_start(rng, half_range) for name, arm in self.arms.items()}

    def run(self, targets: dict[str, dict[str, ObjectTarget]], config: AugmentConfig,
            start_q: dict[str, np.ndarray] | None = None) -> BimanualTrajectory:
        """Plan every arm (from ``start_q[arm]``, rad, where given; else the source's first joints),
        put them on one timeline and check them against each other."""
        starts = start_q or {}
        planned = {}
        for name, arm in self.arms.items():
            try:
                planned[name] = augment_trajectory(arm, targets.get(name, {}), config, starts.get(name))
            except Rejected as exc:
                raise Rejected(exc.reason, f"{name} arm: {exc.detail}") from exc
        if self.handovers:
            return self._handed_over(self._at_one_pace(planned, targets, config, self.handovers[0], starts),
                                     self.handovers[0])
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
            raise Rejected("arm_collision", _too_close(distance, frame, pair, self.fps, self.min_clearance_m, tried))
        return self._validated(together, (distance, frame, pair))

    def _at_one_pace(self, planned: dict[str, NewTrajectory], targets: dict[str, dict[str, ObjectTarget]],
                     config: AugmentConfig, handover: Handover, starts: dict[str, np.ndarray]
                     ) -> dict[str, NewTrajectory]:
        """``planned`` with the arm that plays the shared skill faster planned again at the other's
        pace (a skill is slowed uniformly where its new joints would break a limit)."""
        pace = {arm: float(skill_segment(planned[arm].segments, handover).get("slowed", 1.0))
                for arm in (handover.giver, handover.taker)}
        slowest = max(pace.values())
        for arm, own in pace.items():
            if own < slowest:
                paced = replace(config, min_slow={**config.min_slow, HANDOVER_SKILL: slowest})
                try:
                    planned = {**planned, arm: augment_trajectory(self.arms[arm], targets.get(arm, {}), paced,
                                                                  starts.get(arm))}
                except Rejected as exc:
                    raise Rejected(exc.reason, f"{arm} arm, at the other arm's pace x{slowest:.2f}: {exc.detail}") from exc
        return planned

    def _handed_over(self, planned: dict[str, NewTrajectory], handover: Handover) -> BimanualTrajectory:
        """The arms of a handover on one timeline: the one that reaches the shared skill first
        waits at its start until the other does (no other wait), then the arm-pair check."""
        delays = entry_delays({name: traj.segments for name, traj in planned.items()}, handover)
        planned = {name: waiting(traj, delays.get(name, 0), self.fps) for name, traj in planned.items()}
        together, (distance, frame, pair) = self._together(planned)
        if distance < self.min_clearance_m:
            raise Rejected("arm_collision", _too_close(distance, frame, pair, self.fps, self.min_clearance_m,
                                                       "; the handover sets when each arm moves"))
        segment = skill_segment(together.arms[handover.taker].segments, handover)
        together.validation["handover"] = {
            "object": handover.object, "giver": handover.giver, "taker": handover.taker,
            "frames": segment["frames"], "takeover_frame": output_frame(segment, handover.takeover),
            "slowed": segment["slowed"], "waited_s": {name: round(d / self.fps, 4) for name, d in delays.items()},
            "source_pairs_allowed": sorted(" and ".join(sorted(p)) for p in self.allowed[handover.object])}
        return self._validated(together, (distance, frame, pair))

    def _together(self, planned: dict[str, NewTrajectory]
                  ) -> tuple[BimanualTrajectory, tuple[float, int | None, str | None]]:
        """The arms' trajectories on one timeline (the one that ends first holds) and their closest
        approach (m, frame, pair) by :meth:`ArmPairCheck.closest`; a handed object's track is the
        giver's, then the taker's (:func:`~manisplat.augment.handover.handed_track`)."""
        frames = max(len(traj.t) for traj in planned.values())
        planned = {name: held_to(traj, frames, self.fps) for name, traj in planned.items()}
        object_poses = {obj: self.arms[name].to_world(traj.object_poses[obj])
                        for name, traj in planned.items() for obj in self.arms[name].objects}
        windows = []
        for h in self.handovers:
            giver, taker = planned[h.giver], planned[h.taker]
            object_poses[h.object] = handed_track(self.arms[h.giver].to_world(giver.object_poses[h.object]),
                                                  self.arms[h.taker].to_world(taker.object_poses[h.object]),
                                                  taker.segments, h)
            first, last = skill_segment(taker.segments, h)["frames"]
            windows.append(HandoverWindow(h.object, h.giver, h.taker, first, last, self.allowed[h.object]))
        clearance = self.check.closest(planned, object_poses, tuple(windows))
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


def _too_close(distance: float, frame: int, pair: str | None, fps: float, required: float, why: str) -> str:
    """The arm_collision message: what came how close when, and ``why`` no wait cleared it."""
    return (f"{pair} come within {distance * 1e3:.1f} mm at frame {frame} (t = {frame / fps:.2f} s; at least "
            f"{required * 1e3:g} mm required{why})")


def _transform(T: np.ndarray) -> coal.Transform3s:
    return coal.Transform3s(np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]))


__all__ = ["ArmPairCheck", "BimanualPlanner", "BimanualTrajectory", "HandoverWindow", "MIN_ARM_CLEARANCE_M",
           "WAITS_S", "held_to", "waiting"]
