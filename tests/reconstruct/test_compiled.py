"""The iteration's compilable tensor functions: compiled they compute what they compute eagerly,
gradients included, and a change in the number of Gaussians (densification) reuses the compiled
code instead of compiling again. On the CPU they run in the "trace" mode (Dynamo and AOTAutograd:
the graphs, guards and backward that compiling makes, without Inductor's code generation, which
takes minutes on a 2-core machine and is PyTorch's own); on CUDA, tests/reconstruct/test_device.py
and the device benchmark run Inductor's kernels."""

from __future__ import annotations

import pytest
import torch
from torch._dynamo.utils import counters

from manisplat.compilation import MODES, compilable, compilation
from manisplat.reconstruct.config import resolve_compile
from manisplat.reconstruct.loss import frame_loss
from manisplat.scene.placement import place_scene

# One worker runs this module's tests in order (`--dist loadgroup`): the placement of the same
# nodes, traced by the first, serves the second (16 s on 2 cores when each worker traced it anew).
pytestmark = pytest.mark.xdist_group("tests/reconstruct/test_compiled.py")


def _node(n: int, g: torch.Generator) -> dict[str, torch.Tensor]:
    return {"means": torch.randn(n, 3, generator=g), "quats": torch.randn(n, 4, generator=g),
            "scales": torch.randn(n, 3, generator=g) - 3, "opacities": torch.randn(n, generator=g),
            "sh0": torch.randn(n, 3, generator=g), "shN": torch.randn(n, 8, 3, generator=g) * 0.1}


def _poses(k: int, g: torch.Generator) -> torch.Tensor:
    from manisplat.geometry import se3_exp

    return se3_exp(torch.randn(k, 6, generator=g, dtype=torch.float64)).float()


def _placement_inputs(sizes: tuple[int, ...], seed: int = 0):
    """(background params, moving nodes' params, poses, index, camera centre) for place_scene."""
    g = torch.Generator().manual_seed(seed)
    background, *moving = [{k: torch.nn.Parameter(v) for k, v in _node(n, g).items()} for n in sizes]
    index = torch.repeat_interleave(torch.arange(len(moving)), torch.tensor(sizes[1:]))
    return background, moving, _poses(len(moving), g), index, torch.tensor([0.3, -0.2, 1.5])


def _bands(degree: int) -> torch.Tensor:
    """The weights of the 8 view-dependent coefficients (SH degree 2) with bands up to ``degree`` in use."""
    return (torch.arange(8) < (degree + 1) ** 2 - 1).float()


def _placed(inputs, degree: int) -> list[torch.Tensor]:
    background, moving = place_scene(*inputs, _bands(degree), _bands(degree))
    return [*background, *moving]


def _gradients(outputs, inputs) -> list[torch.Tensor]:
    weights = torch.Generator().manual_seed(7)
    loss = sum((o * torch.rand(o.shape, generator=weights)).sum() for o in outputs)
    params = [p for node in [inputs[0], *inputs[1]] for p in node.values()]
    return torch.autograd.grad(loss, params, allow_unused=True)


def test_compiled_placement_equals_eager_and_serves_any_number_of_gaussians():
    """With the view-dependent bands on: the same Gaussians and gradients as eagerly; then
    densification's new sizes (parameters included) reuse the compiled code."""
    inputs = _placement_inputs((30, 40, 5, 25))  # sizes unlike the tensors' other dimensions (3, 4, 8)
    eager = _placed(inputs, 2)
    resized = [_placement_inputs(sizes, seed=2) for sizes in ((31, 41, 12, 9), (7, 50, 6, 17), (64, 64, 64, 5))]
    with compilation("trace"):
        compiled = _placed(inputs, 2)
        compiled_graphs = counters["stats"]["unique_graphs"]
        reused = [_placed(r, 2) for r in resized]
    assert counters["stats"]["unique_graphs"] == compiled_graphs
    for a, b in zip(compiled, eager):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    for a, b in zip(_gradients(compiled, inputs), _gradients(eager, inputs)):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    for r, outputs in zip(resized, reused):  # the reused code places the new sizes right
        for a, b in zip(outputs, _placed(r, 2)):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_a_new_sh_band_changes_values_not_the_compiled_code():
    """The bands in use are weights, not a degree: raising the degree (every ``sh_every``
    iterations) reuses the compiled placement, and each degree's colours are those of its bands
    alone (the higher coefficients add exact zeros)."""
    from manisplat.splat.sh import spherical_harmonics

    inputs = _placement_inputs((20, 30, 10, 6))  # as many nodes as the test above: its compiled code serves
    with compilation("trace"):
        _placed(inputs, 0)
        compiled_graphs = counters["stats"]["unique_graphs"]
        by_degree = {degree: _placed(inputs, degree) for degree in (0, 1, 2)}
    assert counters["stats"]["unique_graphs"] == compiled_graphs
    background, centre = inputs[0], inputs[4]
    sh0, shN, means = background["sh0"], background["shN"], background["means"]
    assert torch.equal(by_degree[0][4], (0.5 + 0.28209479177387814 * sh0).clamp_min(0.0))
    for degree in (1, 2):
        coeffs = torch.cat([sh0[:, None], shN[:, : (degree + 1) ** 2 - 1]], dim=1)
        expected = (spherical_harmonics(degree, means - centre, coeffs) + 0.5).clamp_min(0.0)
        torch.testing.assert_close(by_degree[degree][4], expected, rtol=0, atol=1e-7)
    assert not torch.equal(by_degree[1][4], by_degree[2][4])


