"""Joint conventions: how an episode's joint angles (its ``robot.description``) become the
angles a real PiPER takes on CAN (piper_sdk's convention, firmware S-V1.6-3 and later, the
``builtin:agilex_piper`` model).

Known descriptions, recognised by their joint frames (never by file name):
* ``builtin:agilex_piper``: the arm's own convention; identity.
* AgileX ``piper_description`` from ``Piper_ros`` branch ``ros-noetic-no-aloha`` @4f22c61 (the
  "old" URDF; the sample data's): ``q_arm = (q1, q2 - 2 deg, q3 + 2 deg, -q4, q5 + 0.087266, -q6)``.
  The signs: the URDF's joint4 and joint6 turn about -z. The 0.087266 rad (5 deg): the URDF tilts
  joint5's frame by -0.087266 rad. The 2 deg: piper_sdk's DH offsets for firmware S-V1.6-3+
  (-172.22 / -102.78 deg) versus the older ones this CAD matches (-174.22 / -100.78 deg).
  The mapped configuration puts the TCP within 1.5 mm and 0.002 deg of the URDF's (the two CAD
  versions differ by that much); ``shared/robots/piper_description/README.md`` has the same map.
* AgileX ``robot_description/piper_description`` @116596ce (the "new" URDF): piper_sdk's FK
  equals it within 0.14 mm; identity.

Anything else is refused (:class:`ConventionError`): a wrong map would drive the arm somewhere
else. :func:`tcp_discrepancy_mm` checks a map on the episode's own joint values by forward
kinematics of both models.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from lxml import etree

from manisplat.robot import BUILTIN_NAME, builtin_piper, load_robot

ARM_JOINTS = ("joint1", "joint2", "joint3", "joint4", "joint5", "joint6")
FINGERPRINT_TOL = 1e-4  # m and rad


class ConventionError(ValueError):
    """An episode's joint convention cannot be mapped to the arm's."""


@dataclass(frozen=True)
class JointConvention:
    """``q_arm = sign * q + offset`` (rad), per joint.

    Attributes:
        name: what the episode's angles are.
        sign: (6,) +1 or -1.
        offset: (6,) rad.
    """

    name: str
    sign: np.ndarray
    offset: np.ndarray

    @property
    def identity(self) -> bool:
        return bool(np.all(self.sign == 1.0) and np.all(self.offset == 0.0))

    def to_arm(self, q: np.ndarray) -> np.ndarray:
        """(..., 6) episode angles -> the arm's (rad)."""
        return np.asarray(q, dtype=np.float64) * self.sign + self.offset

    def from_arm(self, q_arm: np.ndarray) -> np.ndarray:
        """(..., 6) arm angles -> the episode's convention (rad)."""
        return (np.asarray(q_arm, dtype=np.float64) - self.offset) * self.sign


IDENTITY = JointConvention("piper_sdk (builtin:agilex_piper)", np.ones(6), np.zeros(6))
AGILEX_URDF_OLD = JointConvention(
    "AgileX piper_description (Piper_ros ros-noetic-no-aloha @4f22c61)",
    np.array([1.0, 1.0, 1.0, -1.0, 1.0, -1.0]),
    np.array([0.0, -math.radians(2.0), math.radians(2.0), 0.0, 0.087266, 0.0]))
AGILEX_URDF_NEW = JointConvention(
    "AgileX robot_description/piper_description (Piper_ros @116596ce)", np.ones(6), np.zeros(6))

