"""Interpolation of rotations, poses and joint vectors at arbitrary query times.

Nothing here extrapolates: a query outside the sampled time range raises ``ValueError``. Each
function also returns or accepts what a caller needs to flag queries that fall into a large gap
between samples (the recorder refuses to trust an interpolation across a dropout).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from manisplat.geometry.rotation import DEFAULT_DTYPE, so3_exp, so3_log


class Bracket(NamedTuple):
    """Where query times fall among sample times.

    Attributes:
        lower: [M] index of the sample at or before each query.
        upper: [M] index of the sample after it (``lower`` when there is one sample).
        fraction: [M] position in [0, 1] between the two.
        gap: [M] time between the two samples (0 for an exact single sample), in s.
    """

    lower: torch.Tensor
    upper: torch.Tensor
    fraction: torch.Tensor
    gap: torch.Tensor


def _as_float(x, like: torch.Tensor | None = None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x
    return torch.as_tensor(x, dtype=like.dtype if like is not None else DEFAULT_DTYPE)


def bracket_times(times: torch.Tensor, query: torch.Tensor) -> Bracket:
    """Locate ``query`` [M] among strictly increasing sample ``times`` [T].

    Raises:
        ValueError: times are empty, not finite or not strictly increasing, or a query lies
            outside ``[times[0], times[-1]]`` (no extrapolation).
    """
    times, query = _as_float(times), _as_float(query)
    if times.ndim != 1 or times.numel() == 0:
        raise ValueError(f"sample times must be a non-empty 1-D array, got shape {tuple(times.shape)}")
    if not bool(torch.isfinite(times).all()) or not bool(torch.isfinite(query).all()):
        raise ValueError("sample or query times contain NaN or Inf")
    steps = times[1:] - times[:-1]
    if bool((steps <= 0).any()):
        k = int((steps <= 0).nonzero()[0])
        raise ValueError(f"sample times must be strictly increasing: t[{k}]={float(times[k])!r} >= t[{k + 1}]={float(times[k + 1])!r}")
    outside = (query < times[0]) | (query > times[-1])
    if bool(outside.any()):
        k = int(outside.nonzero()[0])
        raise ValueError(
            f"query time {float(query[k])!r} lies outside the sampled range "
            f"[{float(times[0])!r}, {float(times[-1])!r}]; refusing to extrapolate"
        )
    n = times.numel()
    if n == 1:
        zeros = torch.zeros_like(query, dtype=torch.long)
        return Bracket(zeros, zeros, torch.zeros_like(query), torch.zeros_like(query))
    upper = torch.searchsorted(times, query, right=True).clamp(1, n - 1)
    lower = upper - 1
    gap = times[upper] - times[lower]
    fraction = ((query - times[lower]) / gap).clamp(0.0, 1.0)
    return Bracket(lower, upper, fraction, gap)


class JointInterpolation(NamedTuple):
    """Joint vectors at query times.

    Attributes:
        values: [M, D] interpolated values.
        gap: [M] time between the two samples each query was interpolated from, in s.
    """

    values: torch.Tensor
    gap: torch.Tensor


def interpolate_joints(times: torch.Tensor, values: torch.Tensor, query: torch.Tensor) -> JointInterpolation:
    """Linear interpolation of joint vectors ``values`` [T, D] sampled at ``times`` [T] at ``query`` [M].

    A query equal to a sample time returns that sample exactly. Compare ``gap`` with a bound
    to flag queries that fall into a dropout.
    """
    values = _as_float(values)
    times = _as_float(times, values)
    if values.ndim != 2 or values.shape[0] != times.shape[0]:
        raise ValueError(f"values must be [T, D] with T = len(times) = {times.shape[0]}; got {tuple(values.shape)}")
    if not bool(torch.isfinite(values).all()):
        raise ValueError("joint values contain NaN or Inf")
    b = bracket_times(times, _as_float(query, values))
    s = b.fraction[:, None]
    return JointInterpolation((1.0 - s) * values[b.lower] + s * values[b.upper], b.gap)


def slerp(R0: torch.Tensor, R1: torch.Tensor, s: torch.Tensor | float) -> torch.Tensor:
    """Rotation a fraction ``s`` [...] of the way from ``R0`` to ``R1`` [..., 3, 3] on the geodesic.

    ``R0 @ exp(s * log(R0^T R1))``, stable for nearly equal rotations (no division by sin of a
    small angle); s = 0 and s = 1 return ``R0`` and ``R1`` bit for bit. At a relative angle of
    exactly pi the two geodesics are equally short and either may be taken.
    """
    s = _as_float(s, R0)
    delta = so3_log(R0.transpose(-1, -2) @ R1)
    out = R0 @ so3_exp(s[..., None] * delta)
    return torch.where((s == 1.0)[..., None, None], R1, out)


def interpolate_poses(times: torch.Tensor, poses: torch.Tensor, query: torch.Tensor) -> torch.Tensor:
    """Poses [M, 4, 4] at ``query`` [M] from ``poses`` [T, 4, 4] sampled at ``times`` [T].

    Rotation by :func:`slerp`, translation linearly ("slerp + lerp"); no extrapolation.
    """
    b = bracket_times(_as_float(times, poses), _as_float(query, poses))
    T0, T1 = poses[b.lower], poses[b.upper]
    out = T0.clone()
    out[:, :3, :3] = slerp(T0[:, :3, :3], T1[:, :3, :3], b.fraction)
    s = b.fraction[:, None]
    out[:, :3, 3] = (1.0 - s) * T0[:, :3, 3] + s * T1[:, :3, 3]
    return out
