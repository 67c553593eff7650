"""The camera extrinsic checked and corrected against the robot itself: the depth of the pixels
the robot covers must lie on the robot's link surfaces, placed by forward kinematics.

A hand calibration is typically off by a few tenths of a degree and a few millimetres
(../shared/reference: hand-eye accuracy); that error moves every object pose the reconstruction
finds in the base frame. The robot is a calibration target whose pose is known in every frame:
its measured surface in the camera frame, aligned to its model surface in the base frame over
many frames and arm configurations, fixes ``T_base_cam`` (point-to-plane ICP, Gauss-Newton on
se(3), Huber weights; each point matched only to the link surface that faces the camera, since a
noisy point behind a thin part's front would otherwise take its back face). Each depth point is trusted by its expected stereo error, which grows
with the square of its depth (weight ``(z_ref / z)^4``). The static background cannot help: it
is seen by one still camera, so any camera pose explains it.

The uncertainty is a bootstrap over frames (frames resampled with replacement, the converged
normal equations re-solved): the 1-sigma spread of the correction's rotation (deg) and camera
centre (mm). It does not include a bias of the robot's meshes against the real robot.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from manisplat.geometry import pose_error, se3_exp
from manisplat.reconstruct.data import EpisodeData

log = logging.getLogger(__name__)

#: fewer measured robot points than this over all frames: the correction is not estimated
MIN_POINTS = 2_000
#: a correction larger than this is not applied (the calibration is wrong, or the robot model is)
MAX_ROTATION_DEG, MAX_TRANSLATION_MM = 3.0, 30.0


@dataclass
class ExtrinsicCorrection:
    """What the robot's depth says about ``T_base_cam``.

    Attributes:
        T_before, T_after: [4, 4] float64 camera-to-base, as recorded and as refined.
        rotation_deg, translation_mm: the correction: rotation angle of ``T_before^-1 T_after`` and
            the camera centre's displacement in the base frame.
        sigma_rotation_deg, sigma_translation_mm: 1-sigma bootstrap spread of those (over frames).
        rms_before_mm, rms_after_mm: robust RMS point-to-plane residual before and after.
        points, frames: how many robot depth points from how many frames were used.
        applied: False when the correction was not trusted (``reason`` says why).
    """

    T_before: np.ndarray
    T_after: np.ndarray
    rotation_deg: float
    translation_mm: float
    sigma_rotation_deg: float
    sigma_translation_mm: float
    rms_before_mm: float
    rms_after_mm: float
    points: int
    frames: int
    applied: bool = True
    reason: str = ""

    def to_dict(self) -> dict:
        return {"rotation_deg": self.rotation_deg, "translation_mm": self.translation_mm,
                "sigma_rotation_deg": self.sigma_rotation_deg, "sigma_translation_mm": self.sigma_translation_mm,
                "rms_before_mm": self.rms_before_mm, "rms_after_mm": self.rms_after_mm,
                "points": self.points, "frames": self.frames, "applied": self.applied, "reason": self.reason,
                "T_correction": (np.linalg.inv(self.T_before) @ self.T_after).tolist(),
                "method": "robot depth on the URDF link surfaces (point-to-plane ICP), bootstrap over frames"}


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(rotation angle of ``T_a^-1 T_b`` in degrees, distance between their origins in mm)."""
    distance, angle = pose_error(torch.as_tensor(T_a), torch.as_tensor(T_b))
    return math.degrees(float(angle)), 1000 * float(distance)


