"""Surface normals of point sets (numpy, float64): of a model's points for the tracker's fits, of
an object's Gaussians for its shading."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from scipy.spatial import cKDTree


def point_normals(points: np.ndarray, neighbours: int, tree: cKDTree | None = None) -> np.ndarray:
    """Unit normals [M, 3] (sign arbitrary) of the points [M, 3]: the direction of least spread of
    each point's ``neighbours`` nearest (zero where there are fewer than 3 points); ``tree``: a
    cKDTree of ``points`` already built."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) < 3:
        return np.zeros_like(points)
    _, idx = (tree or cKDTree(points)).query(points, k=min(neighbours, len(points)))
    patch = points[idx] - points[idx].mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", patch, patch))
    return vectors[:, :, 0]


def outward_normals(points: np.ndarray, neighbours: int) -> np.ndarray:
    """Unit normals [M, 3] of the points [M, 3] (:func:`point_normals`) turned away from their
    centroid: a convex object's outward normals."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = point_normals(points, neighbours)
    inward = np.einsum("ni,ni->n", normals, points - points.mean(axis=0)) < 0
    normals[inward] *= -1
    return normals
