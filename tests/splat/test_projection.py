"""Projection and conventions: C++ equals the torch oracle; gsplat's pixel centre, dilation,
culling and opacity-aware radius; OpenCV intrinsics conversion."""

from __future__ import annotations

import math

import pytest
import torch

from manisplat.splat import opencv_to_splat_K, project_gaussians, rasterization
from manisplat.splat.backends import cpu_raster
from tests.splat.scenes import camera, random_scene

f64 = torch.float64


def one_gaussian(x, y, z, scale=0.05, opacity=0.9):
    return [torch.tensor([[x, y, z]], dtype=f64), torch.tensor([[1.0, 0, 0, 0]], dtype=f64),
            torch.full((1, 3), scale, dtype=f64), torch.tensor([opacity], dtype=f64), torch.ones(1, 3, dtype=f64)]


def test_cpu_projection_equals_the_oracle_with_viewmat_gradients():
    params, _, K, W, H = random_scene(300, 3)
    view = camera(yaw=0.4)[0].clone()
    view[0, :3, 3] += torch.tensor([0.1, -0.2, 0.3], dtype=f64)
    out = {}
    for name, fn in (("torch", project_gaussians), ("cpu", cpu_raster.project)):
        leaves = [p.clone().requires_grad_(True) for p in params[:4]]
        v = view.clone().requires_grad_(True)
        proj = fn(*leaves, v, K, W, H)
        vis = proj.visible[0]
        g = torch.Generator().manual_seed(1)
        loss = sum((getattr(proj, k)[0][vis] * torch.rand(getattr(proj, k)[0][vis].shape, generator=g, dtype=f64)).sum()
                   for k in ("means2d", "conics", "depths"))
        loss.backward()
        out[name] = (proj, [p.grad for p in leaves[:3]] + [v.grad])
    (pt, gt), (pc, gc) = out["torch"], out["cpu"]
    assert torch.equal(pt.radii, pc.radii) and int(pt.visible.sum()) > 200
    for key in ("means2d", "conics", "depths"):
        assert torch.allclose(getattr(pt, key), getattr(pc, key), atol=1e-12, rtol=1e-12)
    for a, b in zip(gt, gc):
        assert float((a - b).norm()) <= 1e-9 * float(a.norm())


def test_pixel_centres_are_at_half_integers():
    """A small Gaussian on the ray through (12.5, 10.5) lights pixel (row 10, col 12) most."""
    view, K = camera(width=24, height=20)
    fx, cx, cy = float(K[0, 0, 0]), float(K[0, 0, 2]), float(K[0, 1, 2])
    z = 3.0
    x = (12.5 - cx) / fx * z
    y = (10.5 - cy) / fx * z
    for backend in ("torch", "cpu"):
        img, alpha, _ = rasterization(*one_gaussian(x, y, 0.0, scale=0.003), view, K, 24, 20, backend=backend)
        row, col = divmod(int(alpha[0, ..., 0].argmax()), 24)
        assert (row, col) == (10, 12)
        a = alpha[0, ..., 0]
        assert torch.allclose(a[10, 11], a[10, 13]) and torch.allclose(a[9, 12], a[11, 12])  # symmetric


def test_dilation_gives_tiny_gaussians_a_0p3_pixel_variance():
    view, K = camera(width=24, height=20)
    proj = project_gaussians(*one_gaussian(0.0, 0.0, 0.0, scale=1e-8)[:4], view, K, 24, 20)
    a, b, c = proj.conics[0, 0].tolist()
    assert abs(a - 1 / 0.3) < 1e-6 and abs(b) < 1e-12 and abs(c - 1 / 0.3) < 1e-6


@pytest.mark.parametrize(
    "z, opacity, xy, why",
    [(-3.0, 0.9, (0.0, 0.0), "behind the camera"), (-2.995, 0.9, (0.0, 0.0), "closer than near"),
     (0.0, 1e-3, (0.0, 0.0), "opacity below 1/255"), (0.0, 0.9, (10.0, 0.0), "box off the image")],
)
def test_culling_rules(z, opacity, xy, why):
    view, K = camera()
    params = one_gaussian(xy[0], xy[1], z, opacity=opacity)
    for fn in (project_gaussians, cpu_raster.project):
        proj = fn(*params[:4], view, K, 40, 30)
        assert not bool(proj.visible.any()), why
    img, alpha, meta = rasterization(*params, view, K, 40, 30)
    assert float(alpha.abs().max()) == 0.0 and not bool(meta["visible"].any())


def test_radius_is_opacity_aware():
    view, K = camera()
    strong = project_gaussians(*one_gaussian(0, 0, 0, 0.05, 0.99)[:4], view, K, 40, 30).radii[0, 0]
    faint = project_gaussians(*one_gaussian(0, 0, 0, 0.05, 0.02)[:4], view, K, 40, 30).radii[0, 0]
    assert bool((faint < strong).all())
    sigma_px = math.sqrt((0.05 * 50 / 3) ** 2 + 0.3)
    assert int(strong[0]) == math.ceil(min(3.33, math.sqrt(2 * math.log(0.99 * 255))) * sigma_px)


def test_opencv_intrinsics_shift_by_half_a_pixel():
    K = torch.tensor([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]], dtype=f64)
    out = opencv_to_splat_K(K)
    assert out[0, 2] == 32.0 and out[1, 2] == 24.0 and K[0, 2] == 31.5  # input untouched
