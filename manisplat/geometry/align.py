"""Least-squares rigid (Kabsch) and similarity (Umeyama) fits of point pairs, plus RANSAC.

The fits solve ``min sum_i w_i |s R p_i + t - q_i|^2`` in closed form by SVD of the weighted
cross-covariance, with the sign correction that rules out reflections (so coplanar sets are
fine). A set that does not fix a rotation (fewer than 3 weighted points, all points coincident
or collinear) raises :class:`GeometryError` instead of returning an arbitrary rotation.
Results carry no gradient (SVD gradients blow up for symmetric point sets); these fits are
estimators for initial values and pseudo-ground truth, not differentiable layers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from manisplat.geometry.errors import GeometryError
from manisplat.geometry.se3 import make_transform


@dataclass(frozen=True)
class RigidFit:
    """A fitted transform mapping source points to target points: ``q ~ scale * R p + t``.

    Attributes:
        T: [..., 4, 4] the rigid part (R, t); the scale is not folded into it.
        scale: [...] 1 for Kabsch; the similarity scale for Umeyama.
        rms: [...] weighted root-mean-square residual, in the points' unit.
    """

    T: torch.Tensor
    scale: torch.Tensor
    rms: torch.Tensor


@dataclass(frozen=True)
class RansacFit(RigidFit):
    """A :class:`RigidFit` refined on its consensus set.

    Attributes:
        inliers: [N] bool, pairs whose residual is within the threshold.
        iterations: hypotheses drawn.
    """

    inliers: torch.Tensor
    iterations: int


def _default_rtol(dtype: torch.dtype) -> float:
    return 1e-6 if dtype == torch.float64 else 1e-3


def _fit(
    P: torch.Tensor, Q: torch.Tensor, w: torch.Tensor, with_scale: bool, rtol: float
) -> tuple[RigidFit, torch.Tensor, torch.Tensor]:
    """Core batched fit. Returns the fit, a bool [...] 'well-conditioned' mask and the spread ratio."""
    W = w.sum(-1, keepdim=True)  # [..., 1]
    wn = w / torch.where(W > 0, W, torch.ones_like(W))  # [..., N]
    p_mean = (wn[..., None] * P).sum(-2)  # [..., 3]
    q_mean = (wn[..., None] * Q).sum(-2)
    X = P - p_mean[..., None, :]  # [..., N, 3]
    Y = Q - q_mean[..., None, :]
    sqrt_w = wn.sqrt()[..., None]
    spread_x = torch.linalg.svdvals(X * sqrt_w)  # [..., 3], descending
    spread_y = torch.linalg.svdvals(Y * sqrt_w)
    ratio = torch.minimum(spread_x[..., 1] / spread_x[..., 0], spread_y[..., 1] / spread_y[..., 0])
    ratio = torch.nan_to_num(ratio, nan=0.0)
    ok = (ratio > rtol) & (spread_x[..., 0] > 0) & ((w > 0).sum(-1) >= 3)

    H = (X * wn[..., None]).transpose(-1, -2) @ Y  # [..., 3, 3] cross-covariance
    U, S, Vh = torch.linalg.svd(H)
    V = Vh.transpose(-1, -2)
    d = torch.sign(torch.linalg.det(V @ U.transpose(-1, -2)))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.ones_like(S)
    D[..., 2] = d
    R = (V * D[..., None, :]) @ U.transpose(-1, -2)
    if with_scale:
        var_x = (wn * (X * X).sum(-1)).sum(-1)
        scale = (S * D).sum(-1) / torch.where(var_x > 0, var_x, torch.ones_like(var_x))
    else:
        scale = torch.ones_like(d)
    t = q_mean - scale[..., None] * (R @ p_mean[..., None])[..., 0]
    resid = scale[..., None, None] * (P @ R.transpose(-1, -2)) + t[..., None, :] - Q
    rms = (wn * (resid * resid).sum(-1)).sum(-1).sqrt()
    return RigidFit(make_transform(R, t), scale, rms), ok, ratio


def _check_pairs(P: torch.Tensor, Q: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
    if P.shape != Q.shape or P.shape[-1] != 3 or P.ndim < 2:
        raise ValueError(f"point sets must both be [..., N, 3]; got {tuple(P.shape)} and {tuple(Q.shape)}")
    if P.shape[-2] < 3:
        raise GeometryError(f"a rigid fit needs at least 3 point pairs, got {P.shape[-2]}")
    if not (torch.isfinite(P).all() and torch.isfinite(Q).all()):
        raise ValueError("point sets contain NaN or Inf")
    if weights is None:
        return torch.ones(P.shape[:-1], dtype=P.dtype, device=P.device)
    w = torch.as_tensor(weights, dtype=P.dtype, device=P.device).expand(P.shape[:-1])
    if not torch.isfinite(w).all() or bool((w < 0).any()):
        raise ValueError("weights must be finite and non-negative")
    return w


def _fit_or_raise(P, Q, weights, with_scale: bool, rtol: float | None, name: str) -> RigidFit:
    w = _check_pairs(P, Q, weights)
    with torch.no_grad():
        fit, ok, ratio = _fit(P, Q, w, with_scale, _default_rtol(P.dtype) if rtol is None else rtol)
    if not bool(ok.all()):
        bad = (~ok).nonzero()[0].tolist()
        count = int((w[tuple(bad)] > 0).sum()) if bad else int((w > 0).sum())
        where = f" at batch index {tuple(bad)}" if bad else ""
        raise GeometryError(
            f"{name}: the points do not determine a rotation{where}: "
            f"{count} weighted pairs, spread ratio sigma2/sigma1 = {float(ratio[tuple(bad)]):.3g} "
            f"(collinear, coincident or too few points; need > {rtol or _default_rtol(P.dtype):g})"
        )
    return fit


def kabsch(
    P: torch.Tensor, Q: torch.Tensor, weights: torch.Tensor | None = None, *, rtol: float | None = None
) -> RigidFit:
    """Rigid transform mapping points ``P`` [..., N, 3] onto ``Q`` [..., N, 3] (weighted least squares).

    Args:
        weights: [..., N] non-negative pair weights (default: all 1).
        rtol: the smallest accepted ratio of the second to the first principal spread of either
            point set (default 1e-6 for float64, 1e-3 for float32); below it the rotation about
            the points' line is undetermined and :class:`GeometryError` is raised.
    """
    return _fit_or_raise(P, Q, weights, False, rtol, "kabsch")


def umeyama(
    P: torch.Tensor, Q: torch.Tensor, weights: torch.Tensor | None = None, *, rtol: float | None = None
) -> RigidFit:
    """Similarity transform (rotation, translation and uniform scale) mapping ``P`` onto ``Q``.

    Same arguments and errors as :func:`kabsch`; ``scale`` holds the fitted scale.
    """
    return _fit_or_raise(P, Q, weights, True, rtol, "umeyama")


def kabsch_ransac(
    P: torch.Tensor,
    Q: torch.Tensor,
    threshold: float,
    *,
    confidence: float = 0.999,
    max_iterations: int = 2000,
    min_inliers: int = 3,
    with_scale: bool = False,
    rtol: float | None = None,
    generator: torch.Generator | None = None,
) -> RansacFit:
    """Robust rigid (or similarity) fit of pairs ``P``, ``Q`` [N, 3] containing outliers.

    Draws minimal 3-pair samples in batches, scores each hypothesis by the truncated squared
    residual (MSAC), stops once ``confidence`` is reached for the best inlier ratio, then refits
    on the consensus set until it stops changing. Deterministic by default (seed 0).

    Args:
        threshold: a pair is an inlier when its residual is at most this (points' unit).
        min_inliers: fewer inliers than this raises :class:`GeometryError`.

    Raises:
        GeometryError: no hypothesis reaches ``min_inliers`` or the consensus set is degenerate.
    """
    w = _check_pairs(P, Q, None)
    if P.ndim != 2:
        raise ValueError(f"kabsch_ransac takes one problem, [N, 3] points; got {tuple(P.shape)}")
    if not threshold > 0:
        raise ValueError(f"threshold must be positive, got {threshold}")
    tol = _default_rtol(P.dtype) if rtol is None else rtol
    gen = generator if generator is not None else torch.Generator().manual_seed(0)
    n = P.shape[0]
    chunk = max(1, min(256, 4_000_000 // n))
    th2 = threshold * threshold
    best_score, best_T, best_s = math.inf, None, None
    needed, drawn = float(max_iterations), 0
    with torch.no_grad():
        while drawn < min(needed, max_iterations):
            k = int(min(chunk, max_iterations - drawn))
            idx = torch.multinomial(torch.ones(k, n, dtype=torch.float64), 3, generator=gen).to(P.device)
            fit, ok, _ = _fit(P[idx], Q[idx], w[idx], with_scale, tol)
            drawn += k
            resid2 = _residual2(P, Q, fit.T, fit.scale)  # [k, N]
            score = resid2.clamp(max=th2).sum(-1)
            score = torch.where(ok, score, torch.full_like(score, math.inf))
            i = int(score.argmin())
            if float(score[i]) < best_score:
                best_score, best_T, best_s = float(score[i]), fit.T[i], fit.scale[i]
                ratio = float((resid2[i] <= th2).sum()) / n
                needed = _iterations_needed(ratio, confidence)
        if best_T is None:
            raise GeometryError(f"RANSAC: all {drawn} minimal samples were degenerate (collinear points)")
        inliers = _residual2(P, Q, best_T, best_s) <= th2
        for _ in range(20):
            count = int(inliers.sum())
            if count < max(3, min_inliers):
                raise GeometryError(
                    f"RANSAC: best hypothesis has {count} inliers of {n} within {threshold:g}; need {max(3, min_inliers)}"
                )
            fit = _fit_or_raise(P, Q, inliers.to(P.dtype), with_scale, rtol, "kabsch_ransac refit")
            new = _residual2(P, Q, fit.T, fit.scale) <= th2
            if torch.equal(new, inliers):
                break
            inliers = new
    return RansacFit(fit.T, fit.scale, fit.rms, inliers, drawn)


def _residual2(P: torch.Tensor, Q: torch.Tensor, T: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Squared residuals [..., N] of ``scale R p + t - q`` for pairs [N, 3] and fits T [..., 4, 4]."""
    R, t = T[..., :3, :3], T[..., None, :3, 3]
    return (scale[..., None, None] * (P @ R.transpose(-1, -2)) + t - Q).pow(2).sum(-1)


def _iterations_needed(inlier_ratio: float, confidence: float) -> float:
    """Samples of 3 needed to draw one all-inlier sample with probability ``confidence``."""
    p_good = inlier_ratio**3
    if p_good >= 1.0:
        return 1.0
    if p_good <= 0.0:
        return math.inf
    return math.log(1.0 - confidence) / math.log(1.0 - p_good)
