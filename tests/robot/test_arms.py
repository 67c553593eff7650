"""Several arms as one robot in the world frame (a Cobot Magic): the set's forward kinematics is
each arm's at its base pose, its links and visuals are named by arm, and what it needs is checked."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from manisplat.robot import RobotModelError, builtin_piper
from manisplat.robot.arms import ArmSet


def base(y: float, yaw_deg: float = 0.0) -> np.ndarray:
    """[4, 4] a base at (0, y, 0) turned by ``yaw_deg`` about z."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[1, 3] = y
    return T


@pytest.fixture(scope="module")
def arms() -> ArmSet:
    robot = builtin_piper()
    return ArmSet({"left": robot, "right": robot}, {"left": base(0.3, 10.0), "right": base(-0.3, -5.0)})


def test_each_arms_links_are_its_forward_kinematics_at_its_base(arms: ArmSet) -> None:
    robot = arms.arms["left"]
    generator = torch.Generator().manual_seed(0)
    q_left, q_right = (robot.sample_configurations(4, generator=generator, dtype=torch.float64) for _ in range(2))
    gripper = torch.tensor([[0.01, 0.05]] * 4, dtype=torch.float64)
    poses = arms.forward_kinematics(torch.cat([q_left, q_right], 1), gripper)
    L = len(robot.link_names)
    assert poses.shape == (4, 2 * L, 4, 4)
    left = torch.as_tensor(arms.T_world_base["left"]) @ robot.forward_kinematics(q_left, gripper[:, 0])
    right = torch.as_tensor(arms.T_world_base["right"]) @ robot.forward_kinematics(q_right, gripper[:, 1])
    torch.testing.assert_close(poses[:, :L], left, atol=1e-12, rtol=0)
    torch.testing.assert_close(poses[:, L:], right, atol=1e-12, rtol=0)
    tcp = arms.tcp_poses(torch.cat([q_left, q_right], 1))
    torch.testing.assert_close(tcp[:, 1], torch.as_tensor(arms.T_world_base["right"]) @ robot.tcp_pose(q_right),
                               atol=1e-12, rtol=0)


def test_links_and_visuals_are_named_by_arm(arms: ArmSet) -> None:
    robot = arms.arms["left"]
    assert arms.link_names[0] == f"left/{robot.link_names[0]}"
    assert arms.link_names[len(robot.link_names)] == f"right/{robot.link_names[0]}"
    assert set(arms.visuals) == {f"{a}/{link}" for a in ("left", "right") for link in robot.visuals}
    assert arms.dof == 2 * robot.dof and arms.arm_names == ("left", "right")


def test_what_an_arm_set_needs_is_checked_by_name() -> None:
    robot = builtin_piper()
    with pytest.raises(RobotModelError, match=r"\['right'\]: no T_world_base"):
        ArmSet({"left": robot, "right": robot}, {"left": np.eye(4)})
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(RobotModelError, match="arm left: T_world_base must be a finite 4x4"):
        ArmSet({"left": robot}, {"left": bad})
    arms = ArmSet({"left": robot, "right": robot}, {"left": np.eye(4), "right": np.eye(4)})
    with pytest.raises(RobotModelError, match="length 6, expected 12"):
        arms.forward_kinematics(torch.zeros(6, dtype=torch.float64))
