"""The sensor's white level: a clipped recorded channel says only "at least white"; the loss and
the exposure fit read it so, and a surface brighter than white keeps its true colour (and its
shadow its true strength)."""

from __future__ import annotations

import pytest
import torch

from manisplat.reconstruct.exposure import fit_gains
from manisplat.reconstruct.loss import frame_loss
from manisplat.reconstruct.sensor import WHITE_LEVEL, as_recorded, clipped

WEIGHTS = (0.0, 0.0, 0.0, 0.0)  # plain L1 over the frame


def test_clipped_channels_are_those_at_the_white_level_in_either_encoding():
    recorded = torch.tensor([[[WHITE_LEVEL - 1, WHITE_LEVEL, 255]]], dtype=torch.uint8)
    assert clipped(recorded).tolist() == [[[False, True, True]]]
    assert clipped(recorded.float() / 255.0).tolist() == [[[False, True, True]]]


def test_a_render_brighter_than_a_clipped_channel_costs_nothing_and_a_darker_one_its_error():
    target = torch.tensor([[[1.0, 1.0, 0.5]]])
    clip = clipped(target)
    image = torch.tensor([[[1.3, 0.8, 0.7]]], requires_grad=True)
    recorded = as_recorded(image, target, clip)
    assert recorded.flatten().tolist() == pytest.approx([1.0, 0.8, 0.7])
    (recorded - target).abs().sum().backward()
    # brighter than clipped white: no gradient; darker than it: pulled up; an unclipped channel
    # brighter than its recording: pulled down
    assert image.grad.tolist() == [[[0.0, -1.0, 1.0]]]


def test_the_loss_ignores_how_far_above_a_clipped_recording_the_render_is():
    target = torch.full((12, 12, 3), 255, dtype=torch.uint8)
    target[..., 2] = 128
    image = torch.full((12, 12, 3), 1.4)
    image[..., 2] = 128 / 255
    loss, _ = frame_loss(image, torch.zeros(12, 12), target, None, None, None, [], WEIGHTS)
    assert float(loss) == pytest.approx(0.0, abs=1e-7)
    image[..., 2] = 0.9  # the unclipped channel still counts
    loss, _ = frame_loss(image, torch.zeros(12, 12), target, None, None, None, [], WEIGHTS)
    assert float(loss) == pytest.approx((0.9 - 128 / 255) / 3, rel=1e-4)


def test_a_surface_brighter_than_white_learns_its_colour_from_its_shadowed_frames():
    """A table at 1.25 x white when lit (recorded clipped at 255), 0.75 in shadow (strength 0.4):
    fitted as the sensor records it, its colour goes to 1.25, so that the shadow darkens it to
    what was recorded; read as exact, the lit frames pull it towards 1 (too dark a shadow
    wherever a new state puts one on it)."""
    strength, albedo = 0.4, 1.25
    lit = torch.full((12, 12, 3), 255, dtype=torch.uint8)
    shade = torch.full((12, 12, 3), round(albedo * (1 - strength) * 255), dtype=torch.uint8)
    colour = torch.nn.Parameter(torch.full((3,), 0.9))
    optimiser = torch.optim.Adam([colour], lr=0.01)
    for step in range(600):
        shadowed = step % 2 == 1
        image = (colour * (1 - strength if shadowed else 1.0)).expand(12, 12, 3)
        loss, _ = frame_loss(image, torch.zeros(12, 12), shade if shadowed else lit, None, None, None, [], WEIGHTS)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    assert colour.detach().tolist() == pytest.approx([albedo] * 3, abs=0.02)


def test_exposure_gains_are_fitted_on_the_channels_the_sensor_did_not_clip():
    """The recording is the render 10 % brighter, clipped at white: a third of the red channel
    is white. Fitted on every pixel, the gain comes out low; without the clipped channels, right."""
    g = torch.Generator().manual_seed(0)
    render = torch.rand(32, 32, 3, generator=g) * 0.8 + 0.2
    render[..., 0] += 0.4 * (torch.rand(32, 32, generator=g) > 0.66)  # a bright, red surface
    recorded = ((render * 1.1).clamp(0, 1) * 255).round() / 255
    assert clipped(recorded)[..., 0].float().mean() > 0.25
    gains = fit_gains(render, recorded, None)
    assert gains.tolist() == pytest.approx([1.1] * 3, abs=0.01)
    rt, rr = (render * recorded).sum((0, 1)), (render * render).sum((0, 1))
    naive = rt[0] / rr[0]  # what every pixel would give, without the ridge
    assert float(naive) < 1.06
    # the clipped channels as the loss already has them: the same fit; none declared clipped: the low one
    assert torch.equal(fit_gains(render, recorded, None, clipped(recorded)), gains)
    assert float(fit_gains(render, recorded, None, torch.zeros_like(recorded, dtype=torch.bool))[0]) < 1.06
