"""Kabsch / Umeyama / RANSAC: exact recovery, noise, weights, and every degenerate set."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from manisplat.geometry import (
    GeometryError,
    is_rotation,
    kabsch,
    kabsch_ransac,
    make_transform,
    pose_error,
    random_rotations,
    so3_exp,
    transform_points,
    umeyama,
)
from tests.geometry.strategies import transforms


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


@given(transforms(), st.integers(3, 60), st.integers(0, 10_000))
def test_kabsch_recovers_any_transform_exactly(T, n, seed):
    P = torch.randn(n, 3, dtype=torch.float64, generator=gen(seed))
    fit = kabsch(P, transform_points(T, P))
    t_err, r_err = pose_error(fit.T, T)
    assert float(t_err) < 1e-12 and float(r_err) < 1e-12
    assert float(fit.rms) < 1e-12 and float(fit.scale) == 1.0


def test_three_points_coplanar_sets_and_batches():
    T = make_transform(random_rotations(8, generator=gen(0)), torch.randn(8, 3, dtype=torch.float64, generator=gen(1)))
    P = torch.randn(8, 40, 3, dtype=torch.float64, generator=gen(2))
    P[:4, :, 2] = 0.0  # half of the problems are planar
    fit = kabsch(P, transform_points(T, P))
    assert fit.T.shape == (8, 4, 4)
    assert torch.allclose(fit.T, T, atol=1e-12)
    three = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=torch.float64)
    assert torch.allclose(kabsch(three, transform_points(T[0], three)).T, T[0], atol=1e-13)


def test_noise_gives_rms_near_sigma_and_small_error():
    """100 points in a 1 m cube, 1 mm noise: the rotation is known to ~sigma/(extent*sqrt(N))."""
    T = make_transform(so3_exp(torch.tensor([0.4, -1.2, 2.0], dtype=torch.float64)), torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64))
    P = torch.rand(100, 3, dtype=torch.float64, generator=gen(3)) - 0.5
    Q = transform_points(T, P) + 1e-3 * torch.randn(100, 3, dtype=torch.float64, generator=gen(4))
    fit = kabsch(P, Q)
    t_err, r_err = pose_error(fit.T, T)
    assert 0.7e-3 < float(fit.rms) < 1.3e-3 * math.sqrt(3)
    assert float(t_err) < 1e-3 and math.degrees(float(r_err)) < 0.05


def test_weights_ignore_zero_weighted_outliers():
    T = make_transform(so3_exp(torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)), torch.ones(3, dtype=torch.float64))
    P = torch.randn(20, 3, dtype=torch.float64, generator=gen(5))
    Q = transform_points(T, P)
    Q[:5] += 10.0
    w = torch.ones(20, dtype=torch.float64)
    w[:5] = 0.0
    assert torch.allclose(kabsch(P, Q, w).T, T, atol=1e-12)
    with pytest.raises(ValueError, match="non-negative"):
        kabsch(P, Q, -w)


def test_mirror_image_still_returns_a_proper_rotation():
    P = torch.randn(30, 3, dtype=torch.float64, generator=gen(6))
    Q = P * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)  # best orthogonal fit is a reflection
    fit = kabsch(P, Q)
    assert bool(is_rotation(fit.T[:3, :3], atol=1e-12))


@pytest.mark.parametrize(
    "points, message",
    [
        (torch.tensor([[0.0, 0, 0], [1, 1, 1]]), "at least 3"),
        (torch.tensor([[0.0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3]]), "collinear"),
        (torch.tensor([[1.0, 2, 3]] * 5), "collinear"),
        (torch.tensor([[0.0, 0, 0], [0, 0, 0], [1, 0, 0]]), "collinear"),  # duplicates leave 2 distinct points
    ],
    ids=["two points", "collinear", "all identical", "duplicates"],
)
def test_degenerate_sets_raise_a_clear_error(points, message):
    P = points.double()
    with pytest.raises(GeometryError, match=message):
        kabsch(P, P + 1.0)


def test_nearly_collinear_float32_is_rejected_but_float64_accepted():
    t = torch.linspace(0, 1, 20, dtype=torch.float64)
    P = torch.stack([t, 1e-4 * torch.sin(7 * t), torch.zeros_like(t)], -1)
    kabsch(P, P)  # float64: spread ratio ~1e-4 > 1e-6
    with pytest.raises(GeometryError, match="spread ratio"):
        kabsch(P.float(), P.float())  # float32 threshold 1e-3


def test_umeyama_recovers_scale():
    T = make_transform(so3_exp(torch.tensor([1.0, 0.0, 0.5], dtype=torch.float64)), torch.tensor([0.5, 0.0, -1.0], dtype=torch.float64))
    P = torch.randn(50, 3, dtype=torch.float64, generator=gen(7))
    Q = 2.5 * (P @ T[:3, :3].T) + T[:3, 3]
    fit = umeyama(P, Q)
    assert abs(float(fit.scale) - 2.5) < 1e-12
    assert torch.allclose(fit.T, T, atol=1e-12)


def test_ransac_recovers_transform_through_forty_percent_outliers():
    T = make_transform(so3_exp(torch.tensor([0.3, -0.2, 0.9], dtype=torch.float64)), torch.tensor([0.2, -0.1, 0.4], dtype=torch.float64))
    P = torch.rand(200, 3, dtype=torch.float64, generator=gen(8))
    Q = transform_points(T, P) + 2e-4 * torch.randn(200, 3, dtype=torch.float64, generator=gen(9))
    outlier = torch.zeros(200, dtype=torch.bool)
    outlier[::5] = outlier[1::5] = True  # 40 %
    Q[outlier] += 0.05 + torch.rand(int(outlier.sum()), 3, dtype=torch.float64, generator=gen(10))
    fit = kabsch_ransac(P, Q, threshold=1e-3)
    t_err, r_err = pose_error(fit.T, T)
    assert float(t_err) < 2e-4 and math.degrees(float(r_err)) < 0.05
    assert torch.equal(fit.inliers, ~outlier)
    again = kabsch_ransac(P, Q, threshold=1e-3)
    assert torch.equal(again.T, fit.T)  # deterministic by default
    with pytest.raises(GeometryError):
        kabsch_ransac(P, torch.rand(200, 3, dtype=torch.float64, generator=gen(11)) * 10, threshold=1e-4)


def test_ransac_rejects_bad_arguments():
    P = torch.rand(10, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="threshold"):
        kabsch_ransac(P, P, threshold=0.0)
    with pytest.raises(ValueError, match="one problem"):
        kabsch_ransac(P[None], P[None], threshold=0.1)
    with pytest.raises(ValueError, match="NaN"):
        kabsch(P, P * float("nan"))
