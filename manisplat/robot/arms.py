"""Several named arms in one world frame, seen as one robot by the scene (a Cobot Magic: two
PiPERs side by side): links named ``<arm>/<link>``, the arms' joint vectors concatenated in
order, one gripper opening per arm, every pose in the world frame (``T_world_base @ FK``)."""

from __future__ import annotations

from typing import Mapping

import numpy as np
import torch

from manisplat.robot.model import RobotModel, RobotModelError, Visual


class ArmSet:
    """Named arms, each a :class:`RobotModel` standing at ``T_world_base``.

    What the scene reads of a robot (``link_names``, ``visuals``, :meth:`forward_kinematics`) it
    offers for all arms at once; what belongs to one arm (TCP, gripper, limits) stays per arm.

    Args:
        arms: arm name -> its robot model, in the order of the joint vector.
        T_world_base: arm name -> (4, 4) pose of its base in the world (m).
    """

    def __init__(self, arms: Mapping[str, RobotModel], T_world_base: Mapping[str, np.ndarray]) -> None:
        if not arms:
            raise RobotModelError("an arm set needs at least one arm")
        missing = [name for name in arms if name not in T_world_base]
        if missing:
            raise RobotModelError(f"arms {missing}: no T_world_base (calibrate the rig: manisplat-calibrate solve-rig)")
        self.arms = dict(arms)
        self.T_world_base = {}
        for name in self.arms:
            T = np.asarray(T_world_base[name], dtype=np.float64)
            if T.shape != (4, 4) or not np.isfinite(T).all():
                raise RobotModelError(f"arm {name}: T_world_base must be a finite 4x4 matrix")
            self.T_world_base[name] = T
        self.name = " + ".join(f"{name}: {robot.name}" for name, robot in self.arms.items())
        self.arm_names = tuple(self.arms)
        self.link_names = tuple(f"{arm}/{link}" for arm, robot in self.arms.items() for link in robot.link_names)
        self.visuals: dict[str, list[Visual]] = {
            f"{arm}/{link}": visuals for arm, robot in self.arms.items() for link, visuals in robot.visuals.items()}
        dofs = [robot.dof for robot in self.arms.values()]
        starts = np.cumsum([0, *dofs])
        self._q_slices = {name: slice(int(starts[k]), int(starts[k + 1])) for k, name in enumerate(self.arms)}

    @property
    def dof(self) -> int:
        """Length of the joint vector: every arm's joints, in arm order."""
        return sum(robot.dof for robot in self.arms.values())

    def arm_q(self, q, arm: str) -> torch.Tensor:
        """The joints [..., dof_arm] of ``arm`` in the set's joint vector ``q`` [..., dof]."""
        return torch.as_tensor(q)[..., self._q_slices[arm]]

    def forward_kinematics(self, q, gripper=None) -> torch.Tensor:
        """``T_world_link`` [..., L, 4, 4] of every link of every arm (order :attr:`link_names`).

        Args:
            q: [..., dof] the arms' joints concatenated (rad).
            gripper: [..., A] each arm's gripper opening (m); None: closed.
        """
        q = torch.as_tensor(q)
        if q.shape[-1] != self.dof:
            raise RobotModelError(f"{self.name}: joint vector of length {q.shape[-1]}, expected {self.dof}")
        poses = []
        for k, (name, robot) in enumerate(self.arms.items()):
            width = None if gripper is None else torch.as_tensor(gripper)[..., k]
            local = robot.forward_kinematics(self.arm_q(q, name), width)
            base = torch.as_tensor(self.T_world_base[name], dtype=local.dtype, device=local.device)
            poses.append(base @ local)
        return torch.cat(poses, dim=-3)

    def tcp_poses(self, q) -> torch.Tensor:
        """``T_world_tcp`` [..., A, 4, 4] of every arm (order :attr:`arm_names`)."""
        q = torch.as_tensor(q)
        poses = []
        for name, robot in self.arms.items():
            local = robot.tcp_pose(self.arm_q(q, name))
            poses.append(torch.as_tensor(self.T_world_base[name], dtype=local.dtype, device=local.device) @ local)
        return torch.stack(poses, dim=-3)

    def __repr__(self) -> str:
        return f"ArmSet({self.name})"


__all__ = ["ArmSet"]
