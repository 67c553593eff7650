"""Robot models: kinematic trees with limits, TCP and gripper; batched FK, Jacobian and IK.

``load_robot(description)`` reads what an episode's ``robot.description`` names
(``docs/episode-format.md``): a built-in name such as ``builtin:agilex_piper`` (piper_sdk's
convention, primitive geometry, no files needed) or a URDF path (AgileX's ``piper_description``
gets its TCP, finger mapping and real speed limits).
"""

import os
from pathlib import Path
from typing import Callable

from manisplat.robot.ik import IKResult, solve_ik
from manisplat.robot.model import Gripper, Joint, JointLimits, RobotModel, RobotModelError, Visual, link_meshes
from manisplat.robot.piper import BUILTIN_NAME, builtin_piper, is_agilex_piper_urdf, load_agilex_piper_urdf
from manisplat.robot.urdf import load_urdf

BUILTINS: dict[str, Callable[[], RobotModel]] = {BUILTIN_NAME: builtin_piper}
"""The robot descriptions that need no file, by name."""


def description_file(description: str, base_dir: str | Path | None = None) -> Path | None:
    """The URDF file a ``robot.description`` names, or None for a built-in name.

    Args:
        description: a ``builtin:`` name or a URDF path (relative paths resolve against
            ``base_dir``, the episode folder, or the current folder without one).

    Raises:
        RobotModelError: an unknown ``builtin:`` name (the message lists the known ones).
        FileNotFoundError: no file there; the message says where it looked and how to fix it.
    """
    if description.startswith("builtin:"):
        if description not in BUILTINS:
            raise RobotModelError(f"unknown built-in robot {description!r}; known: {', '.join(BUILTINS)}")
        return None
    path = Path(description)
    if not path.is_absolute() and base_dir is not None:
        path = Path(base_dir) / path
    if not path.is_file():
        episode = base_dir if base_dir is not None else "EPISODE"
        raise FileNotFoundError(
            f"robot description {description!r} (episode.json robot.description) not found: looked at "
            f"{os.path.abspath(path)}. Pass --robot URDF|{BUILTIN_NAME} to override it, or fix the episode with "
            f"`manisplat-episode set-robot {episode} DESCRIPTION` (--embed copies the URDF and its meshes into "
            "the episode)")
    return path


def load_robot(description: str, base_dir: str | Path | None = None, *, load_meshes: bool = True) -> RobotModel:
    """The robot model an episode's ``robot.description`` names.

    Args:
        description: a name of :data:`BUILTINS` (``"builtin:agilex_piper"``) or a URDF path
            (relative paths resolve against ``base_dir``, the episode folder).
        load_meshes: read the URDF's visual meshes (not needed for kinematics).

    Raises:
        RobotModelError, FileNotFoundError: see :func:`description_file`; and what
            :func:`load_urdf` raises for a broken file.
    """
    path = description_file(description, base_dir)
    if path is None:
        return BUILTINS[description]()
    if is_agilex_piper_urdf(path):
        return load_agilex_piper_urdf(path, load_meshes=load_meshes)
    return load_urdf(path, load_meshes=load_meshes)


__all__ = [
    "BUILTINS",
    "BUILTIN_NAME",
    "Gripper",
    "IKResult",
    "Joint",
    "JointLimits",
    "RobotModel",
    "RobotModelError",
    "Visual",
    "builtin_piper",
    "description_file",
    "is_agilex_piper_urdf",
    "link_meshes",
    "load_agilex_piper_urdf",
    "load_robot",
    "load_urdf",
    "solve_ik",
]
