"""Rigid transforms as 4x4 homogeneous matrices: build, invert, compose, apply, exp/log, errors.

Convention (docs/episode-format.md): ``T_a_b`` maps coordinates in frame b to frame a, ``X_a = T_a_b @ X_b``;
composition is matrix multiplication ``T_a_c = T_a_b @ T_b_c``. A twist ``xi`` [..., 6] is
``(v, w)``: translational part first, rotational part (axis-angle, rad) last, as in kornia and
Sophus. Exp/log call kornia's ``Se3`` (passes our stress tests at 0 and pi); its results are
detached when the input needs no gradient (kornia wraps the translation in an ``nn.Parameter``,
which would otherwise make every output require grad).
"""

from __future__ import annotations

import torch
from kornia.geometry.liegroup import Se3 as _KorniaSe3

from manisplat.geometry.rotation import _flat, is_rotation, rotation_error


def make_transform(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Homogeneous transform [..., 4, 4] from rotation [..., 3, 3] and translation [..., 3]."""
    batch = torch.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = torch.zeros(*batch, 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert_transform(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms [..., 4, 4], using ``R^T`` (exact for rotations, no matrix inverse)."""
    R_inv = T[..., :3, :3].transpose(-1, -2)
    return make_transform(R_inv, -(R_inv @ T[..., :3, 3:4])[..., 0])


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply ``T`` [..., 4, 4] to points [..., N, 3] -> [..., N, 3]."""
    return points @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Transform [..., 4, 4] of twists ``xi`` [..., 6] = (v, w)."""
    flat, batch = _flat(xi, 1)
    return _plain(_KorniaSe3.exp(flat).matrix().reshape(*batch, 4, 4), xi)


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """Twist [..., 6] = (v, w) of rigid transforms [..., 4, 4]; rotation angle in [0, pi]."""
    flat, batch = _flat(T, 2)
    return _plain(_KorniaSe3.from_matrix(flat).log().reshape(*batch, 6), T)


def _plain(out: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
    return out if source.requires_grad else out.detach()


def translation_error(T_a: torch.Tensor, T_b: torch.Tensor) -> torch.Tensor:
    """Euclidean distance [...] between the translations of transforms [..., 4, 4] (their unit)."""
    return (T_a[..., :3, 3] - T_b[..., :3, 3]).norm(dim=-1)


def pose_error(T_a: torch.Tensor, T_b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(translation distance [...], geodesic rotation angle [...] in rad) between two poses."""
    return translation_error(T_a, T_b), rotation_error(T_a[..., :3, :3], T_b[..., :3, :3])


def is_transform(T: torch.Tensor, atol: float = 1e-6) -> torch.Tensor:
    """Bool [...]: a finite rigid transform (rotation block, last row exactly-ish 0 0 0 1)."""
    last = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype, device=T.device)
    bottom = (T[..., 3, :] - last).abs().amax(dim=-1) <= atol
    return is_rotation(T[..., :3, :3], atol) & bottom & torch.isfinite(T[..., :3, 3]).all(dim=-1)
