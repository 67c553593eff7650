"""Where things can stand: a height map of the scene's support surfaces, measured from the
recording's depth, and the check that a placed object rests on one flat surface.

The reconstructed background is a good picture but a poor ruler: on the shared pick-and-place
its rendered depth scatters by 8 mm (10th-90th percentile) over a flat plate, twice the plate's
4 mm step. The recording's depth frames measure the surfaces directly, so the map is their
per-pixel median over the training frames (background pixels only: robot and objects masked
out), back-projected to the base frame and binned into cells of ``cell`` metres, each cell's
median height kept. Cells never seen are NaN.

An object set down across a step rests on the higher surface; it stays only if its centre is
well inside that surface's edge. On the shared pick-and-place, boxes let go within 1 cm of the
4 mm plate's rim ended 5-10 deg tilted and 1-2 cm away, while boxes overhanging the rim with their
centre 2 cm inside it stayed. :meth:`SupportMap.edge_drop` measures how far the surface falls
away from the highest one under a footprint within a margin of its centre; augmentation
discards placements where it falls by more than :data:`MAX_STEP`.

A stereo camera's depth scatters by millimetres at a metre, and the median over frames does not
remove what is the same in every frame. A map whose cells scatter more than :data:`NOISY_CELL`
about their neighbours is therefore smoothed by a median over :data:`SMOOTH_CELLS` x
:data:`SMOOTH_CELLS` cells, which keeps steps; a map of exact depth is left as it is.

A stereo camera's depth also comes in steps: its disparity in 1/8 pixel, so about 7 mm at 1.07 m
for the oak preset's 320x240 camera. Seen from above, a flat table becomes terraces one step
apart, each edge as high as the plate whose rim tips a box: no smoothing tells them apart. The
map keeps its ``resolution``, the height one depth step makes where its background is seen
(:func:`depth_step`), and a step smaller than :data:`RESOLVED_STEPS` of them is not taken for an
edge (:meth:`SupportMap.smallest_edge`). Measured ad hoc from a camera 1.1 m to the side of the
workspace (the oak preset of shared/tools/degrade): of 376 spots exact depth judges flat, 220 were
taken for edges, none with both changes; of its 43 edges, 35 are then too low to be seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CELL = 0.005  # m
MAX_STEP = 0.0025  # m: a larger height difference under an object is a step it would tip over
REACH = 1.0  # m: the map covers base-frame x, y within this (a PiPER reaches 0.63 m)
MIN_KNOWN = 0.5  # fraction of the footprint's cells that must have been seen to judge it
EDGE_MARGIN = 0.015  # m: the centre of a set-down object must be this far inside its support's edge
NOISY_CELL = 0.0005  # m: a map whose cells scatter more than this about their neighbours' median is smoothed
SMOOTH_CELLS = 5  # the smoothing median's window, in cells a side
RESOLVED_STEPS = 1.5  # a height difference under this many of the depth's steps may be one of its steps


@dataclass(frozen=True)
class SupportMap:
    """Heights [Ny, Nx] float32 (m, base frame z; NaN where never seen) of cells ``cell`` m wide,
    cell (0, 0) centred at ``origin`` (x, y) m; ``resolution`` (m): the height one step of the
    measured depth makes (0: continuous depth)."""

    heights: np.ndarray
    origin: tuple[float, float]
    cell: float
    resolution: float = 0.0

    def smallest_edge(self, max_step: float = MAX_STEP) -> float:
        """The smallest drop (m) taken for an edge: ``max_step``, or more where the depth's own
        steps are larger (:data:`RESOLVED_STEPS` of them)."""
        return max(max_step, RESOLVED_STEPS * self.resolution)

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """Heights [N] (NaN outside the map or unseen) under base-frame points ``xy`` [N, 2]."""
        idx = np.round((np.asarray(xy, np.float64) - np.asarray(self.origin)) / self.cell).astype(np.int64)
        ny, nx = self.heights.shape
        inside = (idx[:, 0] >= 0) & (idx[:, 0] < nx) & (idx[:, 1] >= 0) & (idx[:, 1] < ny)
        out = np.full(len(idx), np.nan)
        out[inside] = self.heights[idx[inside, 1], idx[inside, 0]]
        return out

    def _cells_under(self, xy: np.ndarray) -> np.ndarray:
        """Heights of the distinct cells [K] under base-frame points ``xy`` [N, 2] (NaN unseen)."""
        idx = np.unique(np.round((np.asarray(xy) - np.asarray(self.origin)) / self.cell).astype(np.int64), axis=0)
        return self.height_at(idx * self.cell + np.asarray(self.origin))

    def edge_drop(self, footprint_xy: np.ndarray, margin: float = EDGE_MARGIN) -> float | None:
        """How far (m) the surface falls below the highest one under a footprint (base-frame points
        [N, 2]; 95th percentile of its cells) within ``margin`` of the footprint's centre (the
        middle of its extent; the margin at most half its smaller side): 0 where the object's
        centre is well inside the surface it rests on, the step's height where it would rest on
        an edge. None where less than :data:`MIN_KNOWN` of the footprint or of the disc was seen."""
        footprint_xy = np.asarray(footprint_xy, np.float64)
        under = self._cells_under(footprint_xy)
        known = under[np.isfinite(under)]
        if len(under) == 0 or len(known) < MIN_KNOWN * len(under):
            return None
        top = float(np.percentile(known, 95))
        low, high = footprint_xy.min(0), footprint_xy.max(0)
        radius = min(margin, 0.5 * float((high - low).min()))
        centre = (low + high) / 2
        steps = np.arange(-radius, radius + 1e-12, self.cell / 2)
        disc = np.stack(np.meshgrid(steps, steps), -1).reshape(-1, 2)
        disc = centre + disc[np.hypot(disc[:, 0], disc[:, 1]) <= radius + 1e-12]
        near = self._cells_under(disc)
        near_known = near[np.isfinite(near)]
        if len(near_known) < MIN_KNOWN * len(near):
            return None
        return max(0.0, top - float(np.percentile(near_known, 5)))


def support_map(depth: np.ndarray, background: np.ndarray, K: np.ndarray, T_base_cam: np.ndarray, *,
                cell: float | None = None, reach: float = REACH) -> SupportMap | None:
    """The height map (module docstring) from depth frames [N, H, W] (m, 0 invalid) and their
    background masks [N, H, W] bool, seen with OpenCV intrinsics ``K`` [3, 3] and camera-to-base
    ``T_base_cam`` [4, 4], over base-frame x, y within ``reach`` m of the base; ``cell`` (m)
    defaults to the module docstring's. None when no frame has a valid background pixel there."""
    stack = np.where(np.asarray(background) & (np.asarray(depth) > 0), depth, np.nan).astype(np.float32)
    seen = np.isfinite(stack).any(0)
    if not seen.any():
        return None
    z = np.full(seen.shape, np.nan, np.float32)
    z[seen] = np.nanmedian(stack[:, seen], axis=0)
    ys, xs = np.nonzero(seen)
    zs = z[ys, xs].astype(np.float64)
    cam = np.stack([(xs - K[0, 2]) / K[0, 0] * zs, (ys - K[1, 2]) / K[1, 1] * zs, zs], -1)
    points = cam @ np.asarray(T_base_cam)[:3, :3].T + np.asarray(T_base_cam)[:3, 3]
    points = points[(np.abs(points[:, :2]) <= reach).all(1)]
    if not len(points):
        return None
    if cell is None:
        cell = max(CELL, 1.5 * float(np.median(zs)) / float(min(K[0, 0], K[1, 1])))
    rays = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones(len(xs))], -1)
    rise = np.abs(rays @ np.asarray(T_base_cam)[2, :3])  # base-frame height per metre of z-depth
    resolution = float(np.median(depth_step(np.asarray(depth), np.asarray(background)) * zs ** 2 * rise))
    origin = points[:, :2].min(0)
    idx = np.round((points[:, :2] - origin) / cell).astype(np.int64)
    nx, ny = idx.max(0) + 1
    flat = idx[:, 1] * nx + idx[:, 0]
    order = np.argsort(flat, kind="stable")
    flat, heights_sorted = flat[order], points[order, 2]
    cells, starts = np.unique(flat, return_index=True)
    heights = np.full(nx * ny, np.nan, np.float32)
    heights[cells] = [np.median(chunk) for chunk in np.split(heights_sorted, starts[1:])]
    heights = heights.reshape(ny, nx)
    if cell_scatter(heights) > NOISY_CELL:
        heights = np.where(np.isfinite(heights), nan_median_filter(heights, SMOOTH_CELLS), np.nan).astype(np.float32)
    return SupportMap(heights, (float(origin[0]), float(origin[1])), cell, resolution)


