"""The C++ backend against the pure-PyTorch oracle: images, alphas, depth, group alphas and
the gradients of every input, in float64 (exact to rounding) and float32 (to tolerance)."""

from __future__ import annotations

import pytest
import torch

from manisplat.splat import rasterization
from tests.splat.scenes import camera, random_scene


def render_and_grad(backend, params, viewmats, Ks, W, H, **kwargs):
    leaves = [p.clone().requires_grad_(True) for p in params]
    views = viewmats.clone().requires_grad_(True)
    colors, alphas, meta = rasterization(*leaves, views, Ks, W, H, backend=backend, **kwargs)
    g = torch.Generator().manual_seed(99)
    loss = (colors * torch.rand(colors.shape, generator=g, dtype=colors.dtype)).sum() + (alphas**2).sum()
    if "group_alphas" in meta:
        loss = loss + (meta["group_alphas"] * torch.rand(meta["group_alphas"].shape, generator=g, dtype=colors.dtype)).sum()
    loss.backward()
    return colors.detach(), alphas.detach(), meta, [p.grad for p in leaves] + [views.grad]


def assert_close_relative(a, b, rtol):
    assert torch.isfinite(a).all() and torch.isfinite(b).all()
    assert float((a - b).norm()) <= rtol * max(float(a.norm()), 1e-30)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_cpu_depth_order_is_torchs_stable_argsort(dtype):
    """The C++ backend sorts splats front to back with a radix sort: the same indices as
    torch.argsort(stable=True) with ties (in index order), -0 and +0 equal, infinities, NaN last."""
    from manisplat.splat.backends.cpu_raster import load_extension

    order = load_extension().depth_order
    g = torch.Generator().manual_seed(3)
    ties = (torch.rand(5000, generator=g, dtype=dtype) * 20).round() / 4 - 1  # many equal depths
    spread = torch.randn(5000, generator=g, dtype=dtype) * 1e3
    special = torch.tensor([0.0, -0.0, float("inf"), float("-inf"), float("nan"), -float("nan"), 1e-40, -1e-40,
                            torch.finfo(dtype).max, torch.finfo(dtype).tiny], dtype=dtype)
    depths = torch.cat([ties, spread, special, ties[:100]])[torch.randperm(10_110, generator=g)]
    # positive quarter steps alone: their keys' low bytes are all equal (passes that sort nothing are skipped)
    for d in (depths, ties.abs(), depths[:1], depths[:0], torch.full((300,), 2.5, dtype=dtype)):
        got = order(d)
        assert got.dtype == torch.int64 and torch.equal(got, torch.argsort(d, stable=True))


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("mode", ["RGB", "RGB+D", "RGB+ED", "D"])
@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
def test_float64_images_and_gradients_match(seed, mode, rasterize_mode):
    """Antialiased, the opacities' compensation is a function of the conics: its gradient flows
    back through the C++ projection's conic gradient."""
    params, V, K, W, H = random_scene(80, seed)
    torch_out = render_and_grad("torch", params, V, K, W, H, render_mode=mode, rasterize_mode=rasterize_mode)
    cpu_out = render_and_grad("cpu", params, V, K, W, H, render_mode=mode, rasterize_mode=rasterize_mode)
    assert torch.allclose(torch_out[0], cpu_out[0], atol=1e-12, rtol=0)
    assert torch.allclose(torch_out[1], cpu_out[1], atol=1e-12, rtol=0)
    names = ["means", "quats", "scales", "opacities", "colors", "viewmats"]
    for name, a, b in zip(names, torch_out[3], cpu_out[3]):
        if name == "colors" and mode == "D":
            continue  # colours are not rendered in depth-only mode
        assert_close_relative(a, b, 1e-6), name


def test_multiple_cameras_backgrounds_sh_and_groups():
    params, _, _, W, H = random_scene(60, 5)
    views = torch.cat([camera(yaw=0.0)[0], camera(yaw=0.3)[0]])
    Ks = torch.cat([camera()[1], camera()[1]])
    sh = torch.randn(60, 16, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4)) * 0.3
    groups = torch.arange(60) % 3
    common = dict(sh_degree=3, backgrounds=torch.tensor([[0.1, 0.2, 0.3], [1.0, 1.0, 1.0]], dtype=torch.float64),
                  group_ids=groups, num_groups=3, render_mode="RGB+ED")
    p = params[:4] + [sh]
    t = render_and_grad("torch", p, views, Ks, W, H, **common)
    c = render_and_grad("cpu", p, views, Ks, W, H, **common)
    assert t[0].shape == (2, H, W, 4) and t[2]["group_alphas"].shape == (2, H, W, 3)
    assert torch.allclose(t[0], c[0], atol=1e-12) and torch.allclose(t[2]["group_alphas"], c[2]["group_alphas"], atol=1e-12)
    # the group alphas split the total alpha
    assert torch.allclose(c[2]["group_alphas"].sum(-1), c[1][..., 0], atol=1e-12)
    for a, b in zip(t[3], c[3]):
        assert_close_relative(a, b, 1e-6)


