"""The colour-fitted held-out score (``psnr_colour_fitted``): an exposure change is undone, and a
background of few colours cannot recolour an object of another colour."""

from __future__ import annotations

import torch

from manisplat.reconstruct.metrics import psnr
from manisplat.reconstruct.outputs import colour_fitted


def _scene(seed: int, palette: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """An image [48, 64, 3] of static pixels drawn from ``palette`` [P, 3] with shading, and the
    mask [48, 64] of a red object in its middle."""
    g = torch.Generator().manual_seed(seed)
    pick = torch.randint(len(palette), (48, 64), generator=g)
    shade = 0.8 + 0.2 * torch.rand(48, 64, 1, generator=g)
    image = (palette[pick] * shade).clamp(0, 1)
    obj = torch.zeros(48, 64, dtype=torch.bool)
    obj[16:32, 24:40] = True
    image[obj] = torch.tensor([0.78, 0.24, 0.2])
    return image, obj


def test_an_exposure_change_is_undone_on_every_region():
    rich = torch.rand(12, 3, generator=torch.Generator().manual_seed(1)) * 0.8 + 0.1
    render, obj = _scene(0, rich)
    gains, offset = torch.tensor([1.15, 1.05, 0.92]), torch.tensor([0.01, -0.01, 0.02])
    recorded = (render * gains + offset).clamp(0, 1)
    fitted = colour_fitted(render, recorded, ~obj)
    assert psnr(render, recorded, obj) < 25
    assert psnr(fitted, recorded, obj) > 40 and psnr(fitted, recorded, ~obj) > 40


def test_a_background_of_few_colours_does_not_recolour_the_object():
    """Table browns and a grey wall span one plane of colours: along the rest, the least squares
    is free and turned the sample's red box 12 dB worse than the raw render (29.96 -> 18.12 dB)."""
    few = torch.tensor([[0.70, 0.59, 0.44], [0.59, 0.49, 0.35], [0.78, 0.80, 0.84]])
    render, obj = _scene(2, few)
    recorded = render.clone()
    recorded[~obj] = (recorded[~obj] * 1.03 + 0.004 * torch.randn(int((~obj).sum()), 3,
                                                                   generator=torch.Generator().manual_seed(3))).clamp(0, 1)
    recorded[obj] = (render[obj] + 0.02).clamp(0, 1)  # the twin's object error: 0.02 in every channel
    raw = psnr(render, recorded, obj)
    assert psnr(colour_fitted(render, recorded, ~obj), recorded, obj) > raw - 1.0
