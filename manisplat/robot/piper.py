"""The AgileX PiPER: a built-in model in piper_sdk's joint convention, and the settings that
make AgileX's own URDF (``piper_description``) usable.

Built-in model (``builtin:agilex_piper``), what a real arm reports on CAN (firmware S-V1.6-3+):
* Kinematics: piper_sdk's modified-DH table (``piper_sdk/kinematics/piper_fk.py``,
  ``dh_is_offset=1``): link i = RotX(alpha) TransX(a) RotZ(theta + offset) TransZ(d). Link
  frames are the DH frames, so ``link6`` is the SDK's flange frame.
* Position limits: piper_sdk ``piper_param_manager.py`` (J1 +-150 deg, J2 0..180, J3 -170..0,
  J4 +-100, J5 +-70, J6 +-120).
* Speed limits: AgileX's PiPER datasheet, 180/195/180/225/225/225 deg/s for J1..J6 (as quoted
  in third-party copies of the datasheet; other AgileX sources disagree: the newer URDF says
  5 rad/s (J6 3), the MoveIt config 5 rad/s, the firmware's configurable cap 0..3 rad/s, and
  the older URDF carries placeholders 0 and 1). Replay should still scale these down.
* Acceleration limits: 5 rad/s^2 per joint, the SDK's default ``max_joint_acc=500`` in units
  of 0.01 rad/s^2 (``JointMaxAccConfig``); the factory value is not documented.
* TCP (docs/episode-format.md): midway between the finger pads, 0.12 m along the flange z
  axis. In the DH flange frame its axes are the flange axes (z approach, y closing): AgileX's
  URDF ``link6`` is the DH flange rotated by +90 deg about z, and the episode format puts the
  TCP at Rz(-90 deg) there.
* Gripper: two fingers sliding along the flange y axis, each by half the opening width.
* Geometry: simple primitives sized from AgileX's meshes (capsules, cylinders, boxes), so the
  model works with no mesh files; accurate to a few millimetres, not a CAD model.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import trimesh
from lxml import etree

from manisplat.robot.model import Gripper, Joint, JointLimits, RobotModel, Visual
from manisplat.robot.urdf import load_urdf

BUILTIN_NAME = "builtin:agilex_piper"
ARM_JOINTS = ("joint1", "joint2", "joint3", "joint4", "joint5", "joint6")

# piper_sdk modified DH (dh_is_offset=1): alpha (rad), a (m), d (m), theta offset (rad).
DH_ALPHA = (0.0, -math.pi / 2, 0.0, math.pi / 2, -math.pi / 2, math.pi / 2)
DH_A = (0.0, 0.0, 0.28503, -0.02198, 0.0, 0.0)
DH_D = (0.123, 0.0, 0.0, 0.25075, 0.0, 0.091)
DH_THETA_OFFSET = (0.0, math.radians(-172.22), math.radians(-102.78), 0.0, 0.0, 0.0)

SDK_LOWER = (-2.6179, 0.0, -2.967, -1.745, -1.22, -2.09439)
SDK_UPPER = (2.6179, 3.14, 0.0, 1.745, 1.22, 2.09439)
VELOCITY_LIMITS = tuple(math.radians(v) for v in (180.0, 195.0, 180.0, 225.0, 225.0, 225.0))
ACCELERATION_LIMITS = (5.0,) * 6
GRIPPER_WIDTH_RANGE = (0.0, 0.07)
TCP_OFFSET = 0.12
FINGER_BASE_Z = 0.135


def _translation(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def _rot(axis: str, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    T = np.eye(4)
    i, j = {"x": (1, 2), "z": (0, 1)}[axis]
    T[i, i], T[i, j], T[j, i], T[j, j] = c, -s, s, c
    return T


def dh_origin(i: int) -> np.ndarray:
    """Joint i's (0-based) origin: RotX(alpha) TransX(a) RotZ(offset) TransZ(d).

    ``origin @ RotZ(theta)`` equals the DH link transform at joint angle theta, because RotZ
    commutes with RotZ(offset) TransZ(d).
    """
    return _rot("x", DH_ALPHA[i]) @ _translation(x=DH_A[i]) @ _rot("z", DH_THETA_OFFSET[i]) @ _translation(z=DH_D[i])


def _segment_primitive(kind: str, start, end, radius: float) -> trimesh.Trimesh:
    start, end = np.asarray(start, float), np.asarray(end, float)
    if kind == "cylinder":
        return trimesh.creation.cylinder(radius=radius, segment=np.stack([start, end]), sections=24)
    length = float(np.linalg.norm(end - start))
    mesh = trimesh.creation.capsule(height=length, radius=radius, count=[24, 12])
    T = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], (end - start) / length)
    T[:3, 3] = (start + end) / 2
    mesh.apply_transform(T)
    return mesh


def _box(center, extents) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents, transform=_translation(*center))


def builtin_primitives() -> dict[str, list[Visual]]:
    """Primitive geometry per link in the built-in (DH) link frames, sized from AgileX's meshes."""
    shapes = {
        "base_link": _segment_primitive("cylinder", (0, 0, 0), (0, 0, 0.086), 0.045),
        "link1": _segment_primitive("cylinder", (0, 0, -0.043), (0, 0, 0.03), 0.037),
        "link2": _segment_primitive("capsule", (0, 0, 0), (0.285, 0, 0), 0.045),
        "link3": _segment_primitive("capsule", (0, 0, 0), (-0.021, -0.19, 0), 0.033),
        "link4": _segment_primitive("cylinder", (0, 0, -0.036), (0, 0, 0.0285), 0.030),
        "link5": _segment_primitive("capsule", (0, 0, 0), (0, -0.07, 0), 0.030),
        "link6": _box((-0.00475, 0.0, 0.0335), (0.0705, 0.145, 0.067)),
        # Fingers, in their joint frames at zero opening: pad face on the plane y = 0.
        "link7": _box((0.0, -0.01225, -0.03325), (0.056, 0.0245, 0.0765)),
        "link8": _box((0.0, 0.01225, -0.03325), (0.056, 0.0245, 0.0765)),
    }
    return {link: [Visual(mesh, "primitive")] for link, mesh in shapes.items()}


