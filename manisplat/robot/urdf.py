"""Load a URDF (joints, limits, mimic joints, visual meshes) into a :class:`RobotModel`.

Parsing is yourdfpy's; meshes are read by trimesh (``.stl``, ``.obj``, ``.dae``, ...), with
box/cylinder/sphere primitives built by trimesh too. Mesh paths resolve relative to the URDF
file; ``package://`` paths resolve against ``package_dirs``. Nothing is clamped or "fixed":
what the file says is what the model holds, except what the caller overrides explicitly.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import trimesh
import yourdfpy
from lxml import etree

from manisplat.robot.model import Gripper, Joint, JointLimits, RobotModel, RobotModelError, Visual


def load_urdf(
    path: str | Path,
    *,
    arm_joints: Sequence[str] | None = None,
    tcp_link: str | None = None,
    T_link_tcp: np.ndarray | None = None,
    gripper: Gripper | None = None,
    velocity_limits: Mapping[str, float] | None = None,
    acceleration_limits: Mapping[str, float] | None = None,
    load_meshes: bool = True,
    package_dirs: Mapping[str, str | Path] | None = None,
) -> RobotModel:
    """Read a URDF file into a :class:`RobotModel`.

    Args:
        arm_joints: the joint vector order; default: every non-mimic revolute/prismatic joint
            that is not a gripper finger, in file order.
        tcp_link, T_link_tcp: the TCP; default: the child of the last arm joint, identity.
        gripper: finger joints driven by the gripper width (see :class:`Gripper`).
        velocity_limits, acceleration_limits: joint name -> limit, replacing the file's values
            (URDF velocity limits are often placeholders; URDF has no acceleration limits).
        load_meshes: read visual geometry (set False for kinematics only).
        package_dirs: package name -> folder, to resolve ``package://name/...`` mesh paths.

    Raises:
        FileNotFoundError: the URDF or one of its meshes is missing.
        RobotModelError: the file is not a usable URDF (parse error, not a tree, unknown joints).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"URDF not found: {path}")
    try:
        # Strict parse first: yourdfpy silently switches to lxml's recovering parser on broken
        # XML, which turns a truncated file into a smaller robot.
        etree.parse(str(path), etree.XMLParser(recover=False))
        urdf = yourdfpy.URDF.load(str(path), load_meshes=False, build_scene_graph=False)
    except Exception as exc:  # lxml and yourdfpy raise assorted error types
        raise RobotModelError(f"{path}: not a readable URDF ({exc})") from exc
    robot = urdf.robot
    velocity_limits = dict(velocity_limits or {})
    acceleration_limits = dict(acceleration_limits or {})
    unknown = (set(velocity_limits) | set(acceleration_limits)) - {j.name for j in robot.joints}
    if unknown:
        raise RobotModelError(f"{path}: limits given for joints not in the file: {sorted(unknown)}")
    joints = [_joint(j, velocity_limits, acceleration_limits, path) for j in robot.joints]

    fingers = {name for name, _ in gripper.finger_joints} if gripper else set()
    if arm_joints is None:
        arm_joints = [j.name for j in joints if j.kind != "fixed" and j.mimic is None and j.name not in fingers]
    if tcp_link is None:
        if not arm_joints:
            raise RobotModelError(f"{path}: no movable joints, so no default TCP; pass tcp_link")
        tcp_link = next(j.child for j in joints if j.name == arm_joints[-1])
    visuals = _visuals(robot, path, package_dirs or {}) if load_meshes else {}
    return RobotModel(
        name=str(path),
        joints=joints,
        arm_joints=arm_joints,
        tcp_link=tcp_link,
        T_link_tcp=np.eye(4) if T_link_tcp is None else T_link_tcp,
        gripper=gripper,
        visuals=visuals,
    )


