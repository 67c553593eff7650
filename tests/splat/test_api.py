"""Input checks and backend selection of ``rasterization``: clear errors, nothing silent."""

from __future__ import annotations

import math

import pytest
import torch

from manisplat.splat import BackendUnavailable, RasterizationError, rasterization, spherical_harmonics
from manisplat.splat.sh import C0
from tests.splat.scenes import random_scene


@pytest.fixture()
def scene():
    return random_scene(5, 0)


def call(scene, **kwargs):
    params, V, K, W, H = scene
    return rasterization(*params, V, K, W, H, **kwargs)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda p: p.__setitem__(0, p[0][:, :2]), "means must have shape"),
        (lambda p: p.__setitem__(2, -p[2]), "non-negative"),
        (lambda p: p.__setitem__(3, p[3] + 1.0), r"opacities must be in \[0, 1\]"),
        (lambda p: p[0].__setitem__((0, 0), math.nan), "means contains NaN"),
        (lambda p: p.__setitem__(4, p[4][:3]), "colors must be"),
    ],
)
def test_bad_inputs_are_named(scene, mutate, message):
    params = [p.clone() for p in scene[0]]
    mutate(params)
    with pytest.raises(RasterizationError, match=message):
        call((params, *scene[1:]))


def test_bad_options(scene):
    with pytest.raises(RasterizationError, match="render_mode"):
        call(scene, render_mode="RGBD")
    with pytest.raises(RasterizationError, match="num_groups"):
        call(scene, group_ids=torch.zeros(5, dtype=torch.long))
    with pytest.raises(RasterizationError, match=r"\[0, 2\)"):
        call(scene, group_ids=torch.full((5,), 2), num_groups=2)
    with pytest.raises(ValueError, match="unknown backend"):
        call(scene, backend="vulkan")
    with pytest.raises(RasterizationError, match="SH colours"):
        call(scene, sh_degree=2)
    with pytest.raises(RasterizationError, match="rasterize_mode must be one of"):
        call(scene, rasterize_mode="mip")


def test_gsplat_needs_cuda_and_says_so(scene):
    with pytest.raises(BackendUnavailable, match="CUDA"):
        call(scene, backend="gsplat")


def test_auto_is_the_cpu_backend_on_cpu(scene):
    assert call(scene)[2]["backend"] == "cpu"
    assert call(scene, backend="torch")[2]["backend"] == "torch"


def test_spherical_harmonics_degree_0_and_1():
    coeffs = torch.zeros(1, 4, 3, dtype=torch.float64)
    coeffs[0, 0] = torch.tensor([1.0, 2.0, 3.0])
    coeffs[0, 3] = torch.tensor([1.0, 0.0, 0.0])  # the x band
    d = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    out0 = spherical_harmonics(0, d, coeffs)
    assert torch.allclose(out0, C0 * coeffs[0, 0][None])
    out1 = spherical_harmonics(1, torch.tensor([[2.0, 0.0, 0.0]], dtype=torch.float64), coeffs)  # any length
    assert torch.allclose(out1 - out0, torch.tensor([[-0.4886025119029199, 0.0, 0.0]], dtype=torch.float64))
    with pytest.raises(ValueError, match="0..3"):
        spherical_harmonics(4, d, coeffs)


def _sh_basis_written_out(d: torch.Tensor) -> torch.Tensor:
    """[N, 16] the real SH basis of unit directions [N, 3] in gsplat's order and signs, term by term."""
    x, y, z = d.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    return torch.stack([
        torch.full_like(x, C0), -0.4886025119029199 * y, 0.4886025119029199 * z, -0.4886025119029199 * x,
        1.0925484305920792 * x * y, -1.0925484305920792 * y * z, 0.31539156525252005 * (2 * zz - xx - yy),
        -1.0925484305920792 * x * z, 0.5462742152960396 * (xx - yy),
        -0.5900435899266435 * y * (3 * xx - yy), 2.890611442640554 * x * y * z,
        -0.4570457994644658 * y * (4 * zz - xx - yy), 0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy),
        -0.4570457994644658 * x * (4 * zz - xx - yy), 1.445305721320277 * z * (xx - yy),
        -0.5900435899266435 * x * (xx - 3 * yy),
    ], dim=-1)


@pytest.mark.parametrize("degree", [2, 3])
def test_spherical_harmonics_of_every_band_term_by_term(degree):
    g = torch.Generator().manual_seed(degree)
    d = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64, generator=g), dim=-1)
    n = (degree + 1) ** 2
    coeffs = torch.randn(50, 16, 3, dtype=torch.float64, generator=g)
    expected = (_sh_basis_written_out(d)[:, :n, None] * coeffs[:, :n]).sum(1)
    torch.testing.assert_close(spherical_harmonics(degree, 2.5 * d, coeffs), expected, rtol=0, atol=1e-13)
    for k in range(n):  # each coefficient alone: a misplaced term cannot cancel out
        one = torch.zeros(1, 16, 1, dtype=torch.float64)
        one[0, k] = 1.0
        torch.testing.assert_close(spherical_harmonics(degree, d, one.expand(50, 16, 1))[:, 0],
                                   _sh_basis_written_out(d)[:, k], rtol=0, atol=1e-14)


def test_no_compiler_is_a_clear_error_not_a_silent_fallback(scene, monkeypatch):
    from manisplat.splat.backends import cpu_raster

    monkeypatch.setattr(cpu_raster, "_extension", None)
    monkeypatch.setenv("CXX", "no-such-c++-compiler")
    with pytest.raises(BackendUnavailable, match="backend='torch'"):
        call(scene, backend="cpu")
    assert call(scene, backend="torch")[2]["backend"] == "torch"  # the fallback is the user's explicit choice