def builtin_piper(*, with_geometry: bool = True) -> RobotModel:
    """The built-in PiPER in piper_sdk's convention (see the module docstring for sources)."""
    joints = []
    parent = "base_link"
    for i, name in enumerate(ARM_JOINTS):
        limits = JointLimits(SDK_LOWER[i], SDK_UPPER[i], VELOCITY_LIMITS[i], ACCELERATION_LIMITS[i])
        joints.append(Joint(name, "revolute", parent, f"link{i + 1}", dh_origin(i), np.array([0.0, 0.0, 1.0]), limits))
        parent = f"link{i + 1}"
    half = GRIPPER_WIDTH_RANGE[1] / 2
    finger_origin = _translation(z=FINGER_BASE_Z)
    joints.append(Joint("joint7", "prismatic", "link6", "link7", finger_origin, np.array([0.0, -1.0, 0.0]), JointLimits(0.0, half)))
    joints.append(Joint("joint8", "prismatic", "link6", "link8", finger_origin, np.array([0.0, 1.0, 0.0]), JointLimits(0.0, half)))
    return RobotModel(
        name=BUILTIN_NAME,
        joints=joints,
        arm_joints=ARM_JOINTS,
        tcp_link="link6",
        T_link_tcp=_translation(z=TCP_OFFSET),
        gripper=Gripper((("joint7", 0.5), ("joint8", 0.5)), GRIPPER_WIDTH_RANGE),
        visuals=builtin_primitives() if with_geometry else {},
    )


def is_agilex_piper_urdf(path: str | Path) -> bool:
    """True for AgileX's ``piper_description`` URDF: a robot named like "piper" with joints
    joint1..joint8 where joint7/joint8 are the prismatic fingers."""
    try:
        root = etree.parse(str(path)).getroot()
    except etree.XMLSyntaxError:
        return False
    kinds = {j.get("name"): j.get("type") for j in root.iter("joint")}
    arm = all(kinds.get(f"joint{i}") in ("revolute", "continuous") for i in range(1, 7))
    fingers = kinds.get("joint7") == kinds.get("joint8") == "prismatic"
    return "piper" in (root.get("name") or "").lower() and arm and fingers


def load_agilex_piper_urdf(path: str | Path, *, load_meshes: bool = True) -> RobotModel:
    """AgileX's ``piper_description`` URDF with the settings its file lacks.

    * TCP: ``link6`` @ [Rz(-90 deg), (0, 0, 0.12)] (docs/episode-format.md).
    * Fingers: joint7 = +width/2, joint8 = -width/2. These lie outside the limits the file
      declares (their signs are wrong for its own geometry); the model follows the geometry.
    * Speed and acceleration limits: the PiPER's real ones (the file has placeholders).
    """
    T_link6_tcp = _rot("z", -math.pi / 2) @ _translation(z=TCP_OFFSET)
    return load_urdf(
        path,
        arm_joints=ARM_JOINTS,
        tcp_link="link6",
        T_link_tcp=T_link6_tcp,
        gripper=Gripper((("joint7", 0.5), ("joint8", -0.5)), GRIPPER_WIDTH_RANGE),
        velocity_limits=dict(zip(ARM_JOINTS, VELOCITY_LIMITS)),
        acceleration_limits=dict(zip(ARM_JOINTS, ACCELERATION_LIMITS)),
        load_meshes=load_meshes,
    )
