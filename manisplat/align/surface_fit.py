"""An object's surface model against the depth seen in frames: nearest-point matching, the capped
mean distance (misfit), and the one shift of position that aligns the two (translation-only ICP),
and where the model was seen from (:class:`ModelViews`): a frame that sees the object from
elsewhere shows surface the model lacks.

The shift's fit pairs a seen point with its nearest model point only where their surfaces face
the same way (normals within :data:`NORMAL_AGREEMENT_DEG`), and weighs the distance along the
model's normal fully, along its surface by :data:`TANGENT_WEIGHT` (point-to-plane ICP, after Chen
& Medioni, with the normal test of Rusinkiewicz & Levoy's compatibility rejection). Matched to
the nearest point alone, a seen side the model lacks (a face turned towards the camera, the rim
the first view lost at its silhouette) pulls the model sideways to its edge: on four scenes of the
oak viewpoint set, fitted from the object's true pose after its release, 2.4-13.6 mm, against
1.9-4.0 mm this way.

The pseudo ground truth uses it where the object rests after a release and where it slips in the
hand (:mod:`manisplat.align.pseudo_gt`); the keypoint tracker, to let a tracked pose override the
gripper's prior only when the depth agrees (:class:`manisplat.align.tracking.DepthEvidence`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from manisplat.geometry.normals import point_normals

MAX_VIEW_CHANGE_DEG = 50.0  # farther from every view the model was seen from, a frame is not fitted (ModelViews)
NORMAL_AGREEMENT_DEG = 30.0  # a seen point and its nearest model point pair up when their normals agree this well
TANGENT_WEIGHT = 0.1  # the share of the distance along the surface in the shift's fit (1: point-to-point)
MODEL_NORMAL_NEIGHBOURS = 10  # points whose plane gives a model point's normal
SURFACE_NORMAL_NEIGHBOURS = 20  # ... a seen point's (depth is noisier than the model, made of it)


class SurfaceModel:
    """Model points [M, 3] (object frame, m) in a KD-tree. A point of a frame's surface farther
    than ``cap`` (m) from the model counts ``cap`` in the misfit and is left out of a fit's step:
    surface the model lacks or stray depth cannot pull it further."""

    def __init__(self, points: np.ndarray, cap: float = 0.01) -> None:
        from scipy.spatial import cKDTree

        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self.cap = float(cap)
        self._tree = cKDTree(self.points)

    @cached_property
    def normals(self) -> np.ndarray:
        """Unit normals [M, 3] of the model points (sign arbitrary;
        :func:`~manisplat.geometry.normals.point_normals`), made when :meth:`fit_shift` first needs
        them: the tracker's depth check uses the misfit only."""
        return point_normals(self.points, MODEL_NORMAL_NEIGHBOURS, self._tree)

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
        with the ``surfaces`` [M_k, 3] (base frame) of several frames (module docstring). Returns
        (shift, misfit before, misfit after) (m): the mean distance the fit minimises (along the
        normal, and :data:`TANGENT_WEIGHT` of it along the surface), a point without a partner of
        its orientation within the cap counting the cap."""
        surface_normals = [point_normals(X, SURFACE_NORMAL_NEIGHBOURS) for X in surfaces]
        shift = np.zeros(3)
        normal_eq, rhs, before = self._shift_system(surfaces, surface_normals, poses, shift)
        after = before
        for _ in range(iterations):
            if not normal_eq.any():
                break
            step = np.linalg.solve(normal_eq, rhs)
            shift = shift + step
            normal_eq, rhs, after = self._shift_system(surfaces, surface_normals, poses, shift)
            if np.linalg.norm(step) < 1e-5:
                break
        return shift, before, after

    def _shift_system(self, surfaces: list[np.ndarray], surface_normals: list[np.ndarray], poses: list[np.ndarray],
                      shift: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """The normal equations [3, 3], [3] of one step of :meth:`fit_shift` from ``shift``, and its misfit (m)."""
        normal_eq, rhs, distances = np.zeros((3, 3)), np.zeros(3), []
        agree = np.cos(np.radians(NORMAL_AGREEMENT_DEG))
        w = TANGENT_WEIGHT
        for X, N, T in zip(surfaces, surface_normals, poses):
            local = (X - T[:3, 3] - shift) @ T[:3, :3]
            d, idx = self._tree.query(local, distance_upper_bound=self.cap)
            near = np.flatnonzero(np.isfinite(d))
            n = self.normals[idx[near]] @ T[:3, :3].T
            facing = np.abs(np.einsum("ij,ij->i", n, N[near])) >= agree
            paired, n = near[facing], n[facing]
            r = X[paired] - (self.points[idx[paired]] @ T[:3, :3].T + T[:3, 3] + shift)
            along = np.einsum("ij,ij->i", n, r)
            normal_eq += n.T @ n + w * len(r) * np.eye(3)
            rhs += n.T @ along + w * r.sum(0)
            blended = np.sqrt((along ** 2 + w * (r ** 2).sum(1)) / (1 + w))
            distances += [np.minimum(blended, self.cap), np.full(len(X) - len(r), self.cap)]
        spread = np.concatenate(distances) if distances else np.zeros(0)
        return normal_eq, rhs, float(spread.mean()) if len(spread) else self.cap



@dataclass(frozen=True)
class ModelViews:
    """Where an object's model was seen from: the ``camera`` centre [3] (base frame, m) and the
    unit directions [K, 3] (object frame) from the object to it in the frames the model was made
    of. A frame that sees the object from more than :data:`MAX_VIEW_CHANGE_DEG` away from all of
    them sees surface the model lacks (the side the object turned towards the camera as it was
    carried across the image, the rim the first view lost at its silhouette), so much that even
    the fit that pairs only surfaces facing the same way (:meth:`SurfaceModel.fit_shift`) is pulled
    off. 50 deg: on the oak viewpoint set (benchmarks/_viewpoints.py) it is where the 90th
    percentile of the start-anchored error is lowest of 35, 50 and no limit (0.343 cm against 0.350
    and more). On the shared and test-set episodes (views 14-39 deg from the model's while held,
    median) it leaves out only the frames of one turned box (55 deg by the end)."""

    camera: np.ndarray
    directions: np.ndarray

    @classmethod
    def of(cls, camera: np.ndarray, model_poses: list[np.ndarray]) -> ModelViews:
        """The views of a model made from frames with the object at ``model_poses`` [4, 4] (base
        frame), seen by a fixed camera at ``camera`` [3]."""
        camera = np.asarray(camera, dtype=np.float64)
        return cls(camera, np.stack([_direction(camera, T) for T in model_poses]))

    def sees(self, T_base_obj: np.ndarray) -> bool:
        """Whether the camera sees the object at ``T_base_obj`` [4, 4] from within the limit of a
        view the model was made from."""
        cosine = float(np.max(self.directions @ _direction(self.camera, T_base_obj)))
        return cosine >= np.cos(np.radians(MAX_VIEW_CHANGE_DEG))


def _direction(camera: np.ndarray, T_base_obj: np.ndarray) -> np.ndarray:
    """The unit direction [3] (object frame) from the object at ``T_base_obj`` to ``camera``."""
    T = np.asarray(T_base_obj, dtype=np.float64)
    d = T[:3, :3].T @ (camera - T[:3, 3])
    return d / max(float(np.linalg.norm(d)), 1e-12)
