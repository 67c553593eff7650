"""Per-frame exposure and white balance: learned on training frames, interpolated in time for
held-out frames (which teach it nothing)."""

from __future__ import annotations

import torch

from manisplat.reconstruct.exposure import FrameColour


def test_held_out_frames_take_the_transform_interpolated_between_their_training_neighbours():
    colour = FrameColour(10, [1, 3, 4, 8])
    with torch.no_grad():
        for f in (1, 3, 4, 8):
            colour.delta[f] = float(f)
    expected = {0: 1.0, 1: 1.0, 2: 2.0, 3: 3.0, 5: 5.0, 6: 6.0, 7: 7.0, 8: 8.0, 9: 8.0}
    for frame, value in expected.items():
        assert torch.allclose(colour.transform(frame), torch.full((3, 4), value)), frame


def test_a_drifting_gain_is_learned_and_carried_to_held_out_frames():
    """Frames seen with gains 0.9..1.1 and a blue cast: the learned transforms reproduce them, on the
    training frames and (interpolated) on the held-out ones, with identity as the anchor."""
    g = torch.Generator().manual_seed(0)
    scene = torch.rand(16, 16, 3, generator=g) * 0.8
    n, train = 9, [0, 2, 4, 6, 8]
    gains = torch.linspace(0.9, 1.1, n)
    seen = [(scene * gains[f] * torch.tensor([1.0, 1.0, 1.05])).clamp(0, 1) for f in range(n)]
    colour = FrameColour(n, train)
    opt = torch.optim.Adam(colour.parameters(), lr=1e-2)
    for step in range(600):
        f = train[step % len(train)]
        loss = (colour.apply(scene, f) - seen[f]).abs().mean() + 1e-4 * colour.penalty(f)
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        for f in range(n):
            error = (colour.apply(scene, f) - seen[f]).abs().mean()
            assert error < 0.01, (f, float(error))  # 8-bit: 2.5 levels
        assert not colour.delta[[1, 3, 5, 7]].any()  # held-out frames: never trained
        gain = colour.gains()
        assert abs(gain[3, 0] - float(gains[3])) < 0.02 and abs(gain[3, 2] - 1.05 * float(gains[3])) < 0.03
