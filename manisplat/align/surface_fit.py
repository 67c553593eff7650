"""An object's surface model against the depth seen in frames: nearest-point matching, the capped
mean distance (misfit), and the one shift of position that aligns the two (translation-only ICP).

The pseudo ground truth uses it where the object rests after a release and where it slips in the
hand (:mod:`manisplat.align.pseudo_gt`); the keypoint tracker, to let a tracked pose override the
gripper's prior only when the depth agrees (:class:`manisplat.align.tracking.DepthEvidence`).
"""

from __future__ import annotations

import numpy as np


class SurfaceModel:
    """Model points [M, 3] (object frame, m) in a KD-tree. A point of a frame's surface farther
    than ``cap`` (m) from the model counts ``cap`` in the misfit and is left out of a fit's step:
    surface the model lacks or stray depth cannot pull it further."""

    def __init__(self, points: np.ndarray, cap: float = 0.01) -> None:
        from scipy.spatial import cKDTree

        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self.cap = float(cap)
        self._tree = cKDTree(self.points)

    def match(self, surfaces: list[np.ndarray], poses: list[np.ndarray],
              shift: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """The ``surfaces`` [M_k, 3] (base frame) matched to their nearest model point with the
        model at ``poses`` [4, 4] moved by ``shift`` [3] (m, base frame): the residuals [K, 3]
        (base frame) of the points within the cap, and the mean distance of all points (m), each
        capped."""
        shift = np.zeros(3) if shift is None else shift
        residuals, distances = [], []
        for X, T in zip(surfaces, poses):
            local = (X - T[:3, 3] - shift) @ T[:3, :3]  # the surface in the object frame
            d, idx = self._tree.query(local, distance_upper_bound=self.cap)
            near = np.isfinite(d)
            residuals.append(X[near] - (self.points[idx[near]] @ T[:3, :3].T + T[:3, 3] + shift))
            distances.append(np.minimum(d, self.cap))
        return np.concatenate(residuals), float(np.concatenate(distances).mean())

    def misfit(self, surfaces: list[np.ndarray], poses: list[np.ndarray]) -> float:
        """Mean distance (m, each capped) of the surfaces [M_k, 3] (base frame) to the model at
        the frames' ``poses`` [4, 4]."""
        return self.match(surfaces, poses)[1]

    def fit_shift(self, surfaces: list[np.ndarray], poses: list[np.ndarray], *,
                  iterations: int = 30) -> tuple[np.ndarray, float, float]:
        """One shift of position (m, base frame) [3] that aligns the model at ``poses`` [4, 4]
        with the ``surfaces`` [M_k, 3] (base frame) of several frames. Returns (shift, misfit
        before, misfit after) (m)."""
        shift = np.zeros(3)
        residuals, before = self.match(surfaces, poses, shift)
        after = before
        for _ in range(iterations):
            if len(residuals) == 0:
                break
            step = residuals.mean(0)
            shift = shift + step
            residuals, after = self.match(surfaces, poses, shift)
            if np.linalg.norm(step) < 1e-5:
                break
        return shift, before, after
