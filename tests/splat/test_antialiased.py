"""``rasterize_mode="antialiased"``: splats keep their integral when they are far smaller than
a pixel (a Gaussian fitted to a close-up, seen from afar); large ones barely change."""

from __future__ import annotations

import math

import pytest
import torch

from manisplat.splat import DEFAULT_EPS2D, RasterizationError, rasterization
from manisplat.splat.projection import opacity_compensation
from tests.splat.scenes import camera

EPS2D = 0.3


def test_the_compensation_is_the_square_root_of_the_determinants_ratio():
    """sqrt(det S / det(S + eps I)) for 2D covariances S, given the conic of the dilated one."""
    g = torch.Generator().manual_seed(0)
    spread = torch.rand(200, 1, 1, dtype=torch.float64, generator=g) * 3
    A = torch.randn(200, 2, 2, dtype=torch.float64, generator=g) * spread
    S = A @ A.transpose(-1, -2) + 1e-3 * torch.eye(2, dtype=torch.float64)
    dilated = S + EPS2D * torch.eye(2, dtype=torch.float64)
    inv = torch.linalg.inv(dilated)
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
    expected = torch.sqrt(torch.linalg.det(S) / torch.linalg.det(dilated))
    got = opacity_compensation(conics, EPS2D)
    floor = expected > 0.01
    assert torch.allclose(got[floor], expected[floor], rtol=1e-9)
    assert torch.allclose(got[~floor], torch.full_like(got[~floor], 0.01))
    # isotropic: sigma^2 / (sigma^2 + eps); tends to 1 for splats many pixels wide
    for var in (0.05, 1.0, 100.0):
        iso = torch.tensor([[1 / (var + EPS2D), 0.0, 1 / (var + EPS2D)]], dtype=torch.float64)
        assert float(opacity_compensation(iso, EPS2D)) == pytest.approx(var / (var + EPS2D), rel=1e-12)


def _alpha_integral(distance: float, mode: str, scale: float = 0.024, opacity: float = 1.0) -> float:
    """Summed alpha (px^2) of one round Gaussian of ``scale`` m at the origin, seen from ``distance`` m
    (on a pixel's centre: the image is 41 x 31 px)."""
    V, K = camera(distance=distance, width=41, height=31)
    params = [torch.zeros(1, 3, dtype=torch.float64), torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
              torch.full((1, 3), scale, dtype=torch.float64), torch.tensor([opacity], dtype=torch.float64),
              torch.ones(1, 3, dtype=torch.float64)]
    _, alphas, _ = rasterization(*params, V, K, 41, 31, eps2d=EPS2D, rasterize_mode=mode, backend="cpu")
    return float(alphas.sum())


def test_a_splat_smaller_than_a_pixel_keeps_its_integral_when_seen_from_afar():
    """A Gaussian of sigma 0.4 px, then 0.2 px (twice as far): antialiased, its summed alpha is
    its own integral (2 pi sigma^2 at opacity 1, a quarter when twice as far); classic, the
    0.3 px^2 dilation draws it over 2.9 and 8.5 times that area at full opacity."""
    f = camera(width=41, height=31)[1][0, 0, 0].item()
    for distance in (3.0, 6.0):
        sigma_px = f * 0.024 / distance
        integral = 2 * math.pi * sigma_px**2
        # pixels below 1/255 alpha are cut: about 1 % of the mass of a splat this faint
        assert _alpha_integral(distance, "antialiased") == pytest.approx(integral, rel=0.03)
        assert _alpha_integral(distance, "classic") > 2.5 * integral
    near, far = (_alpha_integral(d, "antialiased") for d in (3.0, 6.0))
    assert far / near == pytest.approx(0.25, rel=0.03)


def test_a_splat_many_pixels_wide_is_drawn_as_in_classic_mode():
    """10 px wide: the compensation is sigma^2 / (sigma^2 + 0.3) = 0.997."""
    classic, antialiased = (_alpha_integral(3.0, mode, scale=0.6, opacity=0.5) for mode in ("classic", "antialiased"))
    assert antialiased == pytest.approx(classic, rel=0.005)
    assert antialiased < classic


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_each_mode_dilates_by_its_own_default(mode):
    """Unset, eps2d is the mode's: gsplat's 0.3 px^2 classic, Mip-Splatting's 0.1 antialiased."""
    assert DEFAULT_EPS2D == {"classic": 0.3, "antialiased": 0.1}
    V, K = camera(distance=6.0, width=41, height=31)
    params = [torch.zeros(1, 3, dtype=torch.float64), torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
              torch.full((1, 3), 0.024, dtype=torch.float64), torch.tensor([1.0], dtype=torch.float64),
              torch.ones(1, 3, dtype=torch.float64)]
    drawn = {eps: rasterization(*params, V, K, 41, 31, eps2d=eps, rasterize_mode=mode, backend="cpu")[1]
             for eps in (None, 0.1, 0.3)}
    other = 0.3 if DEFAULT_EPS2D[mode] == 0.1 else 0.1
    assert torch.equal(drawn[None], drawn[DEFAULT_EPS2D[mode]])
    assert not torch.allclose(drawn[None], drawn[other], atol=1e-3)


@pytest.mark.parametrize("eps2d", [-0.1, float("nan"), float("inf")])
def test_a_dilation_that_is_not_a_finite_non_negative_area_is_refused(eps2d):
    V, K = camera(width=41, height=31)
    params = [torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.02), torch.tensor([0.5]),
              torch.ones(1, 3)]
    with pytest.raises(RasterizationError, match="eps2d must be a finite dilation"):
        rasterization(*params, V.float(), K.float(), 41, 31, eps2d=eps2d, backend="cpu")
