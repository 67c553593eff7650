"""What a released object stands on: the height of the support under its footprint, read from
the depth of frames in which that spot is free (no robot or object pixel covers it).

A released object comes to rest on a support (the table, a mat, another object). The rigid
grasp carries it there with whatever it sagged or slipped in the hand and sets it down that much
too high or too low (1-4 mm on the viewpoint set of ``benchmarks/_viewpoints.py``, where the
simulated box slides in the pads while carried). The spot's depth before the object arrives says
how high the support is; the object's start, standing on its own support, says how its lowest
points sit on one (the same offset, whatever bias the model or the depth has, cancels).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from scipy.spatial import ConvexHull, Delaunay
from scipy.stats import trim_mean

from manisplat.align.tracking import visible_surface

#: the footprint is shrunk towards its centre by this factor before the support is read: the
#: spot's edge shows the object's own side (once it is there) and depth mixed across the edge
FOOTPRINT_SHRINK = 0.7
#: fewer support points than this (over all frames) and the support is not measured
MIN_SUPPORT_POINTS = 30
#: the lowest model points (this percentile of their height) are what stands on the support
LOW_PERCENTILE = 2.0
#: the support is looked for this far (m) below the object's lowest model points: a model made
#: from one view can lack the object's lower part (a can seen from above: 7 cm)
SUPPORT_DEPTH = 0.3
#: the share of the support's heights left out at each end of their distribution
TRIM = 0.2


def footprint(model_points: np.ndarray, T_base_obj: np.ndarray) -> tuple[np.ndarray, float]:
    """The object's footprint at ``T_base_obj`` [4, 4]: the convex hull [K, 2] (base x, y, m) of
    its model points [M, 3] (object frame) seen from above, and the height (m) of its lowest
    points (:data:`LOW_PERCENTILE`)."""
    points = model_points @ T_base_obj[:3, :3].T + T_base_obj[:3, 3]
    xy = points[:, :2]
    return xy[ConvexHull(xy).vertices], float(np.percentile(points[:, 2], LOW_PERCENTILE))


def support_height(hull_xy: np.ndarray, z_low: float, views: Iterable[tuple[np.ndarray, np.ndarray]],
                   K: np.ndarray, T_base_cam: np.ndarray) -> float | None:
    """The height (m, base frame; trimmed mean, :data:`TRIM`) of the depth points under a footprint: ``hull_xy`` [K, 2]
    (base x, y) shrunk by :data:`FOOTPRINT_SHRINK`, looked for from height ``z_low`` down to
    :data:`SUPPORT_DEPTH` below it (the image box the footprint covers at those heights).

    Args:
        views: (depth [H, W] m with 0 invalid, free [H, W] bool: pixels no robot or object covers)
            of the frames to read it in.
        K: [3, 3] OpenCV intrinsics; T_base_cam: [4, 4] the camera's pose (base frame).

    Returns None with fewer than :data:`MIN_SUPPORT_POINTS` points under the footprint.
    """
    centre = hull_xy.mean(0)
    inner = centre + FOOTPRINT_SHRINK * (hull_xy - centre)
    inside = Delaunay(inner)
    corners = np.concatenate([np.concatenate([inner, np.full((len(inner), 1), z)], 1)
                              for z in (z_low, z_low - SUPPORT_DEPTH)])
    T_cam_base = np.linalg.inv(T_base_cam)
    cam = corners @ T_cam_base[:3, :3].T + T_cam_base[:3, 3]
    if (cam[:, 2] <= 0).any():
        return None  # the spot is behind the camera
    pixels = (cam[:, :2] / cam[:, 2:]) * np.diag(K)[:2] + K[:2, 2]
    (u0, v0), (u1, v1) = np.floor(pixels.min(0)).astype(int), np.ceil(pixels.max(0)).astype(int)
    heights = []
    for depth, free in views:
        region = np.zeros(depth.shape, bool)
        region[max(v0, 0):max(v1 + 1, 0), max(u0, 0):max(u1 + 1, 0)] = True
        points = visible_surface(region & free, depth, K, T_base_cam)
        heights.append(points[inside.find_simplex(points[:, :2]) >= 0, 2])
    heights = np.concatenate(heights) if heights else np.zeros(0)
    # a trimmed mean, not the median: stereo depth comes in steps of a fraction of a pixel of
    # disparity (7 mm at 1 m for an OAK at 320 x 240), and the median of such values sticks to a step
    return float(trim_mean(heights, TRIM)) if len(heights) >= MIN_SUPPORT_POINTS else None