def _joint(j, velocity: dict[str, float], acceleration: dict[str, float], path: Path) -> Joint:
    kind = {"revolute": "revolute", "continuous": "revolute", "prismatic": "prismatic", "fixed": "fixed"}.get(j.type)
    if kind is None:
        raise RobotModelError(f"{path}: joint {j.name!r} has unsupported type {j.type!r}")
    origin = np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=np.float64)
    axis = np.array([1.0, 0.0, 0.0]) if j.axis is None else np.asarray(j.axis, dtype=np.float64)
    if kind != "fixed" and not np.linalg.norm(axis) > 0:
        raise RobotModelError(f"{path}: joint {j.name!r} has a zero axis")
    limits = None
    if kind != "fixed":
        if j.type == "continuous":
            lower, upper = -np.pi, np.pi  # documented: continuous joints are limited to one turn
        elif j.limit is None or j.limit.lower is None or j.limit.upper is None:
            raise RobotModelError(f"{path}: joint {j.name!r} has no position limits")
        else:
            lower, upper = float(j.limit.lower), float(j.limit.upper)
        file_velocity = float(j.limit.velocity) if j.limit is not None and j.limit.velocity else None
        effort = float(j.limit.effort) if j.limit is not None and j.limit.effort else None
        limits = JointLimits(
            lower=lower,
            upper=upper,
            velocity=velocity.get(j.name, file_velocity),
            acceleration=acceleration.get(j.name),
            effort=effort,
        )
    mimic = None
    if j.mimic is not None:
        mimic = (j.mimic.joint, float(j.mimic.multiplier or 1.0), float(j.mimic.offset or 0.0))
    return Joint(j.name, kind, j.parent, j.child, origin, axis, limits, mimic)


def _visuals(robot, path: Path, package_dirs: Mapping[str, str | Path]) -> dict[str, list[Visual]]:
    out: dict[str, list[Visual]] = {}
    for link in robot.links:
        for visual in link.visuals:
            mesh, source = _geometry_mesh(visual.geometry, path, package_dirs, link.name)
            if mesh is None:
                continue
            if visual.origin is not None:
                mesh.apply_transform(np.asarray(visual.origin, dtype=np.float64))
            out.setdefault(link.name, []).append(Visual(mesh, source))
    return out


def _geometry_mesh(geometry, path: Path, package_dirs, link: str) -> tuple[trimesh.Trimesh | None, str]:
    if geometry.box is not None:
        return trimesh.creation.box(extents=np.asarray(geometry.box.size, dtype=float)), "primitive:box"
    if geometry.cylinder is not None:
        c = geometry.cylinder
        return trimesh.creation.cylinder(radius=float(c.radius), height=float(c.length)), "primitive:cylinder"
    if geometry.sphere is not None:
        return trimesh.creation.icosphere(subdivisions=2, radius=float(geometry.sphere.radius)), "primitive:sphere"
    if geometry.mesh is None:
        return None, ""
    file = _resolve_mesh_path(geometry.mesh.filename, path, package_dirs, link)
    try:
        mesh = trimesh.load(str(file), force="mesh")
    except Exception as exc:
        raise RobotModelError(f"{path}: cannot read mesh {file} of link {link!r} ({exc})") from exc
    if geometry.mesh.scale is not None:
        mesh.apply_scale(np.asarray(geometry.mesh.scale, dtype=float))
    return mesh, str(file)


def _resolve_mesh_path(filename: str, path: Path, package_dirs, link: str) -> Path:
    if filename.startswith("package://"):
        package, _, rest = filename[len("package://") :].partition("/")
        if package not in package_dirs:
            raise RobotModelError(
                f"{path}: link {link!r} uses {filename}; pass package_dirs={{'{package}': FOLDER}} to resolve it"
            )
        file = Path(package_dirs[package]) / rest
    elif filename.startswith("file://"):
        file = Path(filename[len("file://") :])
    else:
        file = Path(filename) if Path(filename).is_absolute() else path.parent / filename
    if not file.is_file():
        raise FileNotFoundError(f"{path}: mesh {filename} of link {link!r} not found (looked at {file})")
    return file


__all__ = ["load_urdf"]
