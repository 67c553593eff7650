"""Real spherical harmonics up to degree 3, as 3DGS and gsplat evaluate view-dependent colour."""

from __future__ import annotations

import torch

from manisplat.compilation import constant_tensor

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


# Each basis function (gsplat's order and signs) as monomials of the unit direction: (constant, axes).
_BASIS = (
    ((C0, ()),),
    ((-C1, (1,)),), ((C1, (2,)),), ((-C1, (0,)),),
    ((C2[0], (0, 1)),), ((C2[1], (1, 2)),),
    ((2 * C2[2], (2, 2)), (-C2[2], (0, 0)), (-C2[2], (1, 1))),
    ((C2[3], (0, 2)),), ((C2[4], (0, 0)), (-C2[4], (1, 1))),
    ((3 * C3[0], (0, 0, 1)), (-C3[0], (1, 1, 1))),
    ((C3[1], (0, 1, 2)),),
    ((4 * C3[2], (1, 2, 2)), (-C3[2], (0, 0, 1)), (-C3[2], (1, 1, 1))),
    ((2 * C3[3], (2, 2, 2)), (-3 * C3[3], (0, 0, 2)), (-3 * C3[3], (1, 1, 2))),
    ((4 * C3[4], (0, 2, 2)), (-C3[4], (0, 0, 0)), (-C3[4], (0, 1, 1))),
    ((C3[5], (0, 0, 2)), (-C3[5], (1, 1, 2))),
    ((C3[6], (0, 0, 0)), (-3 * C3[6], (0, 1, 1))),
)


def _monomial_index(axes: tuple[int, ...]) -> int:
    """Position of the monomial of ``axes`` in :func:`_monomials`' layout [1, d (3), d d (9), d d d (27)]."""
    offset, flat = (0, 1, 4, 13)[len(axes)], 0
    for axis in axes:
        flat = 3 * flat + axis
    return offset + flat


def _basis_map(degree: int) -> tuple[tuple[float, ...], ...]:
    """[monomials][(degree + 1)^2] the linear map from :func:`_monomials` to the SH basis."""
    n = num_sh_bases(degree)
    M = [[0.0] * n for _ in range((1, 4, 13, 40)[degree])]
    for k, terms in enumerate(_BASIS[:n]):
        for constant, axes in terms:
            M[_monomial_index(axes)][k] += constant
    return tuple(tuple(row) for row in M)


BASIS_MAPS = tuple(_basis_map(degree) for degree in range(4))


def _monomials(d: torch.Tensor, degree: int) -> torch.Tensor:
    """[..., 4 | 13 | 40] the monomials of unit directions ``d`` [..., 3] up to ``degree`` (1..3)."""
    parts = [torch.ones_like(d[..., :1]), d]
    power = d
    for _ in range(degree - 1):
        power = (power[..., :, None] * d[..., None, :]).flatten(-2)
        parts.append(power)
    return torch.cat(parts, dim=-1)


def spherical_harmonics(degree: int, dirs: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """Colour [..., D] of SH ``coeffs`` [..., K, D] (K >= (degree+1)^2) seen along ``dirs`` [..., 3].

    ``dirs`` need not be unit (normalised with a floor, so a zero direction gives finite values).
    Only the first (degree + 1)^2 coefficients are used. No +0.5 offset here (see rasterization).
    The basis is the direction's monomials times a constant matrix: a fixed handful of kernels
    whatever the degree (it runs for every Gaussian in every training iteration).
    """
    n = num_sh_bases(degree)
    if coeffs.shape[-2] < n:
        raise ValueError(f"SH degree {degree} needs {n} coefficients per channel, got {coeffs.shape[-2]}")
    if degree == 0:
        return C0 * coeffs[..., 0, :]
    d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = _monomials(d, degree) @ constant_tensor(BASIS_MAPS[degree], d.dtype, d.device)  # [..., n]
    return (basis[..., None, :] @ coeffs[..., :n, :])[..., 0, :]
