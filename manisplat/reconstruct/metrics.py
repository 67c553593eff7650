"""Evaluation: image quality per region and object pose error against ground truth.

PSNR and SSIM over the held-out frames, on the full image and over the pixels of a region's
ground-truth mask (robot, object). Pose error follows the issue's definition: our canonical object
frame and the ground-truth object frame differ by one constant transform X, fitted by least
squares over all frames (T_gt(t) ~ T_ours(t) X); then the mean translation error (cm) and
geodesic rotation error (deg) of T_ours(t) X against T_gt(t).
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