class _Group:
    """Measured robot points of one frame and one link (camera frame), and that link's model
    surface placed by forward kinematics (base frame)."""

    def __init__(self, frame: int, points_cam: np.ndarray, model_points: np.ndarray, model_normals: np.ndarray) -> None:
        self.frame = frame
        self.p = points_cam
        self.w_depth = points_cam[:, 2] ** -4.0  # 1 / sigma_z^2 up to a constant (sigma_z ~ z^2)
        self.model, self.normals = model_points, model_normals
        self.tree = cKDTree(model_points)

    def residuals(self, T: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Point-to-plane residuals [N] (m) at camera pose ``T``, whether each is within ``gate`` of
        the model [N], and their Jacobian [N, 6] for ``T Exp(e)``, e = (v, omega) in the camera frame."""
        R, t = T[:3, :3], T[:3, 3]
        pb = self.p @ R.T + t
        dist, idx = self.tree.query(pb, distance_upper_bound=gate)
        ok = np.isfinite(dist)
        idx = np.where(ok, idx, 0)
        n = self.normals[idx]
        r = np.einsum("ij,ij->i", n, pb - self.model[idx])
        # d pb / d e = R [I | -[p]x]; n^T R [I | -[p]x] = [(R^T n)^T | (p x R^T n)^T]
        nc = n @ R
        return r, ok, np.concatenate([nc, np.cross(self.p, nc)], axis=1)


def _normal_equations(groups: list[_Group], T: np.ndarray, gate: float, huber: float) -> dict[int, tuple]:
    """frame -> (H [6, 6], g [6], inlier residuals [M] in m) of the Huber- and depth-weighted
    point-to-plane cost at ``T`` over that frame's groups."""
    out: dict[int, tuple] = {}
    for grp in groups:
        r, ok, J = grp.residuals(T, gate)
        a = np.abs(r)
        w = np.where(a <= huber, 1.0, huber / np.maximum(a, 1e-12)) * grp.w_depth * ok
        Jw = J * w[:, None]
        H, g, kept = Jw.T @ J, Jw.T @ r, r[ok]
        if grp.frame in out:
            H0, g0, r0 = out[grp.frame]
            H, g, kept = H0 + H, g0 + g, np.concatenate([r0, kept])
        out[grp.frame] = (H, g, kept)
    return out


def _model_surface(data: EpisodeData, per_link: int, seed: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """link -> (points [M, 3], normals [M, 3]) sampled on its meshes, in the link frame."""
    out = {}
    for name, visuals in data.robot.visuals.items():
        if not visuals:
            continue
        mesh = trimesh.util.concatenate([v.mesh for v in visuals])
        points, faces = trimesh.sample.sample_surface(mesh, per_link, seed=seed)
        out[name] = (np.asarray(points, dtype=np.float64), np.asarray(mesh.face_normals[faces], dtype=np.float64))
    return out


def _robot_points(data: EpisodeData, frame: int, values: list[int], erode_px: int, max_points: int,
                  rng: np.random.Generator) -> np.ndarray:
    """[N, 3] camera-frame points of the frame's pixels labelled ``values`` with valid depth,
    ``erode_px`` away from the mask's edge (stereo depth is unreliable there), at most ``max_points``."""
    region = np.isin(data.masks[frame].numpy(), values).astype(np.uint8)
    if erode_px:
        region = cv2.erode(region, np.ones((2 * erode_px + 1, 2 * erode_px + 1), np.uint8))
    z = data.depth[frame].numpy().astype(np.float64)
    rows, cols = np.nonzero((region > 0) & (z > 0))
    if len(rows) > max_points:
        keep = rng.choice(len(rows), max_points, replace=False)
        rows, cols = rows[keep], cols[keep]
    K = data.K_opencv.numpy()
    zz = z[rows, cols]
    return np.stack([(cols - K[0, 2]) / K[0, 0] * zz, (rows - K[1, 2]) / K[1, 1] * zz, zz], axis=1)


def _groups(data: EpisodeData, frames: list[int], surface: dict, erode_px: int, points_per_frame: int,
            rng: np.random.Generator) -> list[_Group]:
    """The frame-link groups: each mask label naming a link is matched to that link's surface; a
    robot label naming none (one label for the whole arm) to all links together. Only the surface
    facing the camera is kept: a noisy depth point behind a thin part's front would otherwise
    match its back face, whose opposite normal biases the fit (about 1 mm at the oak preset's
    depth noise)."""
    names = list(data.robot.link_names)
    camera = np.linalg.inv(data.viewmat.double().numpy())[:3, 3]
    by_link: dict[str | None, list[int]] = {}
    for value, link in data.labels.robot.items():
        by_link.setdefault(link if link in surface else None, []).append(value)
    share = points_per_frame / max(sum(len(v) for v in by_link.values()), 1)
    groups = []
    for f in frames:
        poses = data.link_poses[f].double().numpy()
        placed = {n: (surface[n][0] @ poses[names.index(n), :3, :3].T + poses[names.index(n), :3, 3],
                      surface[n][1] @ poses[names.index(n), :3, :3].T) for n in surface}
        for link, values in by_link.items():
            p = _robot_points(data, f, values, erode_px, max(int(share * len(values)), 1), rng)
            if len(p) < 20:
                continue
            links = [link] if link is not None else list(placed)
            points = np.concatenate([placed[n][0] for n in links])
            normals = np.concatenate([placed[n][1] for n in links])
            front = np.einsum("ij,ij->i", normals, points - camera) < 0
            if front.sum() < 20:
                continue
            groups.append(_Group(f, p, points[front], normals[front]))
    return groups


def refine_extrinsic(data: EpisodeData, frames: list[int], *, max_frames: int = 40, points_per_frame: int = 1500,
                     per_link: int = 20_000, iterations: int = 20, bootstrap: int = 200, erode_px: int = 2,
                     seed: int = 0) -> ExtrinsicCorrection | None:
    """Align the robot's measured depth with its model over ``frames`` (training frames).

    Returns None when the episode cannot say (no depth, no robot masks, fewer than
    :data:`MIN_POINTS` robot points); otherwise the correction, with ``applied`` False (and the
    reason) when it is larger than :data:`MAX_ROTATION_DEG` / :data:`MAX_TRANSLATION_MM`.
    """
    if data.depth is None or data.masks is None or not data.labels.robot:
        log.info("camera extrinsic: not checked (needs depth and robot masks)")
        return None
    rng = np.random.default_rng(seed)
    chosen = list(frames)[:: max(1, len(frames) // max_frames)][:max_frames]
    groups = _groups(data, chosen, _model_surface(data, per_link, seed), erode_px, points_per_frame, rng)
    total = sum(len(g.p) for g in groups)
    if total < MIN_POINTS:
        log.warning("camera extrinsic: not checked (only %d robot depth points)", total)
        return None
    z_ref = np.median(np.concatenate([g.p[:, 2] for g in groups]))
    for g in groups:  # depth weights relative to the median depth (dimensionless)
        g.w_depth *= z_ref ** 4
    T0 = np.linalg.inv(data.viewmat.double().numpy())
    T = T0.copy()
    gate = 0.02
    r = np.concatenate([s[2] for s in _normal_equations(groups, T, gate, gate).values()])
    rms_before = _robust_rms(r)
    for _ in range(iterations):
        sigma = max(1.4826 * float(np.median(np.abs(r))), 2e-4)  # robust depth residual scale (m)
        gate, huber = max(5 * sigma, 0.003), 1.5 * sigma
        systems = _normal_equations(groups, T, gate, huber)
        H, g = sum(s[0] for s in systems.values()), sum(s[1] for s in systems.values())
        if np.linalg.cond(H) > 1e12:
            log.warning("camera extrinsic: not checked (the robot's points do not constrain all six degrees of "
                        "freedom; condition number %.1e)", np.linalg.cond(H))
            return None
        step = -np.linalg.solve(H, g)
        T = T @ se3_exp(torch.as_tensor(step)).numpy()
        r = np.concatenate([s[2] for s in _normal_equations(groups, T, gate, huber).values()])
        if np.linalg.norm(step) < 1e-8:
            break
    systems = _normal_equations(groups, T, gate, huber)
    rms_after = _robust_rms(r)
    sig_rot, sig_trans = _bootstrap(T, list(systems.values()), bootstrap, rng)
    rot, trans = pose_difference(T0, T)
    frames_used = len(chosen)
    result = ExtrinsicCorrection(T0, T, rot, trans, sig_rot, sig_trans, 1000 * rms_before, 1000 * rms_after,
                                 total, frames_used)
    if rot > MAX_ROTATION_DEG or trans > MAX_TRANSLATION_MM:
        result.applied = False
        result.reason = (f"the correction ({rot:.2f} deg, {trans:.1f} mm) is larger than {MAX_ROTATION_DEG} deg / "
                         f"{MAX_TRANSLATION_MM} mm: recalibrate (manisplat-calibrate) or check the robot description")
        result.T_after = T0.copy()
        log.warning("camera extrinsic: %s", result.reason)
    log.info("camera extrinsic: correction %.3f +- %.3f deg, %.2f +- %.2f mm from %d robot depth points in %d frames "
             "(residual RMS %.2f -> %.2f mm)%s", rot, sig_rot, trans, sig_trans, total, frames_used,
             result.rms_before_mm, result.rms_after_mm, "" if result.applied else "; NOT applied")
    return result


def _robust_rms(r: np.ndarray) -> float:
    """RMS of the residuals within 3 robust sigmas (m)."""
    if not len(r):
        return float("nan")
    sigma = 1.4826 * np.median(np.abs(r))
    inl = r[np.abs(r) <= 3 * sigma] if sigma > 0 else r
    return float(np.sqrt(np.mean(inl ** 2)))


def _bootstrap(T: np.ndarray, systems: list, n: int, rng: np.random.Generator) -> tuple[float, float]:
    """1-sigma spread (deg, mm) of the one-step solutions with the frames' normal equations
    resampled with replacement."""
    Hs = np.stack([s[0] for s in systems])
    gs = np.stack([s[1] for s in systems])
    angles, shifts = [], []
    for _ in range(n):
        pick = rng.integers(0, len(systems), len(systems))
        H, g = Hs[pick].sum(0), gs[pick].sum(0)
        try:
            step = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            continue
        Tb = T @ se3_exp(torch.as_tensor(step)).numpy()
        a, d = pose_difference(T, Tb)
        angles.append(a)
        shifts.append(d)
    if not angles:
        return float("nan"), float("nan")
    # the spread of a 3-vector's length about 0: RMS of the bootstrap displacements
    return float(np.sqrt(np.mean(np.square(angles)))), float(np.sqrt(np.mean(np.square(shifts))))


__all__ = ["ExtrinsicCorrection", "MAX_ROTATION_DEG", "MAX_TRANSLATION_MM", "pose_difference", "refine_extrinsic"]
