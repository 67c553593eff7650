"""Initial Gaussians for each node: the background and objects from back-projected depth, robot
links from samples of their meshes (or the built-in primitives).

Without depth (monocular), the depth is assumed: the table is the plane ``z = table_z`` of the
base frame (the arm stands on it) out to ``radius`` from the base, everything else a backdrop
behind; an object is a billboard standing on the table, facing the camera, through the points
where its mask's lowest pixels meet the table. The camera does not move, so a background's shape
matters little to its images; an object's is refined by training.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from manisplat.reconstruct.data import EpisodeData, ReconstructionInputError
from manisplat.robot import RobotModel, link_meshes
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


def sample_spacing(depth: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor, K: torch.Tensor,
                   stride: int) -> torch.Tensor:
    """[M] m between neighbouring samples taken every ``stride`` pixels at ``rows``, ``cols`` of
    ``depth`` [H, W] (z-depth, m) by a camera of focal length ``K[0, 0]`` (pixels)."""
    return depth[rows, cols] / float(K[0, 0]) * stride


def monocular_depth(data: EpisodeData, *, table_z: float = 0.0, radius: float = 1.5,
                    backdrop: float = 1.25) -> torch.Tensor:
    """The z-depth [H, W] a monocular start assumes: where a pixel's ray meets the table plane
    ``z = table_z`` (base frame, m) within ``radius`` m of the base origin, else a backdrop
    parallel to the image at ``backdrop`` times the farthest table depth.

    Raises:
        ReconstructionInputError: the camera sees no table there (it looks up, or from below).
    """
    W, H = data.size
    rays_cam, centre, R = _pixel_rays(data, W, H)
    rays = rays_cam @ R.T  # base frame, z-depth 1
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (table_z - centre[2]) / rays[..., 2]
    hit = centre + s[..., None] * rays
    on_table = (s > 0) & np.isfinite(s) & (np.linalg.norm(hit[..., :2], axis=-1) < radius)
    if not on_table.any():
        raise ReconstructionInputError(
            f"monocular start: no pixel sees the table plane z = {table_z} m within {radius} m of the base")
    depth = np.where(on_table, s, backdrop * s[on_table].max())
    return torch.from_numpy(depth.astype(np.float32))


def billboard_depth(data: EpisodeData, mask: torch.Tensor, *, table_z: float = 0.0) -> torch.Tensor:
    """The z-depth [H, W] (0 outside ``mask`` [H, W] bool) of an object seen without depth: a
    vertical plane facing the camera through the points where the mask's lowest pixel in each
    column meets the table ``z = table_z``.

    Raises:
        ReconstructionInputError: the mask is empty or its foot does not meet the table.
    """
    W, H = data.size
    m = mask.numpy()
    cols = np.nonzero(m.any(0))[0]
    if not len(cols):
        raise ReconstructionInputError("billboard: the object mask is empty")
    rows = H - 1 - np.argmax(m[::-1, cols], axis=0)  # lowest mask pixel per column
    rays_cam, centre, R = _pixel_rays(data, W, H)
    foot_rays = rays_cam[rows, cols] @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (table_z - centre[2]) / foot_rays[:, 2]
    if not np.all(np.isfinite(s) & (s > 0)):
        raise ReconstructionInputError("billboard: the object's foot does not meet the table plane")
    foot = (centre + s[:, None] * foot_rays).mean(0)
    normal = foot - centre
    normal[2] = 0.0
    if np.linalg.norm(normal) < 1e-6:
        raise ReconstructionInputError("billboard: the camera looks straight down on the object")
    normal /= np.linalg.norm(normal)
    rays = rays_cam @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = (normal @ (foot - centre)) / (rays @ normal)
    depth = np.where(m & np.isfinite(depth) & (depth > 0), depth, 0.0)
    return torch.from_numpy(depth.astype(np.float32))


def _pixel_rays(data: EpisodeData, W: int, H: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-frame rays [H, W, 3] with z = 1 through the pixel centres, the camera centre [3] and
    rotation [3, 3] in the base frame."""
    K = data.K_opencv.double().numpy()
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    T = torch.linalg.inv(data.viewmat.double()).numpy()
    return rays, T[:3, 3], T[:3, :3]


