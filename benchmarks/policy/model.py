"""ACT-style action chunking with a small convolutional encoder and a regression head.

Image (3, 120, 160) -> 4 conv blocks (16-32-64-64 channels, GroupNorm, 15 x 20 at the end) ->
spatial soft-argmax (Levine et al. 2016; the diffusion policy's ResNet variant uses the same) gives
each channel's expected image position, 128 numbers that say *where* things are, which is what a
pick-and-place needs. With the normalised joint state they go through an MLP to a chunk of
``chunk`` future actions (normalised q1..q6, gripper), trained with L1 as ACT is. About 0.45 M
parameters and about 23 M multiply-adds per image: it trains in minutes on two CPU cores, where
ResNet-18 (11 M parameters, about 0.7 G multiply-adds at this size, 30x more) would not."""

from __future__ import annotations

import torch
from torch import nn


def _block(cin: int, cout: int, stride: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.GroupNorm(8, cout), nn.ReLU(inplace=True))


class SpatialSoftArgmax(nn.Module):
    """(B, C, H, W) feature maps -> (B, 2C) expected (x, y) in [-1, 1] of each channel's softmax."""

    def __init__(self) -> None:
        super().__init__()
        self.temperature = nn.Parameter(torch.ones(()))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        b, c, h, w = features.shape
        weights = torch.softmax(features.flatten(2) / self.temperature, dim=-1).view(b, c, h, w)
        xs = torch.linspace(-1.0, 1.0, w, device=features.device)
        ys = torch.linspace(-1.0, 1.0, h, device=features.device)
        x = (weights.sum(2) * xs).sum(-1)
        y = (weights.sum(3) * ys).sum(-1)
        return torch.cat([x, y], dim=1)


class ChunkPolicy(nn.Module):
    """(image, state) -> (B, chunk, 7) normalised actions.

    Args:
        chunk: actions predicted per call (16 = 1 s at 16 fps).
        state_dim, action_dim: 7 each (six joints and the gripper).
    """

    def __init__(self, chunk: int = 16, state_dim: int = 7, action_dim: int = 7, hidden: int = 512) -> None:
        super().__init__()
        self.chunk, self.action_dim = chunk, action_dim
        self.encoder = nn.Sequential(_block(3, 16, 2), _block(16, 32, 2), _block(32, 64, 2), _block(64, 64, 1),
                                     nn.Conv2d(64, 64, 1))
        self.keypoints = SpatialSoftArgmax()
        self.head = nn.Sequential(nn.Linear(128 + state_dim, hidden), nn.ReLU(inplace=True),
                                  nn.Linear(hidden, hidden), nn.ReLU(inplace=True),
                                  nn.Linear(hidden, chunk * action_dim))

    def forward(self, image: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """image: (B, 3, H, W) float in about [-2, 2]; state: (B, 7) normalised."""
        features = self.keypoints(self.encoder(image))
        return self.head(torch.cat([features, state], dim=1)).view(-1, self.chunk, self.action_dim)
