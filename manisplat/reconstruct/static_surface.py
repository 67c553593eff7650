"""The scene's static surface as a fixed camera measures it: a triangle mesh in the world frame
from one frame's depth, without the robot and the objects. A camera riding on an arm (a wrist
camera) sees its own fingers from one place only, which cannot pin its extrinsic down; the table,
the mats and the fixed objects it sweeps over from many poses can, once the fixed camera that
measured them has been checked against the robot (:mod:`manisplat.reconstruct.rig_check`)."""

from __future__ import annotations

import numpy as np
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

from manisplat.reconstruct.data import EpisodeData

#: a triangle between neighbouring depth pixels seen this close to edge-on (the cosine between its
#: normal and the viewing ray) spans a depth edge: the surface behind it is not seen
MIN_VIEW_COSINE = 0.1


def static_surface(data: EpisodeData, frame: int, *, stride: int = 2) -> trimesh.Trimesh:
    """The static surface [world frame, m] a fixed camera's depth shows in ``frame``: every
    ``stride``-th pixel with depth that no robot or object label covers, joined into triangles
    with its grid neighbours where no depth edge lies between them (a triangle seen edge-on,
    :data:`MIN_VIEW_COSINE`); ray-cast with Embree.

    Raises:
        ValueError: the camera rides on a link, or the view has no depth or masks, or no static
            surface is left.
    """
    if data.riding or data.depth is None or data.masks is None:
        raise ValueError(f"camera {data.camera_name}: the static surface needs a fixed camera with depth and masks")
    z = data.depth[frame].cpu().numpy().astype(np.float64)[::stride, ::stride]
    moving = np.array(data.labels.moving, dtype=np.int64)
    static = (z > 0) & ~np.isin(data.masks[frame].cpu().numpy()[::stride, ::stride], moving)
    H, W = z.shape
    rows, cols = np.mgrid[0:H, 0:W] * stride
    K = data.K_opencv.cpu().numpy()
    points = np.stack([(cols - K[0, 2]) / K[0, 0] * z, (rows - K[1, 2]) / K[1, 1] * z, z], axis=-1).reshape(-1, 3)
    T_world_cam = np.linalg.inv(data.viewmat.double().cpu().numpy())
    vertices = points @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    index = np.arange(H * W).reshape(H, W)
    faces = []
    for a, b, c in (((0, 0), (1, 0), (0, 1)), ((1, 0), (1, 1), (0, 1))):  # two triangles per grid cell
        ia, ib, ic = (index[r:H - 1 + r, s:W - 1 + s].ravel() for r, s in (a, b, c))
        ok = static.ravel()[ia] & static.ravel()[ib] & static.ravel()[ic]
        pa, pb, pc = points[ia], points[ib], points[ic]
        normal = np.cross(pb - pa, pc - pa)
        ray = pa + pb + pc
        cosine = np.abs(np.einsum("ij,ij->i", normal, ray)) / np.maximum(
            np.linalg.norm(normal, axis=1) * np.linalg.norm(ray, axis=1), 1e-12)
        ok &= cosine >= MIN_VIEW_COSINE
        faces.append(np.stack([ia[ok], ic[ok], ib[ok]], axis=1))
    faces = np.concatenate(faces)
    if not len(faces):
        raise ValueError(f"camera {data.camera_name}, frame {frame}: no static surface (every pixel robot, object "
                         "or without depth)")
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.remove_unreferenced_vertices()
    mesh.ray = RayMeshIntersector(mesh)
    return mesh


def world_region(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Quadrant [N] int (0-3) of world points [N, 3] about ``centre`` [3] in x and y: the static
    surface's parts, left out in turn when the fit's sensitivity to one part is estimated."""
    return (points[:, 0] > centre[0]).astype(np.int64) + 2 * (points[:, 1] > centre[1])


__all__ = ["MIN_VIEW_COSINE", "static_surface", "world_region"]
