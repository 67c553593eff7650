"""Collision geometry of a robot's links: one convex hull per link, as coal shapes.

Augmentation's scene (:mod:`manisplat.augment.collision`) and the replay's arm-against-arm check
(:mod:`manisplat.drivers.piper.clearance`) both collide links as the convex hull of their geometry
(the built-in PiPER's primitives, or a URDF's meshes). Lengths in metres, in each link's frame.
"""

from __future__ import annotations

import coal
import numpy as np
import trimesh

from manisplat.robot.model import RobotModel

MAX_HULL_VERTICES = 200  # keeps GJK cheap: larger hulls are rebuilt from a subsample of their vertices


def convex(points: np.ndarray) -> coal.ConvexBase:
    """The coal convex hull of ``points`` (N, 3) m."""
    v = coal.StdVec_Vec3s()
    for p in np.asarray(points, np.float64):
        v.append(p)
    return coal.Convex.convexHull(v, False, None)


def link_hulls(robot: RobotModel, description: str | None = None) -> dict[str, trimesh.Trimesh]:
    """Link name -> the convex hull of its geometry (link frame, m), for every link that has some.

    A model loaded without meshes has them read from ``description`` (its URDF) when given.
    ValueError when no link has geometry.
    """
    visuals = robot.visuals
    if not any(visuals.values()) and description:
        from manisplat.robot import load_robot
        visuals = load_robot(description, load_meshes=True).visuals
    hulls = {}
    for link, vis in visuals.items():
        meshes = [v.mesh for v in vis if v.mesh is not None and len(v.mesh.vertices)]
        if not meshes:
            continue
        hull = trimesh.util.concatenate(meshes).convex_hull
        if len(hull.vertices) > MAX_HULL_VERTICES:
            idx = np.random.default_rng(0).choice(len(hull.vertices), MAX_HULL_VERTICES, replace=False)
            hull = trimesh.PointCloud(hull.vertices[idx]).convex_hull
        hulls[link] = hull
    if not hulls:
        raise ValueError(f"{robot.name}: no link geometry for collision checking")
    return hulls
