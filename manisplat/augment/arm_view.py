"""One arm of a twin of several arms, seen as a twin of that arm alone in its base frame: what the
one-arm augmenter (:mod:`manisplat.augment.trajectory`) reads of a twin (robot, joints, gripper,
phases, the objects this arm handles at their poses, the object and background Gaussians, the
support map), so that each arm's skills are moved and its motions planned as for one arm.

Which arm handles an object is decided from the twin's own demonstration, as reconstruction
aligned it (:func:`manisplat.align.acting_arm.holds`: the arm whose gripper first closes nearest
the object's start, then any arm that takes it over). An object passed from one gripper to the
other (a handover) is handled by both arms, each seeing its own half of it
(:mod:`manisplat.augment.handover`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from manisplat.align.acting_arm import holds
from manisplat.augment.handover import Handover, find_handover, giver_part, taker_part
from manisplat.augment.source import SourceError
from manisplat.robot import RobotModel
from manisplat.robot.arms import ArmSet
from manisplat.twin import Phase, Twin
from manisplat.twin.commands import CommandRelation
from manisplat.twin.rig import TwinArm
from manisplat.twin.support import EDGE_MARGIN, MAX_STEP, SupportMap


@dataclass(frozen=True)
class PointSet:
    """Gaussian parameters as the collision model reads them: ``params["means"]`` [N, 3] (the arm's
    base frame) and ``params["opacities"]`` [N] (logits)."""

    params: dict[str, torch.Tensor]

    def __len__(self) -> int:
        return len(self.params["means"])


@dataclass(frozen=True)
class ArmScene:
    """The parts of the scene graph augmentation reads: the objects' Gaussians (canonical frames,
    as they are) and the background's, moved into the arm's base frame."""

    objects: dict
    background: PointSet | None


class BaseFrameSupport:
    """A twin's support map (world frame) read in an arm's base frame: the base is level (its z
    axis the world's), so a footprint's x, y map through the base's planar pose."""

    def __init__(self, support: SupportMap, T_world_base: np.ndarray) -> None:
        if abs(T_world_base[2, 2] - 1.0) > 1e-3:
            raise SourceError("the arm's base is not level (its z axis off the world's by more than 2.6 deg): the "
                              "support map cannot be read in its frame")
        self.support, self.T = support, np.asarray(T_world_base, np.float64)

    def _world_xy(self, xy: np.ndarray) -> np.ndarray:
        return np.asarray(xy, np.float64) @ self.T[:2, :2].T + self.T[:2, 3]

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """[N] the surface height (m, the base frame's z) under base-frame points ``xy`` [N, 2]."""
        return self.support.height_at(self._world_xy(xy)) - self.T[2, 3]

    def edge_drop(self, footprint_xy: np.ndarray, margin: float = EDGE_MARGIN) -> float | None:
        """:meth:`SupportMap.edge_drop` of a base-frame footprint [N, 2] (m)."""
        return self.support.edge_drop(self._world_xy(footprint_xy), margin)

    def smallest_edge(self, max_step: float = MAX_STEP) -> float:
        """:meth:`SupportMap.smallest_edge` (heights do not depend on the frame's x, y)."""
        return self.support.smallest_edge(max_step)


@dataclass(eq=False)
class ArmTwin:
    """One arm of a twin in its base frame, with the objects it handles (see the module docstring).

    Attributes:
        name, T_world_base: the arm and its base in the twin's world (m).
        robot: its kinematics; robot_description, robot_info: its description, model, joint names.
        t, q, gripper, fps: its part of the source demonstration ([T] s, [T, 6] rad, [T] m).
        objects: the objects this arm handles; object_poses: name -> [T, 4, 4] ``T_base_obj``.
        phases: name -> the object's Motion/Skill segments.
        graph: :class:`ArmScene`; support: :class:`BaseFrameSupport` or None.
        commands: its part of the source's :class:`CommandRelation` (press [T, 6] rad), or None.
    """

    name: str
    T_world_base: np.ndarray
    robot: RobotModel
    robot_description: str
    robot_info: dict
    t: np.ndarray
    q: np.ndarray
    gripper: np.ndarray
    fps: float
    objects: list[str]
    object_poses: dict[str, np.ndarray]
    phases: dict[str, list[Phase]]
    graph: ArmScene
    support: BaseFrameSupport | None
    commands: CommandRelation | None = None

    @property
    def n_frames(self) -> int:
        return len(self.t)

    def to_world(self, T_base: np.ndarray) -> np.ndarray:
        """Poses [..., 4, 4] in this arm's base frame -> the twin's world frame."""
        return self.T_world_base @ np.asarray(T_base, np.float64)


def handling(twin: Twin) -> tuple[dict[str, list[str]], list[Handover]]:
    """Who handles what: arm name -> the twin's objects it handles (every arm listed, in order; a
    handed-over object under both arms), and the objects passed from one arm to the other.

    Raises:
        SourceError: a handover that :func:`~manisplat.augment.handover.find_handover` cannot augment.
    """
    positions = twin.robot.tcp_poses(torch.as_tensor(twin.q)).numpy()[..., :3, 3]  # [T, A, 3], every arm at once
    tcp = {name: positions[:, k] for k, name in enumerate(twin.arm_names)}
    gripper = {name: g for name, (_, g) in twin.arm_tracks().items()}
    handled: dict[str, list[str]] = {name: [] for name in twin.arm_names}
    handed = []
    for obj in twin.objects:
        order = holds(tcp, gripper, twin.object_poses[obj][0][:3, 3])
        for arm in dict.fromkeys(h.arm for h in order):
            handled[arm].append(obj)
        if len(order) > 1:
            handed.append(find_handover(obj, order, tcp, gripper, twin.object_poses[obj]))
    return handled, handed


def arm_twins(twin: Twin, handled: dict[str, list[str]], handed: list[Handover]) -> dict[str, ArmTwin]:
    """Each arm of a twin of several arms as an :class:`ArmTwin`, from :func:`handling`'s
    ``handled`` objects and ``handed`` ones (raises :class:`SourceError`)."""
    if not isinstance(twin.robot, ArmSet):
        raise SourceError("arm_twins: the twin has one arm; augment it as it is")
    tracks = twin.arm_tracks()
    parts = {}  # (arm, object) -> (world poses [T, 4, 4], phases) where the arm sees a part of a handover
    for h in handed:
        poses, phases = twin.object_poses[h.object], twin.phases.get(h.object, [])
        parts[h.giver, h.object] = giver_part(h, poses, phases)
        parts[h.taker, h.object] = taker_part(h, poses, phases)
    background = twin.graph.background
    commands = twin.arm_commands()
    out = {}
    for arm in twin.arms:
        T_base_world = np.linalg.inv(arm.T_world_base)
        seen = {name: parts.get((arm.name, name), (twin.object_poses[name], twin.phases.get(name, [])))
                for name in handled[arm.name]}
        out[arm.name] = ArmTwin(
            name=arm.name, T_world_base=arm.T_world_base, robot=twin.robot.arms[arm.name],
            robot_description=arm.description, robot_info=_info(arm), t=twin.t, q=tracks[arm.name][0],
            gripper=tracks[arm.name][1], fps=twin.fps, objects=handled[arm.name],
            object_poses={name: T_base_world @ poses for name, (poses, _) in seen.items()},
            phases={name: phases for name, (_, phases) in seen.items()},
            graph=ArmScene({name: twin.graph.objects[name] for name in handled[arm.name]},
                           None if background is None else _moved(background, T_base_world)),
            support=None if twin.support is None else BaseFrameSupport(twin.support, arm.T_world_base),
            commands=commands[arm.name],
        )
    return out


def _info(arm: TwinArm) -> dict:
    return {"model": arm.model, "joint_names": list(arm.joint_names)}


def _moved(gaussians, T: np.ndarray) -> PointSet:
    """The background's means (and opacities) moved by ``T`` [4, 4] (world -> the arm's base)."""
    means = gaussians.params["means"].detach().double().cpu().numpy()
    moved = means @ T[:3, :3].T + T[:3, 3]
    return PointSet({"means": torch.from_numpy(moved), "opacities": gaussians.params["opacities"].detach().cpu()})


__all__ = ["ArmScene", "ArmTwin", "BaseFrameSupport", "PointSet", "arm_twins", "handling"]