@pytest.mark.parametrize("seed", [0, 1])
def test_float32_agrees_to_rounding(seed):
    """float32: measured max image difference 2.4e-7 and gradient difference 3.4e-7 (relative)."""
    params, V, K, W, H = random_scene(200, seed, dtype=torch.float32, width=64, height=48)
    t = render_and_grad("torch", params, V, K, W, H)
    c = render_and_grad("cpu", params, V, K, W, H)
    assert float((t[0] - c[0]).abs().max()) < 2e-6
    for a, b in zip(t[3], c[3]):
        assert_close_relative(a, b, 5e-6)


@pytest.mark.parametrize("tile_size", [8, 16, 32])
@pytest.mark.parametrize("groups", [0, 6])
def test_float32_eight_pixel_rows_agree_for_every_tile_size_and_channel_count(tile_size, groups):
    """The C++ float32 path composites eight pixels of a row at once: partial tiles (a 45x37
    image), splats reaching past a tile row's end, pixels that turn opaque (300 dense splats up
    to opacity 0.98) and 3 + 6 channels must give the oracle's images and gradients."""
    params, V, K, W, H = random_scene(300, 7, dtype=torch.float32, width=45, height=37, scale=(0.02, 0.25),
                                      opacity=(0.3, 0.98))
    kwargs = dict(tile_size=tile_size, render_mode="RGB+ED")
    if groups:
        kwargs.update(group_ids=torch.arange(300) % groups, num_groups=groups)
    t = render_and_grad("torch", params, V, K, W, H, **kwargs)
    c = render_and_grad("cpu", params, V, K, W, H, **kwargs)
    assert float(t[1].amax()) > 0.999  # some pixels are opaque: compositing stopped there
    # measured: image (depth ~3) 2.1e-6, alpha 2.4e-7, gradients 2.7e-7 relative; 5-7x margin
    assert float((t[0] - c[0]).abs().max()) < 1e-5 and float((t[1] - c[1]).abs().max()) < 1e-6
    if groups:
        assert float((t[2]["group_alphas"] - c[2]["group_alphas"]).detach().abs().max()) < 1e-6
    for a, b in zip(t[3], c[3]):
        assert_close_relative(a, b, 2e-6)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
def test_gradcheck_on_a_tiny_scene(backend, rasterize_mode):
    """Finite differences on 3 Gaussians in a 10x8 image (opacities below the 0.999 clamp), about
    a pixel wide (antialiased: opacities scaled by 0.6-0.9)."""
    params, V, K, _, _ = random_scene(3, 11, width=10, height=8, scale=(0.2, 0.4), opacity=(0.3, 0.7))

    def render(means, quats, scales, opacities, colors):
        img, alpha, _ = rasterization(means, quats, scales, opacities, colors, V, K, 10, 8, backend=backend,
                                      rasterize_mode=rasterize_mode)
        return img, alpha

    inputs = tuple(p.clone().requires_grad_(True) for p in params)
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("threads", [2, 4])
def test_float32_gradients_are_the_same_on_every_call(threads):
    """The backward sums each Gaussian's gradient over tiles in threads; the sum must not depend
    on which thread took which tile (a run resumed from a checkpoint has to continue as the
    unbroken run would). Large splats reaching over many tiles, more threads than cores
    (preempted workers), calls repeated until a thread would have taken another tile."""
    params, V, K, W, H = random_scene(400, 3, dtype=torch.float32, width=160, height=120, scale=(0.05, 0.4))
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        first = render_and_grad("cpu", params, V, K, W, H, tile_size=8)[3]
        for _ in range(30):
            again = render_and_grad("cpu", params, V, K, W, H, tile_size=8)[3]
            for a, b in zip(first, again):
                assert torch.equal(a, b)
    finally:
        torch.set_num_threads(before)
