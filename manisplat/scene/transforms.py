"""Placing Gaussians: a rigid transform moves means and rotates orientations."""

from __future__ import annotations

import torch

from manisplat.geometry import matrix_to_quat, quat_left_multiplier


def transform_gaussians(T: torch.Tensor, means: torch.Tensor, quats: torch.Tensor,
                        q_T: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Means [N, 3] and quaternions [N, 4] (w, x, y, z) moved by the rigid transform ``T`` [4, 4].

    Differentiable in ``T`` (object poses, camera refinement) and in the Gaussians. Covariances
    follow because a Gaussian's rotation is composed with ``T``'s: R_world = R_T @ R_local.
    ``q_T`` [4], ``T``'s rotation as a quaternion, may be given when already known.
    """
    R, t = T[:3, :3], T[:3, 3]
    q = matrix_to_quat(R.to(torch.float64)).to(quats.dtype) if q_T is None else q_T.to(quats.dtype)
    return means @ R.transpose(0, 1).to(means.dtype) + t.to(means.dtype), quats @ quat_left_multiplier(q)
