"""Evaluation: image quality per region and object pose error against ground truth.

PSNR and SSIM over the held-out frames, on the full image and over the pixels of a region's
ground-truth mask (robot, object). Object pose error, two definitions (both: mean translation
error in cm and geodesic rotation error in deg of ``T_ours(t) X`` against ``T_gt(t)``, where our
canonical object frame and the ground truth's differ by one constant transform ``X``):

* **fitted** (:func:`pose_errors`, the paper's): ``X`` fitted by least squares over all frames.
  It flatters: a static object scores zero by construction and a constant error is absorbed.
* **start-anchored** (:func:`start_anchored_errors`): ``X`` fixed by the frames before the object
  first moves (where its pose is known best), errors over the frames after it has left its start
  (carried and placed: what augmentation moves), per phase, the worst frame, and the last frame
  (where the demonstration leaves it). A drift or a wrong placement shows in full.
"""

from __future__ import annotations

import math

import kornia
import numpy as np
import torch

from manisplat.geometry import make_transform, orthonormalize, rotation_error


def psnr(pred: torch.Tensor, target: torch.Tensor, region: torch.Tensor | None = None) -> float:
    """PSNR (dB) of images [H, W, 3] in [0, 1], over ``region`` [H, W] pixels when given."""
    err = ((pred.clamp(0, 1) - target) ** 2).mean(-1)
    if region is not None:
        if not bool(region.any()):
            return math.nan
        err = err[region]
    return float(-10 * torch.log10(err.mean().clamp_min(1e-12)))


def ssim(pred: torch.Tensor, target: torch.Tensor, region: torch.Tensor | None = None) -> float:
    """Mean SSIM (11 x 11 Gaussian window) of images [H, W, 3], over ``region`` pixels when given."""
    ssim_map = kornia.metrics.ssim(pred.clamp(0, 1).permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], 11)
    ssim_map = ssim_map[0].mean(0)
    if region is not None:
        if not bool(region.any()):
            return math.nan
        return float(ssim_map[region].mean())
    return float(ssim_map.mean())


def fit_constant_offset(ours: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """X [4, 4] minimising sum_t |ours(t) X - gt(t)|^2 (chordal rotation mean, then translation)."""
    rel = np.linalg.inv(ours) @ gt  # [T, 4, 4]: each frame's own offset
    R = orthonormalize(torch.as_tensor(rel[:, :3, :3].mean(0))).numpy()
    # translation: gt_t = R_o X_t + t_o  =>  X_t = mean(R_o^T (gt_t - t_o))
    t = np.mean(np.einsum("nji,nj->ni", ours[:, :3, :3], gt[:, :3, 3] - ours[:, :3, 3]), axis=0)
    return make_transform(torch.as_tensor(R), torch.as_tensor(t)).numpy()


def pose_errors(ours: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """{"et_cm", "er_deg"}: mean errors over frames after the constant offset (see module docstring)."""
    X = fit_constant_offset(ours, gt)
    aligned = ours @ X
    et = np.linalg.norm(aligned[:, :3, 3] - gt[:, :3, 3], axis=1)
    er = rotation_error(torch.as_tensor(aligned[:, :3, :3]), torch.as_tensor(gt[:, :3, :3])).numpy()
    return {"et_cm": float(et.mean() * 100), "er_deg": float(np.degrees(er).mean())}


MOVED_M, MOVED_DEG = 0.005, 2.0  # the object has left its start: 5 mm or 2 deg from its first pose


def _errors(aligned: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame translation (cm) and rotation (deg) errors [T] of aligned poses."""
    et = np.linalg.norm(aligned[:, :3, 3] - gt[:, :3, 3], axis=1) * 100
    er = np.degrees(rotation_error(torch.as_tensor(aligned[:, :3, :3]), torch.as_tensor(gt[:, :3, :3])).numpy())
    return et, er


def start_anchored_errors(ours: np.ndarray, gt: np.ndarray,
                          phases: list[tuple[str, int, int]] | None = None) -> dict | None:
    """Start-anchored pose error (module docstring) of ``ours`` [T, 4, 4] against ``gt``.

    Args:
        phases: (name, first frame, end frame exclusive) per phase, for the per-phase means.

    Returns {"moved_frames", "et_cm", "er_deg" (means over the moved frames), "et_cm_max",
    "er_deg_max", "final": {"et_cm", "er_deg"}, "phases": {name: {"et_cm", "er_deg"}}} (phases
    over all their frames), or None when the object never leaves its start.
    """
    gt = np.asarray(gt, np.float64)
    start_dt = np.linalg.norm(gt[:, :3, 3] - gt[0, :3, 3], axis=1)
    start_dr = np.degrees(rotation_error(torch.as_tensor(gt[:1, :3, :3]).expand(len(gt), 3, 3),
                                         torch.as_tensor(gt[:, :3, :3])).numpy())
    moved = (start_dt > MOVED_M) | (start_dr > MOVED_DEG)
    if not moved.any():
        return None
    first = int(np.argmax(moved))
    X = fit_constant_offset(ours[:max(first, 1)], gt[:max(first, 1)])
    et, er = _errors(np.asarray(ours, np.float64) @ X, gt)
    after = np.arange(len(gt)) >= first
    result = {"moved_frames": int(after.sum()), "et_cm": float(et[after].mean()), "er_deg": float(er[after].mean()),
              "et_cm_max": float(et[after].max()), "er_deg_max": float(er[after].max()),
              "final": {"et_cm": float(et[-1]), "er_deg": float(er[-1])}}
    if phases:
        result["phases"] = {name: {"et_cm": float(et[a:b].mean()), "er_deg": float(er[a:b].mean())}
                            for name, a, b in phases if b > a}
    return result
