"""Real spherical harmonics up to degree 3, as 3DGS and gsplat evaluate view-dependent colour."""

from __future__ import annotations

import torch

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """Number of coefficients per channel for ``degree`` (0..3): (degree + 1)^2."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    return (degree + 1) ** 2


def spherical_harmonics(degree: int, dirs: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """Colour [..., D] of SH ``coeffs`` [..., K, D] (K >= (degree+1)^2) seen along ``dirs`` [..., 3].

    ``dirs`` need not be unit (normalised with a floor, so a zero direction gives finite values).
    Only the first (degree + 1)^2 coefficients are used. No +0.5 offset here (see rasterization).
    """
    n = num_sh_bases(degree)
    if coeffs.shape[-2] < n:
        raise ValueError(f"SH degree {degree} needs {n} coefficients per channel, got {coeffs.shape[-2]}")
    out = C0 * coeffs[..., 0, :]
    if degree == 0:
        return out
    d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    x, y, z = (d[..., i : i + 1] for i in range(3))
    out = out - C1 * y * coeffs[..., 1, :] + C1 * z * coeffs[..., 2, :] - C1 * x * coeffs[..., 3, :]
    if degree == 1:
        return out
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    out = (
        out
        + C2[0] * xy * coeffs[..., 4, :]
        + C2[1] * yz * coeffs[..., 5, :]
        + C2[2] * (2 * zz - xx - yy) * coeffs[..., 6, :]
        + C2[3] * xz * coeffs[..., 7, :]
        + C2[4] * (xx - yy) * coeffs[..., 8, :]
    )
    if degree == 2:
        return out
    return (
        out
        + C3[0] * y * (3 * xx - yy) * coeffs[..., 9, :]
        + C3[1] * xy * z * coeffs[..., 10, :]
        + C3[2] * y * (4 * zz - xx - yy) * coeffs[..., 11, :]
        + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * coeffs[..., 12, :]
        + C3[4] * x * (4 * zz - xx - yy) * coeffs[..., 13, :]
        + C3[5] * z * (xx - yy) * coeffs[..., 14, :]
        + C3[6] * x * (xx - 3 * yy) * coeffs[..., 15, :]
    )
