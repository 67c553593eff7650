"""URDF loading through yourdfpy + trimesh: FK against hand-computed transforms, meshes,
mimic joints, package paths, limits, the AgileX PiPER preset, and clear errors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from manisplat.robot import RobotModelError, load_robot, load_urdf


def rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def tr(x=0.0, y=0.0, z=0.0):
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


TOY_URDF = """<?xml version="1.0"?>
<robot name="toy">
  <link name="base"><visual><geometry><box size="0.1 0.2 0.3"/></geometry></visual></link>
  <link name="upper">
    <visual><origin xyz="0.15 0 0"/><geometry><mesh filename="meshes/arm.stl" scale="1 1 1"/></geometry></visual>
    <visual><geometry><cylinder radius="0.02" length="0.1"/></geometry></visual>
  </link>
  <link name="fore"><visual><geometry><mesh filename="package://toy_meshes/fore.stl"/></geometry></visual></link>
  <link name="tool"/>
  <link name="finger_a"/>
  <link name="finger_b"/>
  <joint name="shoulder" type="revolute">
    <parent link="base"/><child link="upper"/>
    <origin xyz="0 0 0.1" rpy="0 0 0.5"/><axis xyz="0 0 1"/>
    <limit lower="-2" upper="2" velocity="{velocity}" effort="10"/>
  </joint>
  <joint name="slide" type="prismatic">
    <parent link="upper"/><child link="fore"/>
    <origin xyz="0.3 0 0"/><axis xyz="1 0 0"/>
    <limit lower="0" upper="0.2" velocity="0.5" effort="10"/>
  </joint>
  <joint name="tool_mount" type="fixed">
    <parent link="fore"/><child link="tool"/><origin xyz="0 0 0.05" rpy="1.5707963267948966 0 0"/>
  </joint>
  <joint name="finger_a_joint" type="prismatic">
    <parent link="tool"/><child link="finger_a"/><axis xyz="0 1 0"/>
    <limit lower="0" upper="0.04" velocity="1" effort="1"/>
  </joint>
  <joint name="finger_b_joint" type="prismatic">
    <parent link="tool"/><child link="finger_b"/><axis xyz="0 1 0"/>
    <limit lower="-0.04" upper="0" velocity="1" effort="1"/>
    <mimic joint="finger_a_joint" multiplier="-1" offset="0.01"/>
  </joint>
