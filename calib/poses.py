"""Small float64 numpy helpers for rigid transforms (the solver's inner loops stay in numpy;
angle and log maps go through :mod:`manisplat.geometry`, which is stable near 0 and pi)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch

from manisplat.geometry import rotation_angle, so3_log


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) float64 transform from a rotation (3, 3) and a translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms [..., 4, 4] (uses R^T)."""
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ T[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def rodrigues(w: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of the rotation vector ``w`` (3,), radians (exact at 0)."""
    R, _ = cv2.Rodrigues(np.asarray(w, dtype=np.float64).reshape(3, 1))
    return R


def log_rotations(R: np.ndarray) -> np.ndarray:
    """Rotation vectors [..., 3] of rotations [..., 3, 3] (radians; stable near 0 and pi)."""
    return so3_log(torch.as_tensor(np.asarray(R, dtype=np.float64))).numpy()


def rotation_deg(R: np.ndarray) -> np.ndarray:
    """Geodesic angles [...] in degrees of rotations [..., 3, 3]."""
    return np.degrees(rotation_angle(torch.as_tensor(np.asarray(R, dtype=np.float64))).numpy())


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(rotation deg, translation mm) between two transforms (4, 4)."""
    dR = np.asarray(T_a)[:3, :3].T @ np.asarray(T_b)[:3, :3]
    return float(rotation_deg(dR)), float(1000.0 * np.linalg.norm(np.asarray(T_a)[:3, 3] - np.asarray(T_b)[:3, 3]))


def project_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) to a 3x3 matrix (SVD, reflection-safe)."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


def mean_transform(Ts: np.ndarray) -> np.ndarray:
    """Chordal mean of transforms (n, 4, 4): projected mean rotation, mean translation."""
    return make_T(project_rotation(np.mean(Ts[:, :3, :3], axis=0)), np.mean(Ts[:, :3, 3], axis=0))


def is_rigid(T: np.ndarray, tol: float = 1e-6) -> bool:
    """True for a finite 4x4 rigid transform."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        return False
    R = T[:3, :3]
    return (np.abs(R.T @ R - np.eye(3)).max() < tol and abs(np.linalg.det(R) - 1) < tol
            and np.abs(T[3] - [0, 0, 0, 1]).max() < tol)


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two 3-vectors, degrees (atan2, exact near 0)."""
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(np.dot(a, b))))
