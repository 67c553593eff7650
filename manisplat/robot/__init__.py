"""Robot models: kinematic trees with limits, TCP and gripper; batched FK, Jacobian and IK.

``load_robot(description)`` reads what an episode's ``robot.description`` names:
``builtin:agilex_piper`` (piper_sdk's convention, primitive geometry, no files needed) or a
URDF path (AgileX's ``piper_description`` gets its TCP, finger mapping and real speed limits).
"""

from pathlib import Path

from manisplat.robot.ik import IKResult, solve_ik
from manisplat.robot.model import Gripper, Joint, JointLimits, RobotModel, RobotModelError, Visual
from manisplat.robot.piper import BUILTIN_NAME, builtin_piper, is_agilex_piper_urdf, load_agilex_piper_urdf
from manisplat.robot.urdf import load_urdf


def load_robot(description: str, base_dir: str | Path | None = None, *, load_meshes: bool = True) -> RobotModel:
    """The robot model an episode's ``robot.description`` names.

    Args:
        description: ``"builtin:agilex_piper"`` or a URDF path (relative paths resolve
            against ``base_dir``, the episode folder).
        load_meshes: read the URDF's visual meshes (not needed for kinematics).
    """
    if description == BUILTIN_NAME:
        return builtin_piper()
    if description.startswith("builtin:"):
        raise RobotModelError(f"unknown built-in robot {description!r}; known: {BUILTIN_NAME!r}")
    path = Path(description)
    if not path.is_absolute() and base_dir is not None:
        path = Path(base_dir) / path
    if not path.is_file():
        raise FileNotFoundError(f"robot description {description!r} not found (looked at {path})")
    if is_agilex_piper_urdf(path):
        return load_agilex_piper_urdf(path, load_meshes=load_meshes)
    return load_urdf(path, load_meshes=load_meshes)


__all__ = [
    "BUILTIN_NAME",
    "Gripper",
    "IKResult",
    "Joint",
    "JointLimits",
    "RobotModel",
    "RobotModelError",
    "Visual",
    "builtin_piper",
    "is_agilex_piper_urdf",
    "load_agilex_piper_urdf",
    "load_robot",
    "load_urdf",
    "solve_ik",
]
