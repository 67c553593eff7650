"""Initial Gaussians for each node: the background and objects from back-projected depth, robot
links from samples of their meshes (or the built-in primitives)."""

from __future__ import annotations

import logging

import numpy as np
import torch
import trimesh

from manisplat.reconstruct.data import EpisodeData
from manisplat.robot import RobotModel
from manisplat.scene import GaussianSet

log = logging.getLogger(__name__)


def backproject(depth: torch.Tensor, K: torch.Tensor, T_base_cam: torch.Tensor, keep: torch.Tensor,
                stride: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Base-frame points [M, 3] of pixels where ``keep`` [H, W] and depth > 0, every ``stride`` pixels.

    Uses the OpenCV ``K`` (integer pixel centres). Returns (points, pixel rows, pixel cols).
    """
    H, W = depth.shape
    rows, cols = torch.meshgrid(torch.arange(0, H, stride), torch.arange(0, W, stride), indexing="ij")
    rows, cols = rows.reshape(-1), cols.reshape(-1)
    z = depth[rows, cols].double()
    sel = keep[rows, cols] & (z > 0)
    rows, cols, z = rows[sel], cols[sel], z[sel]
    K = K.double()
    x = (cols.double() - K[0, 2]) / K[0, 0] * z
    y = (rows.double() - K[1, 2]) / K[1, 1] * z
    cam = torch.stack([x, y, z], -1)
    T = T_base_cam.double()
    return (cam @ T[:3, :3].T + T[:3, 3]).float(), rows, cols


def background_gaussians(data: EpisodeData, *, stride: int = 2, frames: list[int] | None = None,
                         sh_degree: int = 0) -> GaussianSet:
    """Static Gaussians from the depth of a few frames, robot and object pixels excluded.

    Frame 0 gives most points; later frames only add pixels that no earlier frame saw as static
    (the table the arm hid), so nothing is duplicated.
    """
    if data.depth is None:
        raise ValueError("background_gaussians needs depth; use monocular_background_gaussians")
    frames = frames or sorted({0, data.n_frames // 2, data.n_frames - 1})
    T_base_cam = torch.linalg.inv(data.viewmat.double())
    seen = torch.zeros(data.rgb.shape[1:3], dtype=torch.bool)
    points, colors, spacing = [], [], []
    for i in frames:
        static = data.region(i, data.labels.static) if data.masks is not None else torch.ones_like(seen)
        new = static & ~seen
        p, rows, cols = backproject(data.depth[i], data.K_opencv, T_base_cam, new, stride)
        points.append(p)
        colors.append(data.image(i)[rows, cols])
        spacing.append(data.depth[i][rows, cols] / float(data.K_opencv[0, 0]) * stride)
        seen |= static
    pts = torch.cat(points)
    log.info("background: %d Gaussians from depth of frames %s", len(pts), frames)
    return GaussianSet.from_points(pts, torch.cat(colors), torch.cat(spacing), scene_scale=_extent(pts),
                                   sh_degree=sh_degree)


def object_gaussians(data: EpisodeData, label: int, frame: int = 0, *, stride: int = 1,
                     sh_degree: int = 0) -> tuple[GaussianSet, torch.Tensor]:
    """Canonical Gaussians of one object from its masked depth in ``frame``.

    The canonical frame has the base's axes and its origin at the points' centroid. Returns the
    set and ``T_base_obj`` [4, 4] of that frame (the object's pose at ``frame``).
    """
    if data.depth is None or data.masks is None:
        raise ValueError("object_gaussians needs depth and masks")
    keep = data.masks[frame] == label
    p, rows, cols = backproject(data.depth[frame], data.K_opencv, torch.linalg.inv(data.viewmat.double()), keep, stride)
    if len(p) < 10:
        raise ValueError(f"object label {label}: only {len(p)} pixels with depth in frame {frame}")
    center = p.double().mean(0)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, 3] = center
    spacing = data.depth[frame][rows, cols] / float(data.K_opencv[0, 0]) * stride
    gs = GaussianSet.from_points((p.double() - center).float(), data.image(frame)[rows, cols], spacing, opacity=0.8,
                                 sh_degree=sh_degree)
    return gs, T


def link_gaussians(robot: RobotModel, links: list[str], *, total: int = 20_000, seed: int = 0,
                   sh_degree: int = 0) -> dict[str, GaussianSet]:
    """Surface samples of each link's geometry (link frame), as flat discs along the surface.

    The ``total`` budget is shared in proportion to surface area; colours start mid-grey.
    """
    meshes = {name: trimesh.util.concatenate([v.mesh for v in robot.visuals[name]]) for name in links
              if robot.visuals.get(name)}
    missing = [name for name in links if name not in meshes]
    if missing:
        raise ValueError(f"{robot.name}: no geometry for links {missing}; load the URDF with its meshes")
    areas = {name: float(m.area) for name, m in meshes.items()}
    total_area = sum(areas.values())
    out = {}
    trimesh_log = logging.getLogger("trimesh")
    level = trimesh_log.level
    trimesh_log.setLevel(logging.ERROR)  # even sampling returning fewer points is expected (handled below)
    try:
        samples = {name: _surface_samples(mesh, max(64, int(total * areas[name] / total_area)), seed)
                   for name, mesh in meshes.items()}
    finally:
        trimesh_log.setLevel(level)
    for name, mesh in meshes.items():
        points, faces = samples[name]
        pts = torch.as_tensor(np.asarray(points), dtype=torch.float32)
        normals = torch.as_tensor(np.asarray(mesh.face_normals[faces]), dtype=torch.float32)
        spacing = float(np.sqrt(areas[name] / max(len(pts), 1)))
        out[name] = GaussianSet.from_points(pts, torch.full((len(pts), 3), 0.5), spacing, normals=normals, opacity=0.8,
                                            sh_degree=sh_degree)
    log.info("robot: %s Gaussians on links %s", sum(len(g) for g in out.values()), list(out))
    return out


def _surface_samples(mesh: trimesh.Trimesh, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """About ``n`` evenly spread surface points and their faces; plain area sampling when even
    sampling (Poisson-disc rejection) returns fewer than half, as on thin parts."""
    points, faces = trimesh.sample.sample_surface_even(mesh, n, seed=seed)
    if len(points) < n // 2:
        points, faces = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return points, faces


def _extent(points: torch.Tensor) -> float:
    """Scene scale (m): the radius of the points' bounding box, as 3DGS uses for learning rates."""
    return float((points.max(0).values - points.min(0).values).norm() / 2)
