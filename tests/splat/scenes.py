"""Small random Gaussian scenes for rasterizer tests."""

from __future__ import annotations

import math

import torch


def random_scene(n: int, seed: int, *, dtype=torch.float64, width: int = 40, height: int = 30, colors: int = 3,
                 scale: tuple[float, float] = (0.01, 0.16), opacity: tuple[float, float] = (0.05, 0.95)):
    """Gaussians in front of one camera at z = 3 looking along +z; returns (params, viewmats, Ks, W, H).

    params = [means [n, 3], quats [n, 4] (not unit), scales [n, 3], opacities [n], colors [n, D]].
    """
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * torch.tensor([2.0, 1.5, 1.0], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = scale[0] + torch.rand(n, 3, generator=g, dtype=dtype) * (scale[1] - scale[0])
    opacities = opacity[0] + torch.rand(n, generator=g, dtype=dtype) * (opacity[1] - opacity[0])
    cols = torch.rand(n, colors, generator=g, dtype=dtype)
    return [means, quats, scales, opacities, cols], camera(dtype, width, height)[0], camera(dtype, width, height)[1], width, height


def camera(dtype=torch.float64, width: int = 40, height: int = 30, distance: float = 3.0, yaw: float = 0.0):
    """(viewmats [1, 4, 4], Ks [1, 3, 3]) of a camera at z = -distance (rotated by ``yaw`` about y)."""
    c, s = math.cos(yaw), math.sin(yaw)
    view = torch.tensor([[c, 0, -s, 0], [0, 1, 0, 0], [s, 0, c, distance], [0, 0, 0, 1]], dtype=dtype)
    f = 1.25 * width
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=dtype)
    return view[None], K[None]