def background_gaussians(data: EpisodeData, *, stride: int = 2, frames: list[int] | None = None,
                         sh_degree: int = 0, table_z: float = 0.0, riding: Sequence[EpisodeData] = (),
                         riding_frames: list[int] | None = None) -> GaussianSet:
    """Static Gaussians from the depth of a few frames (or :func:`monocular_depth`), robot and
    object pixels excluded.

    Frame 0 gives most points; later frames only add pixels that no earlier frame saw as static
    (the table the arm hid), so nothing is duplicated. The ``riding`` cameras' views (with depth
    and masks) add their close-ups in ``riding_frames`` (default ``frames``):
    :func:`close_up_points`.
    """
    assumed = monocular_depth(data, table_z=table_z) if data.depth is None else None
    frames = frames or sorted({0, data.n_frames // 2, data.n_frames - 1})
    T_base_cam = torch.linalg.inv(data.viewmat.double())
    seen = torch.zeros(data.rgb.shape[1:3], dtype=torch.bool)
    points, colors, spacing = [], [], []
    for i in frames:
        static = data.region(i, data.labels.static) if data.masks is not None else torch.ones_like(seen)
        if data.valid is not None:
            static &= data.valid
        new = static & ~seen
        depth = data.depth[i] if assumed is None else assumed
        p, rows, cols = backproject(depth, data.K_opencv, T_base_cam, new, stride)
        points.append(p)
        colors.append(data.image(i)[rows, cols])
        spacing.append(sample_spacing(depth, rows, cols, data.K_opencv, stride))
        seen |= static
    pts, cols_, gaps = torch.cat(points), torch.cat(colors), torch.cat(spacing)
    log.info("background: %d Gaussians from %s of frames %s", len(pts),
             "depth" if assumed is None else "the monocular table and backdrop", frames)
    for view in riding:
        p, c, g = close_up_points(view, riding_frames or frames, pts, gaps)
        keep = ~seen_through(data, frames, p) if assumed is None else torch.ones(len(p), dtype=torch.bool)
        log.info("background: %d more from camera %s's close-ups (%d in space the fixed camera saw past left out)",
                 int(keep.sum()), view.camera_name, int((~keep).sum()))
        p, c, g = p[keep], c[keep], g[keep]
        pts, cols_, gaps = torch.cat([pts, p]), torch.cat([cols_, c]), torch.cat([gaps, g])
    return GaussianSet.from_points(pts, cols_, gaps, scene_scale=_extent(pts), sh_degree=sh_degree)


def close_up_points(view: EpisodeData, frames: list[int], seeds: torch.Tensor, seed_spacing: torch.Tensor, *,
                    stride: int = 4, finer: float = 0.5) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """What a riding camera (a wrist camera) adds to the background's seeds: (points [M, 3] in the
    base frame, colours [M, 3], spacing [M] m) of its static pixels with depth in ``frames``, every
    ``stride`` pixels, that :func:`finer_points` keeps against the ``seeds`` [N, 3] (spacing
    ``seed_spacing`` [N] m).

    Why: a wrist camera a few centimetres above the table sees it in millimetres, the fixed camera
    a metre away in 5-7 mm steps; Gaussians seeded at those steps show the wrist camera a blur
    that densification does not split away within the budget (its growth cap is not what stops it).
    """
    _check_close_ups(view)
    samples = [_frame_samples(view, f, view.region(f, view.labels.static), torch.linalg.inv(view.view_at(f).double()),
                              stride) for f in frames]
    return finer_points(samples, seeds, seed_spacing, finer=finer)


def object_close_up_points(view: EpisodeData, frames: list[int], poses: np.ndarray, seeds: torch.Tensor,
                           seed_spacing: torch.Tensor, *, stride: int = 4, finer: float = 0.5, margin: float = 0.005,
                           floor: float = 0.003) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """What a riding camera adds to one object's seeds: (points [M, 3] in the object's frame,
    colours [M, 3], spacing [M] m) of its pixels with depth in ``frames``, every ``stride``
    pixels, that are not the robot's (its masks) and that the object's pose there (``poses``
    [T, 4, 4] ``T_base_obj``) puts inside the box around the ``seeds`` [N, 3] (object frame,
    z up at the start), ``margin`` m wider and above their lowest point by ``floor`` m (not the
    support it stands on); kept by :func:`finer_points` against the seeds (spacing
    ``seed_spacing`` [N] m).

    Why: the object's seeds are what the fixed camera's first frame shows, its far sides missing
    and the rest at that camera's 4-5 mm steps, where a wrist camera sees the object from a few
    centimetres: its close-ups there scored 15-20 dB against its held-out frames.
    """
    _check_close_ups(view)
    model = seeds.double().numpy()
    low, high = model.min(0) - margin, model.max(0) + margin
    low[2] = model[:, 2].min() + floor
    samples = []
    for f in frames:
        T_obj_cam = torch.from_numpy(np.linalg.inv(poses[f])) @ torch.linalg.inv(view.view_at(f).double())
        xyz, colours, gap = _frame_samples(view, f, ~view.region(f, list(view.labels.robot)), T_obj_cam, stride)
        inside = np.all((xyz >= low) & (xyz <= high), axis=1)
        samples.append((xyz[inside], colours[torch.from_numpy(inside)], gap[inside]))
    return finer_points(samples, seeds, seed_spacing, finer=finer)


def _check_close_ups(view: EpisodeData) -> None:
    """Refuse a riding camera without depth or masks: its close-ups cannot be placed or sorted."""
    if view.depth is None or view.masks is None:
        raise ValueError(f"camera {view.camera_name}: close-up seeds need its depth and masks")


def _frame_samples(view: EpisodeData, f: int, keep: torch.Tensor, T_frame_cam: torch.Tensor,
                   stride: int) -> tuple[np.ndarray, torch.Tensor, np.ndarray]:
    """Frame ``f`` of ``view`` where ``keep`` [H, W] (and the recording covers), every ``stride``
    pixels with depth: (points [K, 3] float64 in the frame ``T_frame_cam`` [4, 4] takes the camera's
    to, colours [K, 3], spacing [K] m)."""
    if view.valid is not None:
        keep = keep & view.valid
    p, rows, cols = backproject(view.depth[f], view.K_opencv, T_frame_cam, keep, stride)
    gap = sample_spacing(view.depth[f], rows, cols, view.K_opencv, stride)
    return p.double().numpy(), view.image(f)[rows, cols], gap.double().numpy()


def finer_points(samples: list[tuple[np.ndarray, torch.Tensor, np.ndarray]], seeds: torch.Tensor,
                 seed_spacing: torch.Tensor, *, finer: float = 0.5) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Of each frame's ``samples`` (points [K, 3], colours [K, 3], spacing [K] m), the points that
    show the surface at least 1 / ``finer`` times as finely as the nearest of the ``seeds``
    [N, 3] (spacing ``seed_spacing`` [N] m), or where no seed is within two of their spacings;
    the frames that see most finely (median spacing) first, a point a previous one added within
    its own spacing not added again. Returns (points [M, 3], colours [M, 3], spacing [M]) as float32."""
    seed_tree = cKDTree(seeds.double().numpy())
    seed_gap = seed_spacing.double().numpy()
    added: list[tuple[np.ndarray, torch.Tensor, np.ndarray]] = []
    for xyz, colours, gap in sorted((s for s in samples if len(s[0])), key=lambda s: float(np.median(s[2]))):
        distance, nearest = seed_tree.query(xyz)
        keep = (gap < finer * seed_gap[nearest]) | (distance > 2 * seed_gap[nearest])
        if added:
            earlier = cKDTree(np.concatenate([a[0] for a in added]))
            keep &= earlier.query(xyz)[0] > gap
        added.append((xyz[keep], colours[torch.from_numpy(keep)], gap[keep]))
    if not added:
        return torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0)
    return (torch.from_numpy(np.concatenate([a[0] for a in added])).float(), torch.cat([a[1] for a in added]),
            torch.from_numpy(np.concatenate([a[2] for a in added])).float())


def seen_through(data: EpisodeData, frames: list[int], points: torch.Tensor, margin: float = 0.01) -> torch.Tensor:
    """[N] bool: the points [N, 3] (base frame) that the fixed camera ``data`` saw past in one of
    ``frames``: its pixel there is static and its depth more than ``margin`` m beyond the point.
    Such a point is not a static surface (a riding camera's pixel at the edge of a moving part's
    drawn mask, which the fixed camera's view of the background shows to be empty space)."""
    V, K = data.viewmat.double(), data.K_opencv.double()
    cam = points.double() @ V[:3, :3].T + V[:3, 3]
    z = cam[:, 2].clamp_min(1e-6)
    u = (cam[:, 0] / z * K[0, 0] + K[0, 2]).round().long()
    v = (cam[:, 1] / z * K[1, 1] + K[1, 2]).round().long()
    W, H = data.size
    inside = (cam[:, 2] > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    u, v = u.clamp(0, W - 1), v.clamp(0, H - 1)
    through = torch.zeros(len(points), dtype=torch.bool)
    for f in frames:
        static = data.region(f, data.labels.static)[v, u]
        through |= inside & static & (data.depth[f][v, u].double() > z + margin)
    return through


def object_points(data: EpisodeData, label: int, frame: int = 0, *, stride: int = 1,
                  table_z: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """What ``frame`` shows of one object: base-frame points [N, 3] float64 from its masked depth
    (or its :func:`billboard_depth` without depth), their colours [N, 3] in [0, 1] and the pixel
    spacing at each [N] (m)."""
    if data.masks is None:
        raise ValueError("object_gaussians needs the object's mask")
    keep = data.masks[frame] == label
    depth = data.depth[frame] if data.depth is not None else billboard_depth(data, keep, table_z=table_z)
    p, rows, cols = backproject(depth, data.K_opencv, torch.linalg.inv(data.viewmat.double()), keep, stride)
    if len(p) < 10:
        raise ValueError(f"object label {label}: only {len(p)} pixels with depth in frame {frame}")
    spacing = sample_spacing(depth, rows, cols, data.K_opencv, stride)
    return p.double(), data.image(frame)[rows, cols], spacing


def object_gaussians(data: EpisodeData, label: int, frame: int = 0, *, stride: int = 1,
                     sh_degree: int = 0, table_z: float = 0.0) -> tuple[GaussianSet, torch.Tensor]:
    """Canonical Gaussians of one object from what ``frame`` shows of it
    (:func:`canonical_object_points`) and ``T_base_obj`` [4, 4] of its canonical frame."""
    points, colours, spacing, T = canonical_object_points(data, label, frame, stride=stride, table_z=table_z)
    return object_model(points, colours, spacing, sh_degree=sh_degree), T


def canonical_object_points(data: EpisodeData, label: int, frame: int = 0, *, stride: int = 1,
                            table_z: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`object_points` in the object's canonical frame, which has the base's axes and its
    origin at the points' centroid: (points [N, 3] float64, colours [N, 3], spacing [N] m,
    ``T_base_obj`` [4, 4] float64 of that frame, the object's pose at ``frame``)."""
    p, colours, spacing = object_points(data, label, frame, stride=stride, table_z=table_z)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, 3] = p.mean(0)
    return p - T[:3, 3], colours, spacing, T


def object_model(points: torch.Tensor, colours: torch.Tensor, spacing: torch.Tensor, *,
                 sh_degree: int = 0) -> GaussianSet:
    """An object's Gaussians at ``points`` [N, 3] of its frame, ``colours`` [N, 3] in [0, 1], the
    samples' ``spacing`` [N] (m)."""
    return GaussianSet.from_points(points.float(), colours, spacing, opacity=0.8, sh_degree=sh_degree)


def link_gaussians(robot: RobotModel, links: list[str], *, total: int = 20_000, seed: int = 0,
                   sh_degree: int = 0) -> dict[str, GaussianSet]:
    """Surface samples of each link's geometry (link frame), as flat discs along the surface.

    The ``total`` budget is shared in proportion to surface area; colours start mid-grey.
    """
    geometry = link_meshes(robot.visuals)
    meshes = {name: geometry[name] for name in links if name in geometry}
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
