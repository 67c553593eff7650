"""The camera extrinsic and the camera/joint time offset checked and corrected against the robot
itself: the depth of the pixels the robot covers must lie on the robot's link surfaces, placed by
forward kinematics at the frame's time.

A hand calibration is typically off by a few tenths of a degree and a few millimetres
(../shared/reference: hand-eye accuracy), and a camera's timestamps by milliseconds; both move
every object pose the reconstruction finds in the base frame. The robot is a calibration target
whose pose is known in every frame: its measured surface in the camera frame, aligned to its
model surface over many frames and arm configurations, fixes ``T_base_cam`` and, where the arm
moves, the time offset (point-to-plane ICP, Gauss-Newton on se(3) and the offset, Huber
weights; each point matched only to the link surface facing the camera, since a noisy point
behind a thin part's front would otherwise take its back face: about 1 mm of bias at the oak
preset's depth noise). Each depth point is trusted by its expected stereo error, which grows with
the square of its depth (weight ``(z_ref / z)^4``). The static background cannot help: it is seen
by one still camera, so any camera pose explains it.

The uncertainty is a bootstrap over frames (frames resampled with replacement, the converged
normal equations re-solved): the 1-sigma spread of the correction's rotation (deg), camera
centre (mm) and time offset (ms). It does not include a bias of the robot's meshes against the
real robot (on the simulator's episodes the true error after correction is about 3x the spread).
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
from manisplat.reconstruct.data import EpisodeData, joints_at

log = logging.getLogger(__name__)

#: fewer measured robot points than this over all frames: the correction is not estimated
MIN_POINTS = 2_000
#: a correction larger than this is not applied (the calibration is wrong, or the robot model is)
MAX_ROTATION_DEG, MAX_TRANSLATION_MM, MAX_TIME_OFFSET_S = 3.0, 30.0, 0.2
#: a time offset is applied when it is this large and three times its spread (s)
MIN_TIME_OFFSET_S = 0.002
#: the time offset is estimated only where the arm moves enough to tell it from the camera pose
#: (condition number of the unit-diagonal normal equations with the offset)
MAX_TIME_CONDITION = 1e8
#: the residuals before and after are compared within this distance of the model (m): the first
#: iteration's gate (later ones shrink with the residuals, and would flatter the refined pose)
COMPARE_GATE = 0.02
#: a fit that leaves more than this residual RMS (mm) does not describe the depth (stereo noise of
#: an OAK is a few mm at 1.5 m): the model or the depth is wrong, and the correction means nothing
MAX_RESIDUAL_MM = 5.0
_VELOCITY_STEP_S = 0.01  # central difference of the link poses for the surface velocity
REPLACE_AFTER_S = 0.5e-3  # the surfaces are placed anew when the offset moved this far (s)


@dataclass
class ExtrinsicCorrection:
    """What the robot's depth says about ``T_base_cam`` and the time offset.

    Attributes:
        T_before, T_after: [4, 4] float64 camera-to-base, as recorded and as refined.
        rotation_deg, translation_mm: the correction: rotation angle of ``T_before^-1 T_after`` and
            the camera centre's displacement in the base frame.
        sigma_rotation_deg, sigma_translation_mm: 1-sigma bootstrap spread of those (over frames).
        time_offset_s, sigma_time_offset_s: frame f shows the robot at joint time
            ``t[f] + offset`` beyond the offset already used (``EpisodeData.time_offset_s``); None
            when the arm did not move enough to tell.
        rms_before_mm, rms_after_mm: robust RMS point-to-plane residual before and after, both
            within :data:`COMPARE_GATE` of the model.
        points, frames: how many robot depth points from how many frames were used.
        applied: False when the extrinsic correction was not trusted (``reason`` says why).
        time_applied: whether the time offset is large and certain enough to re-pair the joints.
    """

    T_before: np.ndarray
    T_after: np.ndarray
    rotation_deg: float
    translation_mm: float
    sigma_rotation_deg: float
    sigma_translation_mm: float
    time_offset_s: float | None
    sigma_time_offset_s: float | None
    rms_before_mm: float
    rms_after_mm: float
    points: int
    frames: int
    applied: bool = True
    reason: str = ""
    time_applied: bool = False

    def to_dict(self) -> dict:
        return {"rotation_deg": self.rotation_deg, "translation_mm": self.translation_mm,
                "sigma_rotation_deg": self.sigma_rotation_deg, "sigma_translation_mm": self.sigma_translation_mm,
                "time_offset_ms": None if self.time_offset_s is None else 1e3 * self.time_offset_s,
                "sigma_time_offset_ms": None if self.sigma_time_offset_s is None else 1e3 * self.sigma_time_offset_s,
                "time_applied": self.time_applied,
                "rms_before_mm": self.rms_before_mm, "rms_after_mm": self.rms_after_mm,
                "points": self.points, "frames": self.frames, "applied": self.applied, "reason": self.reason,
                "T_correction": (np.linalg.inv(self.T_before) @ self.T_after).tolist(),
                "method": "robot depth on the URDF link surfaces (point-to-plane ICP), bootstrap over frames"}


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(rotation angle of ``T_a^-1 T_b`` in degrees, distance between their origins in mm)."""
    distance, angle = pose_error(torch.as_tensor(T_a), torch.as_tensor(T_b))
    return math.degrees(float(angle)), 1000 * float(distance)


