"""The source demonstration as augmentation sees it: the twin's joints, gripper, object poses and
phases turned into an ordered list of skills (each bound to one object and one object pose it is
relative to) with the Motions between them.

Per manipulated object (one that has a Skill phase):
* ``T_rest`` = its pose at frame 0 (where it starts, and where the pick happens);
* a grasp = the first gripper closing (:func:`manisplat.align.phases.gripper_events`) that falls in
  one of its skills, the release = that event's opening; ``G = inv(T_tcp(grasp)) @ T_rest`` is the
  grasp offset (object in the TCP frame) kept while it is held;
* ``T_placed`` = its pose at the last frame (where a pick-and-place leaves it), when released.
Roles of its skills: the one holding the grasp is the "pick" (relative to ``T_rest``), the one
holding the release the "place" (relative to ``T_placed``), any other is relative to ``T_rest``
before the release and ``T_placed`` after it ("reach"). Skills of different objects must not
overlap in time.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from manisplat.align.phases import gripper_events
from manisplat.geometry import orthonormalize
from manisplat.twin.commands import CommandRelation


class SourceError(ValueError):
    """The twin's demonstration cannot be augmented (no phases, overlapping skills, ...)."""


@dataclass(frozen=True)
class SkillSpec:
    """One skill: source frames ``first..last`` (inclusive) acting on ``object``.

    ``role``: "pick", "place" or "reach"; ``relative_to``: "start" (the object's start pose) or
    "place" (its placed pose).
    """

    name: str
    object: str
    first: int
    last: int
    role: str
    relative_to: str


@dataclass
class ObjectSource:
    name: str
    T_rest: np.ndarray
    T_placed: np.ndarray | None
    grasp: int | None              # source frame where the gripper starts closing on it
    release: int | None            # source frame where it opens again
    G: np.ndarray | None           # T_tcp_obj while held
    manipulated: bool


@dataclass
class SourceDemo:
    fps: float
    q: np.ndarray                  # [T, dof]
    gripper: np.ndarray            # [T]
    tcp: np.ndarray                # [T, 4, 4]
    skills: list[SkillSpec]
    objects: dict[str, ObjectSource]
    object_poses: dict[str, np.ndarray] = field(default_factory=dict)
    commands: CommandRelation | None = None  # how its commands led and pressed its joints, if recorded

    @property
    def n_frames(self) -> int:
        return len(self.q)

    @property
    def dt(self) -> float:
        return 1.0 / self.fps


def source_demo(twin) -> SourceDemo:
    """The :class:`SourceDemo` of a :class:`~manisplat.twin.Twin`; raises :class:`SourceError`."""
    q = np.asarray(twin.q, np.float64)
    gripper = np.asarray(twin.gripper, np.float64)
    if len(q) < 2:
        raise SourceError("the demonstration has fewer than 2 frames")
    if not twin.fps > 0:
        raise SourceError(f"the twin's fps is {twin.fps}")
    tcp = twin.robot.tcp_pose(torch.as_tensor(q)).numpy()
    events = gripper_events(gripper)
    skills: list[SkillSpec] = []
    objects: dict[str, ObjectSource] = {}
    for name in twin.objects:
        poses = twin.object_poses.get(name)
        if poses is None or len(poses) != len(q):
            raise SourceError(f"object {name!r} has no pose per frame")
        phases = [p for p in twin.phases.get(name, []) if p.kind == "skill"]
        if not phases:
            objects[name] = ObjectSource(name, rigid(poses[0]), None, None, None, None, False)
            continue
        grasp = release = None
        for ev in events:
            if any(p.start <= ev.grasp < p.end for p in phases):
                grasp, release = ev.grasp, ev.release
                break
        T_rest = rigid(poses[0])
        G = np.linalg.inv(tcp[grasp]) @ T_rest if grasp is not None else None
        T_placed = rigid(poses[-1]) if (grasp is not None and release is not None) else None
        objects[name] = ObjectSource(name, T_rest, T_placed, grasp, release, G, True)
        for p in phases:
            first, last = int(p.start), int(p.end) - 1
            if last <= first:
                raise SourceError(f"skill {p.name} of {name!r} has fewer than 2 frames")
            if grasp is not None and first <= grasp <= last:
                role, rel = "pick", "start"
            elif release is not None and first <= release <= last:
                role, rel = "place", "place"
            else:
                role = "reach"
                rel = "place" if (release is not None and first >= release) else "start"
            skills.append(SkillSpec(p.name, name, first, last, role, rel))
    skills.sort(key=lambda s: s.first)
    for a, b in zip(skills, skills[1:]):
        if b.first <= a.last:
            raise SourceError(f"skills {a.name} ({a.object}, frames {a.first}-{a.last}) and {b.name} ({b.object}, "
                              f"frames {b.first}-{b.last}) overlap")
    if not skills:
        raise SourceError("the demonstration has no Skill phase")
    return SourceDemo(float(twin.fps), q, gripper, tcp, skills, objects,
                      {k: np.asarray(v, np.float64) for k, v in twin.object_poses.items()}, twin.commands)


def rigid(T: np.ndarray) -> np.ndarray:
    """A pose [4, 4] float64 with its rotation projected onto SO(3) (trained poses drift from it
    by ~1e-7), so every transform built from it is exactly rigid."""
    T = np.asarray(T, np.float64)
    out = np.eye(4)
    out[:3, :3] = orthonormalize(torch.as_tensor(T[:3, :3])).numpy()
    out[:3, 3] = T[:3, 3]
    return out