# (xyz, rpy, axis) of joint1..joint6 as each URDF declares them
_FINGERPRINTS: list[tuple[JointConvention, list[tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]]]] = [
    (AGILEX_URDF_OLD, [
        ((0, 0, 0.123), (0, 0, -1.5708), (0, 0, 1)),
        ((0, 0, 0), (1.5708, -0.10095, -1.5708), (0, 0, 1)),
        ((0.28503, 0, 0), (0, 0, 1.3826), (0, 0, 1)),
        ((0.021984, 0.25075, 0), (-1.5708, 0, 0), (0, 0, -1)),
        ((0, 0, 0), (1.5708, -0.087266, 0), (0, 0, 1)),
        ((0, 0.091, 0.0014165), (-1.5708, -1.5708, 0), (0, 0, -1)),
    ]),
    (AGILEX_URDF_NEW, [
        ((0, 0, 0.123), (0, 0, 0), (0, 0, 1)),
        ((0, 0, 0), (1.5708, -0.1359, -3.1416), (0, 0, 1)),
        ((0.28503, 0, 0), (0, 0, -1.7939), (0, 0, 1)),
        ((-0.021984, -0.25075, 0), (1.5708, 0, 0), (0, 0, 1)),
        ((0, 0, 0), (-1.5708, 0, 0), (0, 0, 1)),
        ((8.8259e-05, -0.091, 0), (1.5708, 0, 0), (0, 0, 1)),
    ]),
]


def _numbers(text: str | None) -> tuple[float, ...]:
    return tuple(float(v) for v in (text or "0 0 0").split())


def _urdf_joints(path: Path) -> list[tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]] | None:
    """(xyz, rpy, axis) of joint1..joint6 in a URDF, None when it lacks them."""
    try:
        root = etree.parse(str(path)).getroot()
    except (etree.XMLSyntaxError, OSError) as exc:
        raise ConventionError(f"robot description {path}: cannot read the URDF: {exc}") from None
    joints = {j.get("name"): j for j in root.iter("joint")}
    out = []
    for name in ARM_JOINTS:
        j = joints.get(name)
        if j is None:
            return None
        origin, axis = j.find("origin"), j.find("axis")
        out.append((_numbers(origin.get("xyz") if origin is not None else None),
                    _numbers(origin.get("rpy") if origin is not None else None),
                    _numbers(axis.get("xyz") if axis is not None else "1 0 0")))
    return out


def _matches(found: list, known: list) -> bool:
    return all(len(f) == len(k) and np.allclose(f, k, atol=FINGERPRINT_TOL, rtol=0)
               for fj, kj in zip(found, known) for f, k in zip(fj, kj))


def resolve_description(description: str, base_dir: str | Path | None) -> Path | None:
    """The URDF file an episode's ``robot.description`` names (None for a built-in)."""
    if description.startswith("builtin:"):
        return None
    path = Path(description)
    if not path.is_absolute() and base_dir is not None:
        path = Path(base_dir) / path
    if not path.is_file():
        raise ConventionError(f"robot description {description!r} not found (looked at {path})")
    return path


def convention_for(description: str, base_dir: str | Path | None = None) -> JointConvention:
    """The map from the convention ``description`` names to the arm's; :class:`ConventionError`
    when it is not one this module knows (module docstring)."""
    if description == BUILTIN_NAME:
        return IDENTITY
    if description.startswith("builtin:"):
        raise ConventionError(f"unknown built-in robot {description!r}; the PiPER's is {BUILTIN_NAME!r}")
    path = resolve_description(description, base_dir)
    joints = _urdf_joints(path)
    if joints is not None:
        for convention, known in _FINGERPRINTS:
            if _matches(joints, known):
                return convention
    known_names = ", ".join([BUILTIN_NAME] + [c.name for c, _ in _FINGERPRINTS])
    raise ConventionError(
        f"cannot map the joint angles of {path} to the PiPER's own convention (piper_sdk): its joint1..joint6 "
        f"frames are none of the known ones ({known_names}). Convert the episode's angles to "
        f"{BUILTIN_NAME} first and name that description in episode.json")


def tcp_discrepancy_mm(convention: JointConvention, description: str, base_dir: str | Path | None,
                       q: np.ndarray) -> float:
    """Max distance (mm) between the TCP of ``description``'s model at ``q`` (N, 6) and the
    built-in model's at ``convention.to_arm(q)``: how well the map preserves the motion."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 6)
    if description == BUILTIN_NAME:
        return 0.0
    model = load_robot(description, base_dir, load_meshes=False)
    builtin = builtin_piper(with_geometry=False)
    a = model.tcp_pose(torch.from_numpy(q))[:, :3, 3]
    b = builtin.tcp_pose(torch.from_numpy(convention.to_arm(q)))[:, :3, 3]
    return float(torch.linalg.norm(a - b, dim=1).max()) * 1e3