class _Group:
    """Measured robot points of one frame and one link (camera frame), and that link's camera-facing
    model surface at the frame's time (base frame), with the surface's velocity."""

    def __init__(self, frame: int, points_cam: np.ndarray, model: np.ndarray, normals: np.ndarray,
                 velocity: np.ndarray, w_depth: np.ndarray) -> None:
        self.frame, self.p, self.w_depth = frame, points_cam, w_depth
        self.model, self.normals, self.velocity = model, normals, velocity
        self.tree = cKDTree(model)

    def residuals(self, T: np.ndarray, gate: float, shift: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Point-to-plane residuals [N] (m) at camera pose ``T`` with the model moved ``shift`` s
        along its velocity, whether each is within ``gate`` of the model [N], and their Jacobian
        [N, 7] for ``T Exp(e)`` and a further time shift ``s``: (e, s) = (v, omega, s), e in the
        camera frame, s in seconds."""
        R, t = T[:3, :3], T[:3, 3]
        pb = self.p @ R.T + t
        dist, idx = self.tree.query(pb, distance_upper_bound=gate)
        ok = np.isfinite(dist)
        idx = np.where(ok, idx, 0)
        n = self.normals[idx]
        r = np.einsum("ij,ij->i", n, pb - self.model[idx] - shift * self.velocity[idx])
        # d pb / d e = R [I | -[p]x]; n^T R [I | -[p]x] = [(R^T n)^T | (p x R^T n)^T]; d r / d s = -n.v
        nc = n @ R
        J = np.concatenate([nc, np.cross(self.p, nc), -np.einsum("ij,ij->i", n, self.velocity[idx])[:, None]], 1)
        return r, ok, J


def _normal_equations(groups: list[_Group], T: np.ndarray, gate: float, huber: float,
                      shift: float = 0.0) -> dict[int, tuple]:
    """frame -> (H [7, 7], g [7], inlier residuals [M] in m) of the Huber- and depth-weighted
    point-to-plane cost at ``T`` (models moved ``shift`` s) over that frame's groups."""
    out: dict[int, tuple] = {}
    for grp in groups:
        r, ok, J = grp.residuals(T, gate, shift)
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


@dataclass
class _Measured:
    """One frame's robot depth points matched to one link (``link`` None: to all links)."""

    frame: int
    link: str | None
    points: np.ndarray
    w_depth: np.ndarray


def _measurements(data: EpisodeData, frames: list[int], surface: dict, erode_px: int, points_per_frame: int,
                  rng: np.random.Generator) -> list[_Measured]:
    """Each mask label naming a link is matched to that link's surface; a robot label naming none
    (one label for the whole arm) to all links together."""
    by_link: dict[str | None, list[int]] = {}
    for value, link in data.labels.robot.items():
        by_link.setdefault(link if link in surface else None, []).append(value)
    share = points_per_frame / max(sum(len(v) for v in by_link.values()), 1)
    out = []
    for f in frames:
        for link, values in by_link.items():
            p = _robot_points(data, f, values, erode_px, max(int(share * len(values)), 1), rng)
            if len(p) >= 20:
                out.append(_Measured(f, link, p, p[:, 2] ** -4.0))  # 1 / sigma_z^2 up to a constant
    if out:
        z_ref = np.median(np.concatenate([m.points[:, 2] for m in out]))
        for m in out:  # relative to the median depth (dimensionless)
            m.w_depth = m.w_depth * z_ref ** 4
    return out


def _groups(data: EpisodeData, measured: list[_Measured], surface: dict, camera: np.ndarray | None,
            offset: float) -> list[_Group]:
    """The measurements with their links' surfaces placed at joint time ``t[f] + offset`` beyond
    the data's own offset (and the surface velocity there), keeping the surface that faces
    ``camera`` (base-frame position; None keeps all of it)."""
    names = list(data.robot.link_names)
    frames = sorted({m.frame for m in measured})
    t = data.t.cpu().numpy()[frames] + data.time_offset_s + offset  # joint time of what the frame shows
    h = _VELOCITY_STEP_S
    times = np.concatenate([t, t - h, t + h])
    q, gripper = joints_at(data, times)
    poses = data.robot.forward_kinematics(torch.as_tensor(q), torch.as_tensor(gripper)).double().numpy()
    now, before, after = np.split(poses, 3)
    row = {f: k for k, f in enumerate(frames)}
    groups = []
    for m in measured:
        k = row[m.frame]
        links = [m.link] if m.link is not None else list(surface)
        parts = []
        for n in links:
            i = names.index(n)
            pts, nrm = surface[n]
            placed = pts @ now[k, i, :3, :3].T + now[k, i, :3, 3]
            velocity = (pts @ (after[k, i, :3, :3] - before[k, i, :3, :3]).T + after[k, i, :3, 3] - before[k, i, :3, 3]) / (2 * h)
            parts.append((placed, nrm @ now[k, i, :3, :3].T, velocity))
        model, normals, velocity = (np.concatenate(x) for x in zip(*parts))
        front = (np.einsum("ij,ij->i", normals, model - camera) < 0 if camera is not None
                 else np.ones(len(model), dtype=bool))
        if front.sum() >= 20:
            groups.append(_Group(m.frame, m.points, model[front], normals[front], velocity[front], m.w_depth))
    return groups


def refine_extrinsic(data: EpisodeData, frames: list[int], *, max_frames: int = 40, points_per_frame: int = 1500,
                     per_link: int = 20_000, iterations: int = 20, bootstrap: int = 200, erode_px: int = 2,
                     time_offset: bool = True, depth_weighting: bool = True, camera_facing: bool = True,
                     seed: int = 0) -> ExtrinsicCorrection | None:
    """Align the robot's measured depth with its model over ``frames`` (training frames).

    ``time_offset`` also estimates the camera/joint time offset where the arm moves enough to
    tell it (:data:`MAX_TIME_CONDITION`); it is applied (``time_applied``) when at least
    :data:`MIN_TIME_OFFSET_S` and three times its bootstrap spread. ``depth_weighting`` False
    weighs every depth point the same and ``camera_facing`` False matches points to the whole link
    surface (the ablations in ``benchmarks/bench_reconstruct_degraded_ablation.py``).

    Returns None when the episode cannot say (no depth, no robot masks, fewer than
    :data:`MIN_POINTS` robot points, a degenerate geometry); otherwise the correction, with
    ``applied`` False (and the reason) when the fit leaves a residual above
    :data:`MAX_RESIDUAL_MM` (the depth or the model is wrong: the painter's one depth per triangle
    leaves several millimetres and the fit proposes degrees), is larger than
    :data:`MAX_ROTATION_DEG` / :data:`MAX_TRANSLATION_MM`, or does not lower the residual (the
    recorded camera already fits).
    """
    if data.depth is None or data.masks is None or not data.labels.robot:
        log.info("camera extrinsic: not checked (needs depth and robot masks)")
        return None
    rng = np.random.default_rng(seed)
    chosen = list(frames)[:: max(1, len(frames) // max_frames)][:max_frames]
    surface = _model_surface(data, per_link, seed)
    measured = _measurements(data, chosen, surface, erode_px, points_per_frame, rng)
    if not depth_weighting:
        for m in measured:
            m.w_depth = np.ones_like(m.w_depth)
    total = sum(len(m.points) for m in measured)
    if total < MIN_POINTS:
        log.warning("camera extrinsic: not checked (only %d robot depth points)", total)
        return None
    T0 = np.linalg.inv(data.viewmat.double().numpy())
    T, offset = T0.copy(), 0.0
    camera = T0[:3, 3] if camera_facing else None
    groups, placed_at = _groups(data, measured, surface, camera, offset), offset
    gate = COMPARE_GATE
    r = np.concatenate([s[2] for s in _normal_equations(groups, T, gate, gate).values()])
    rms_before = _robust_rms(r)
    solve_time = time_offset
    for _ in range(iterations):
        sigma = max(1.4826 * float(np.median(np.abs(r))), 2e-4)  # robust depth residual scale (m)
        gate, huber = max(5 * sigma, 0.003), 1.5 * sigma
        systems = _normal_equations(groups, T, gate, huber, offset - placed_at)
        H, g = sum(s[0] for s in systems.values()), sum(s[1] for s in systems.values())
        if solve_time and _condition(H) > MAX_TIME_CONDITION:
            solve_time = False  # the arm hardly moves: the offset cannot be told apart from the camera
        k = 7 if solve_time else 6
        if _condition(H[:k, :k]) > 1e10:
            log.warning("camera extrinsic: not checked (the robot's points do not constrain the camera; "
                        "condition number %.1e)", _condition(H[:k, :k]))
            return None
        step = -np.linalg.solve(H[:k, :k], g[:k])
        T = T @ se3_exp(torch.as_tensor(step[:6])).numpy()
        if solve_time:
            offset += float(step[6])
            if abs(offset - placed_at) > REPLACE_AFTER_S:  # the surface at the new time (within it: linear)
                groups, placed_at = _groups(data, measured, surface, camera, offset), offset
        r = np.concatenate([s[2] for s in _normal_equations(groups, T, gate, huber, offset - placed_at).values()])
        if np.linalg.norm(step[:6]) < 1e-8 and (not solve_time or abs(step[6]) < 1e-6):
            break
    systems = _normal_equations(groups, T, gate, huber, offset - placed_at)
    k = 7 if solve_time else 6
    sig_rot, sig_trans, sig_time = _bootstrap(T, list(systems.values()), k, bootstrap, rng)
    rot, trans = pose_difference(T0, T)
    # after compared with before on the same terms: the first iteration's gate
    rms_after = _robust_rms(np.concatenate([s[2] for s in _normal_equations(
        groups, T, COMPARE_GATE, COMPARE_GATE, offset - placed_at).values()]))
    result = ExtrinsicCorrection(T0, T, rot, trans, sig_rot, sig_trans, offset if solve_time else None,
                                 sig_time if solve_time else None, 1000 * rms_before, 1000 * rms_after,
                                 total, len(chosen))
    if solve_time:
        result.time_applied = (abs(offset) >= max(MIN_TIME_OFFSET_S, 3 * sig_time) and abs(offset) <= MAX_TIME_OFFSET_S)
    if 1000 * rms_after > MAX_RESIDUAL_MM:
        result.applied, result.time_applied = False, False
        result.reason = (f"the robot's depth does not fit its model (residual RMS {1000 * rms_before:.2f} -> "
                         f"{1000 * rms_after:.2f} mm, at most {MAX_RESIDUAL_MM} mm expected): the extrinsic cannot "
                         "be checked and the episode's calibration is kept; check the depth scale and the robot "
                         "description")
        result.T_after = T0.copy()
        log.warning("camera extrinsic: %s", result.reason)
    elif rot > MAX_ROTATION_DEG or trans > MAX_TRANSLATION_MM:
        result.applied, result.time_applied = False, False
        result.reason = (f"the correction ({rot:.2f} deg, {trans:.1f} mm) is larger than {MAX_ROTATION_DEG} deg / "
                         f"{MAX_TRANSLATION_MM} mm: recalibrate (manisplat-calibrate) or check the robot description")
        result.T_after = T0.copy()
        log.warning("camera extrinsic: %s", result.reason)
    elif rms_after >= rms_before:
        result.applied, result.time_applied = False, False
        result.reason = (f"the robot's depth fits the recorded camera (residual RMS {1000 * rms_before:.2f} mm; the "
                         f"fit's {rot:.3f} deg, {trans:.2f} mm does not lower it)")
        result.T_after = T0.copy()
    if solve_time:
        verdict = ("applied" if result.time_applied else "not applied: " + (
            "the extrinsic was not" if not result.applied else
            f"beyond {MAX_TIME_OFFSET_S} s" if abs(offset) > MAX_TIME_OFFSET_S else "too small to be sure"))
        timing = f"; camera/joint time offset {1e3 * offset:+.1f} +- {1e3 * sig_time:.1f} ms ({verdict})"
    else:
        timing = ""
    if result.applied or rms_after < rms_before:  # a correction, applied or refused above with a warning
        log.info("camera extrinsic: correction %.3f +- %.3f deg, %.2f +- %.2f mm from %d robot depth points in %d "
                 "frames (residual RMS %.2f -> %.2f mm)%s%s", rot, sig_rot, trans, sig_trans, total, len(chosen),
                 result.rms_before_mm, result.rms_after_mm, "" if result.applied else "; NOT applied", timing)
    else:
        log.info("camera extrinsic: kept: %s; %d robot depth points in %d frames%s", result.reason, total,
                 len(chosen), timing)
    return result


def _condition(H: np.ndarray) -> float:
    """Condition number of ``H`` scaled to unit diagonal (the parameters' units do not count)."""
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    return float(np.linalg.cond(H / d[:, None] / d[None, :]))


def _robust_rms(r: np.ndarray) -> float:
    """RMS of the residuals within 3 robust sigmas (m)."""
    if not len(r):
        return float("nan")
    sigma = 1.4826 * np.median(np.abs(r))
    inl = r[np.abs(r) <= 3 * sigma] if sigma > 0 else r
    return float(np.sqrt(np.mean(inl ** 2)))


def _bootstrap(T: np.ndarray, systems: list, k: int, n: int, rng: np.random.Generator) -> tuple[float, float, float]:
    """1-sigma spread (deg, mm, s) of the one-step solutions of the first ``k`` parameters with
    the frames' normal equations resampled with replacement (the time's NaN when ``k`` is 6)."""
    Hs = np.stack([s[0][:k, :k] for s in systems])
    gs = np.stack([s[1][:k] for s in systems])
    angles, shifts, times = [], [], []
    for _ in range(n):
        pick = rng.integers(0, len(systems), len(systems))
        try:
            step = -np.linalg.solve(Hs[pick].sum(0), gs[pick].sum(0))
        except np.linalg.LinAlgError:
            continue
        a, d = pose_difference(T, T @ se3_exp(torch.as_tensor(step[:6])).numpy())
        angles.append(a)
        shifts.append(d)
        times.append(step[6] if k == 7 else math.nan)
    if not angles:
        return math.nan, math.nan, math.nan
    # the spread of a 3-vector's length about 0: RMS of the bootstrap displacements
    rms = lambda x: float(np.sqrt(np.mean(np.square(x))))  # noqa: E731
    return rms(angles), rms(shifts), rms(times)


__all__ = ["ExtrinsicCorrection", "MAX_ROTATION_DEG", "MAX_TIME_OFFSET_S", "MAX_TRANSLATION_MM", "pose_difference",
           "refine_extrinsic"]
