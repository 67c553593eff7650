"""The twin's Gaussians in the form viser draws them: centres, 3x3 covariances, colours, opacities."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from manisplat.geometry.rotation import quat_to_matrix
from manisplat.scene.gaussians import GaussianSet


@dataclass(frozen=True)
class SplatArrays:
    """One node's Gaussians in its own frame: ``centers`` [N, 3] m, ``covariances`` [N, 3, 3] m^2,
    ``rgbs`` [N, 3] in [0, 1] (the view-independent colour), ``opacities`` [N, 1] in [0, 1]; float32."""

    centers: np.ndarray
    covariances: np.ndarray
    rgbs: np.ndarray
    opacities: np.ndarray

    def __len__(self) -> int:
        return len(self.centers)


@torch.no_grad()
def splat_arrays(gaussians: GaussianSet) -> SplatArrays:
    """The activated parameters of ``gaussians`` as viser's ``add_gaussian_splats`` takes them:
    covariance ``R diag(s^2) R^T``; colour the degree-0 band (viser draws no higher bands)."""
    means, quats, scales, opacities, colors = gaussians.activated()
    rotations = quat_to_matrix(quats.double())
    covariances = rotations @ torch.diag_embed(scales.double() ** 2) @ rotations.transpose(1, 2)
    return SplatArrays(centers=means.float().cpu().numpy(), covariances=covariances.float().cpu().numpy(),
                       rgbs=colors.clamp(0.0, 1.0).float().cpu().numpy(),
                       opacities=opacities.float().cpu().numpy().reshape(-1, 1))