def _loss_inputs(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    H, W, T = 24, 32, 9
    image = torch.rand(H, W, 3, generator=g).requires_grad_()
    alpha = torch.rand(H, W, generator=g).requires_grad_()
    target = (torch.rand(H, W, 3, generator=g) * 255).to(torch.uint8)
    dynamic = torch.rand(H, W, generator=g) > 0.7
    valid = (torch.rand(H, W, generator=g) > 0.1).float()
    fitted = 1 + 0.1 * torch.rand(T, 3, generator=g)
    weight = torch.zeros(T)
    weight[::2] = 1 / len(weight[::2])
    exposure = (fitted, torch.arange(T)[4], weight)
    twists = [(torch.randn(6, generator=g, dtype=torch.float64) * 0.01).requires_grad_() for _ in range(2)]
    return image, alpha, target, dynamic, valid, exposure, twists, (0.2, 1.0, 1.0, 1.0)


def test_the_compiled_frame_loss_equals_eager_with_gradients_and_gains():
    inputs = _loss_inputs()
    image, alpha, *_, twists, _ = inputs
    eager, eager_gains = frame_loss(*inputs)
    with compilation("trace"):
        compiled, compiled_gains = frame_loss(*inputs)
    torch.testing.assert_close(compiled, eager, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(compiled_gains, eager_gains, rtol=1e-5, atol=1e-6)
    leaves = [image, alpha, *twists]
    for a, b in zip(torch.autograd.grad(compiled, leaves), torch.autograd.grad(eager, leaves)):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-7)


def test_the_exposure_gains_in_the_loss_are_those_fit_returns():
    """frame_loss fits the frame's gains on its static pixels and scales the render by them
    relative to the training frames' mean, as FrameExposure.fit does."""
    from manisplat.reconstruct.exposure import FrameExposure

    image, alpha, target, dynamic, valid, _, twists, weights = _loss_inputs(3)
    exposure = FrameExposure(9, list(range(0, 9, 2)))
    exposure.fitted.uniform_(0.8, 1.2)
    loss, gains = frame_loss(image, alpha, target, dynamic, valid, exposure.fit_inputs(4), twists, weights)
    used = exposure.fit(4, image, target.float() / 255, (1 - dynamic.float()) * valid)
    torch.testing.assert_close(gains, exposure.fitted[4])
    assert (used - 1).abs().max() > 0.01  # the gains do something
    reference, _ = frame_loss(image * used, alpha, target, dynamic, valid, None, twists, weights)
    torch.testing.assert_close(loss, reference, rtol=1e-6, atol=1e-7)


def test_compilation_is_off_outside_its_block_and_modes_are_checked():
    calls = []

    @compilable
    def double(x):
        calls.append(torch.compiler.is_compiling())
        return 2 * x

    assert double(torch.ones(2)).tolist() == [2.0, 2.0] and calls == [False]
    with pytest.raises(ValueError, match="unknown compilation mode"):
        with compilation("fast"):
            pass
    assert set(MODES) == {"default", "trace"}


def test_the_compile_setting_resolves_per_device_and_budget():
    from manisplat.reconstruct.config import COMPILE_MIN_ITERS

    assert resolve_compile("auto", "cuda", 30_000) == "default"
    assert resolve_compile("auto", "cuda", COMPILE_MIN_ITERS - 1) is None  # the compilation would not pay
    assert resolve_compile("auto", "cpu", 30_000) is None
    assert resolve_compile("on", "cpu", 10) == "default"
    assert resolve_compile("off", "cuda", 30_000) is None
    with pytest.raises(ValueError, match="unknown compile setting"):
        resolve_compile("yes", "cpu", 10)
