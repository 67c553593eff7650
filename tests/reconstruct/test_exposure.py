"""Per-frame exposure and white balance: per-channel gains fitted on training frames' static
pixels, interpolated in time for held-out frames (which teach them nothing)."""

from __future__ import annotations

import pytest
import torch

from manisplat.reconstruct.exposure import RIDGE, FrameExposure


def test_held_out_frames_take_the_gains_interpolated_between_their_training_neighbours():
    exposure = FrameExposure(10, [1, 3, 4, 8])
    for f in (1, 3, 4, 8):
        exposure.fitted[f] = float(f)
    expected = {0: 1.0, 1: 1.0, 2: 2.0, 3: 3.0, 5: 5.0, 6: 6.0, 7: 7.0, 8: 8.0, 9: 8.0}
    mean = (1 + 3 + 4 + 8) / 4  # gains are relative to the training frames' mean
    for frame, value in expected.items():
        assert torch.allclose(exposure.gains_of(frame), torch.full((3,), value / mean)), frame
    assert exposure.gains()[6].tolist() == [6.0 / mean] * 3


def test_a_frame_s_gains_are_fitted_on_its_static_pixels():
    """The recording is the render with a warm cast and 8 % more light, except where the robot is
    (whose render is still wrong): the gains come from the static pixels only."""
    g = torch.Generator().manual_seed(0)
    render = torch.rand(32, 32, 3, generator=g) * 0.8 + 0.1
    gains = torch.tensor([1.08 * 1.03, 1.08, 1.08 * 0.97])
    recorded = render * gains
    robot = torch.zeros(32, 32)
    robot[8:20, 8:20] = 1
    recorded[robot.bool()] = torch.rand(144, 3, generator=g)  # the robot moved: nothing to fit there
    exposure = FrameExposure(4, [0, 2])
    used = exposure.fit(2, render, recorded, 1 - robot)
    fitted = exposure.fitted[2]
    # the ridge pulls towards 1 by RIDGE / (E[render^2] + RIDGE) of the deviation: 3.5 % of 0.11 here
    assert torch.allclose(fitted, gains, atol=0.005)
    assert (exposure.fitted[[0, 1, 3]] == 1).all()
    assert torch.allclose(used, fitted / ((1 + fitted) / 2))  # relative to the training frames' mean
    unmasked = FrameExposure(4, [0, 2])
    unmasked.fit(2, render, recorded, None)
    assert (unmasked.fitted[2] - gains).abs().max() > 3 * (fitted - gains).abs().max()


def test_the_fit_does_not_differentiate_the_render():
    render = torch.full((4, 4, 3), 0.5, requires_grad=True)
    exposure = FrameExposure(2, [0])
    gains = exposure.fit(0, render, torch.full((4, 4, 3), 0.6), None)
    assert not gains.requires_grad
    assert exposure.fitted[0].tolist() == pytest.approx([(0.3 + RIDGE) / (0.25 + RIDGE)] * 3)
    assert gains.tolist() == pytest.approx([1.0] * 3)  # one training frame: it is the mean