</robot>
"""


def write_toy(folder: Path, velocity: str = "1.5") -> Path:
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=(0.3, 0.04, 0.04)).export(folder / "meshes" / "arm.stl")
    pkg = folder / "pkg"
    pkg.mkdir(exist_ok=True)
    trimesh.creation.icosphere(radius=0.03).export(pkg / "fore.stl")
    path = folder / "toy.urdf"
    path.write_text(TOY_URDF.format(velocity=velocity))
    return path


def test_fk_matches_hand_computed_chain(tmp_path):
    model = load_urdf(
        write_toy(tmp_path),
        arm_joints=["shoulder", "slide"],
        tcp_link="tool",
        package_dirs={"toy_meshes": tmp_path / "pkg"},
    )
    q = np.array([0.7, 0.12])
    poses = model.forward_kinematics(torch.tensor(q)).numpy()
    upper = tr(z=0.1) @ rz(0.5) @ rz(q[0])
    fore = upper @ tr(x=0.3) @ tr(x=q[1])
    tool = fore @ tr(z=0.05) @ rx(math.pi / 2)
    for link, T in (("base", np.eye(4)), ("upper", upper), ("fore", fore), ("tool", tool)):
        assert np.allclose(poses[model.link_index(link)], T, atol=1e-15), link
    assert np.allclose(model.tcp_pose(torch.tensor(q)).numpy(), tool, atol=1e-15)


def test_meshes_primitives_and_mimic(tmp_path):
    model = load_urdf(
        write_toy(tmp_path),
        arm_joints=["shoulder", "slide"],
        package_dirs={"toy_meshes": tmp_path / "pkg"},
    )
    assert [v.source for v in model.visuals["upper"]] == [str(tmp_path / "meshes" / "arm.stl"), "primitive:cylinder"]
    arm_mesh = model.visuals["upper"][0].mesh
    # origin applied; STL stores float32 vertices
    assert np.allclose(arm_mesh.bounds, [[0.0, -0.02, -0.02], [0.3, 0.02, 0.02]], atol=1e-7)
    assert np.allclose(model.visuals["base"][0].mesh.extents, [0.1, 0.2, 0.3])
    # finger_a is neither arm nor gripper: held at 0, and finger_b mimics it: -1 * 0 + 0.01
    poses = model.forward_kinematics(torch.zeros(2, dtype=torch.float64))
    delta = poses[model.link_index("finger_b"), :3, 3] - poses[model.link_index("tool"), :3, 3]
    assert torch.allclose(delta, poses[model.link_index("tool"), :3, 1] * 0.01)


def test_limits_placeholders_and_overrides(tmp_path):
    path = write_toy(tmp_path, velocity="0")
    model = load_urdf(path, arm_joints=["shoulder", "slide"], load_meshes=False)
    assert np.allclose(model.lower, [-2, 0]) and np.allclose(model.upper, [2, 0.2])
    with pytest.raises(RobotModelError, match="velocity limit of shoulder is unknown"):
        model.velocity_limits
    with pytest.raises(RobotModelError, match="acceleration limit"):
        model.acceleration_limits
    fixed = load_urdf(
        path, arm_joints=["shoulder", "slide"], load_meshes=False,
        velocity_limits={"shoulder": 3.0}, acceleration_limits={"shoulder": 5.0, "slide": 1.0},
    )
    assert np.allclose(fixed.velocity_limits, [3.0, 0.5]) and np.allclose(fixed.acceleration_limits, [5.0, 1.0])
    with pytest.raises(RobotModelError, match="not in the file"):
        load_urdf(path, velocity_limits={"elbow": 1.0}, load_meshes=False)


def test_clear_errors(tmp_path):
    path = write_toy(tmp_path)
    with pytest.raises(RobotModelError, match="package_dirs"):
        load_urdf(path, arm_joints=["shoulder", "slide"])
    (tmp_path / "meshes" / "arm.stl").unlink()
    with pytest.raises(FileNotFoundError, match="arm.stl"):
        load_urdf(path, arm_joints=["shoulder", "slide"], package_dirs={"toy_meshes": tmp_path / "pkg"})
    broken = tmp_path / "broken.urdf"
    broken.write_text("<robot name='x'><link name='a'>")
    with pytest.raises(RobotModelError, match="not a readable URDF"):
        load_urdf(broken)
    with pytest.raises(FileNotFoundError):
        load_urdf(tmp_path / "nope.urdf")
    forest = tmp_path / "forest.urdf"
    forest.write_text(
        "<robot name='f'><link name='a'/><link name='b'/><link name='c'/><link name='d'/>"
        "<joint name='j1' type='revolute'><parent link='a'/><child link='b'/>"
        "<limit lower='-1' upper='1' velocity='1' effort='1'/></joint>"
        "<joint name='j2' type='fixed'><parent link='c'/><child link='d'/></joint></robot>"
    )
    with pytest.raises(RobotModelError, match="one root"):
        load_urdf(forest)
    with pytest.raises(RobotModelError, match="not an independent"):
        load_urdf(path, arm_joints=["tool_mount"], load_meshes=False)
    bad_mimic = tmp_path / "bad_mimic.urdf"
    bad_mimic.write_text(TOY_URDF.format(velocity="1").replace('mimic joint="finger_a_joint"', 'mimic joint="tool_mount"'))
    with pytest.raises(RobotModelError, match="not a movable joint"):
        load_urdf(bad_mimic, arm_joints=["shoulder", "slide"], load_meshes=False)


def piper_like_urdf(folder: Path) -> Path:
    """A chain named like AgileX's piper_description (joint1..joint8, fingers link7/link8)."""
    joints = []
    for i in range(1, 7):
        joints.append(
            f"<joint name='joint{i}' type='revolute'><parent link='{'base_link' if i == 1 else f'link{i - 1}'}'/>"
            f"<child link='link{i}'/><origin xyz='0 0 0.1'/><axis xyz='0 0 1'/>"
            f"<limit lower='-1' upper='1' velocity='0' effort='1'/></joint>"
        )
    for i, axis in ((7, "0 0 -1"), (8, "0 0 -1")):  # as in AgileX's file: both along link6 -x
        joints.append(
            f"<joint name='joint{i}' type='prismatic'><parent link='link6'/><child link='link{i}'/>"
            f"<origin xyz='0 0 0.135' rpy='0 1.5707963267948966 0'/><axis xyz='{axis}'/>"
            f"<limit lower='-0.038' upper='0.038' velocity='1' effort='1'/></joint>"
        )
    links = "".join(f"<link name='{n}'/>" for n in ["base_link"] + [f"link{i}" for i in range(1, 9)])
    path = folder / "piper_description.urdf"
    path.write_text(f"<robot name='piper_description'>{links}{''.join(joints)}</robot>")
    return path


def test_agilex_piper_urdf_gets_tcp_fingers_and_real_limits(tmp_path):
    model = load_robot(str(piper_like_urdf(tmp_path).name), base_dir=tmp_path)
    assert model.gripper.finger_joints == (("joint7", 0.5), ("joint8", -0.5))
    assert np.allclose(np.degrees(model.velocity_limits), [180, 195, 180, 225, 225, 225])
    q = torch.zeros(6, dtype=torch.float64)
    rel = torch.linalg.inv(model.link_pose(q, "link6")) @ model.tcp_pose(q)
    assert torch.allclose(rel, torch.tensor(rz(-math.pi / 2) @ tr(z=0.12)), atol=1e-15)
    # the fingers follow the geometry, outside the file's declared finger limits
    poses = model.forward_kinematics(q, torch.tensor(0.07, dtype=torch.float64))
    gap = poses[model.link_index("link8"), :3, 3] - poses[model.link_index("link7"), :3, 3]
    assert abs(float(gap.norm()) - 0.07) < 1e-15