def depth_step(depth: np.ndarray, background: np.ndarray) -> float:
    """The depth's step as ``q`` in ``step = q z^2`` (1/m; a stereo camera's disparity steps make
    depth steps growing with its square): the median gap between the distinct depth values the
    background pixels take (depth [N, H, W] m, background [N, H, W] bool), each gap over its depth
    squared, gaps over 2 % of the depth left out (nothing measured between). About 0 for depth
    that takes every value (continuous, or stored in 0.1 mm); 0 without two distinct values."""
    values = np.unique(np.round(depth[background & (depth > 0)].astype(np.float64), 5))
    gaps, lower = np.diff(values), values[:-1]
    near = gaps < 0.02 * lower
    if not near.any():
        return 0.0
    return float(np.median(gaps[near] / lower[near] ** 2))


def nan_median_filter(heights: np.ndarray, size: int) -> np.ndarray:
    """Each cell's median [Ny, Nx] over the ``size`` x ``size`` cells around it, unseen (NaN)
    cells left out (NaN where all are)."""
    half = size // 2
    padded = np.pad(heights.astype(np.float64), half, constant_values=np.nan)
    windows = np.lib.stride_tricks.sliding_window_view(padded, (size, size)).reshape(*heights.shape, -1)
    out = np.full(heights.shape, np.nan)
    seen = np.isfinite(windows).any(-1)
    out[seen] = np.nanmedian(windows[seen], axis=-1)
    return out


def cell_scatter(heights: np.ndarray) -> float:
    """Robust spread (m, 1.4826 x the median absolute deviation) of the seen cells about the
    median of their 3 x 3 neighbourhood: the map's noise, steps aside. 0 with no cell seen."""
    residual = (heights - nan_median_filter(heights, 3))[np.isfinite(heights)]
    return float(1.4826 * np.median(np.abs(residual))) if len(residual) else 0.0
