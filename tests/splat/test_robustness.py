"""Never NaN/Inf, in outputs or gradients: Gaussians on or behind the camera plane, scales from
1e-8 to 1e3, zero or unnormalised quaternions, empty scenes, everything culled, large counts."""

from __future__ import annotations

import pytest
import torch

from manisplat.splat import rasterization
from tests.splat.scenes import camera, random_scene

BACKENDS = ["torch", "cpu"]


def check_finite_everywhere(backend, params, V, K, W, H, **kwargs):
    leaves = [p.clone().requires_grad_(True) for p in params]
    colors, alphas, meta = rasterization(*leaves, V, K, W, H, backend=backend, **kwargs)
    assert torch.isfinite(colors).all() and torch.isfinite(alphas).all()
    assert bool((alphas >= 0).all() and (alphas <= 1).all())
    (colors.sum() + alphas.sum()).backward()
    for p in leaves:
        assert p.grad is not None and torch.isfinite(p.grad).all()
    return colors.detach(), alphas.detach(), meta


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_gaussians_on_and_behind_the_camera_plane(backend, dtype):
    params, V, K, W, H = random_scene(40, 0, dtype=dtype)
    params[0][:10, 2] = -3.0  # exactly on the camera plane (camera at z = -3)
    params[0][10:20, 2] = -5.0  # behind
    params[0][20:25, 2] = -3.0 + 1e-9  # just in front, closer than the near plane
    check_finite_everywhere(backend, params, V, K, W, H, render_mode="RGB+ED")


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("scale", [1e-8, 1e-4, 1.0, 1e3])
def test_scales_from_1e_minus_8_to_1e3(backend, dtype, scale):
    params, V, K, W, H = random_scene(20, 1, dtype=dtype)
    params[2] = torch.full_like(params[2], scale)
    params[2][::2, 0] = scale * 1e-3  # needle-like too
    params[0][:5, 2] = -2.9  # some of them 0.1 m from the camera
    check_finite_everywhere(backend, params, V, K, W, H, render_mode="RGB+ED")


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_and_unnormalised_quaternions(backend):
    params, V, K, W, H = random_scene(20, 2)
    params[1][:5] = 0.0
    params[1][5:10] *= 1e6
    params[1][10:15] *= 1e-9
    colors, _, _ = check_finite_everywhere(backend, params, V, K, W, H)
    ref = params.copy()
    ref[1] = params[1].clone()
    ref[1][:5] = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)  # zero means identity
    ref[1][5:15] /= ref[1][5:15].norm(dim=-1, keepdim=True)
    expected, _, _ = rasterization(*ref, V, K, W, H, backend=backend)
    assert torch.allclose(colors, expected, atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_scene_and_all_culled(backend):
    V, K = camera()
    empty = [torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, 4, dtype=torch.float64),
             torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, dtype=torch.float64),
             torch.zeros(0, 3, dtype=torch.float64)]
    bg = torch.tensor([[0.2, 0.4, 0.6]], dtype=torch.float64)
    colors, alphas, _ = rasterization(*empty, V, K, 40, 30, backend=backend, backgrounds=bg)
    assert torch.equal(alphas, torch.zeros_like(alphas)) and torch.allclose(colors, bg.expand(1, 30, 40, 3)[..., None, :, :].reshape(1, 30, 40, 3))
    params, V, K, W, H = random_scene(10, 3)
    params[0][:, 2] = -10.0
    colors, alphas, _ = check_finite_everywhere(backend, params, V, K, W, H)
    assert float(alphas.max()) == 0.0


def test_many_gaussians_stay_finite_and_saturate():
    """200k small Gaussians in a 64x48 image (hundreds per pixel, early termination everywhere)."""
    params, V, K, W, H = random_scene(200_000, 4, dtype=torch.float32, width=64, height=48, scale=(0.005, 0.05))
    colors, alphas, _ = check_finite_everywhere("cpu", params, V, K, W, H)
    assert float(alphas.min()) > 0.99
