"""Tile binning shared by the backends: which 16x16 tiles each projected Gaussian touches."""

from __future__ import annotations

import torch


def tile_rects(means2d: torch.Tensor, radii: torch.Tensor, width: int, height: int, tile_size: int) -> torch.Tensor:
    """[N, 4] int64 tile ranges (x0, y0, x1, y1), end exclusive, clipped to the tile grid; empty when culled.

    A Gaussian covers the pixel box ``mean +- radius`` (pixel centres at +0.5), so it touches
    tiles ``floor((mean - r) / tile) .. ceil((mean + r) / tile) - 1``, as in gsplat.
    """
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    with torch.no_grad():
        m = means2d.detach().double()
        r = radii.double()
        x0 = torch.floor((m[:, 0] - r[:, 0]) / tile_size).clamp(0, tiles_x)
        x1 = torch.ceil((m[:, 0] + r[:, 0]) / tile_size).clamp(0, tiles_x)
        y0 = torch.floor((m[:, 1] - r[:, 1]) / tile_size).clamp(0, tiles_y)
        y1 = torch.ceil((m[:, 1] + r[:, 1]) / tile_size).clamp(0, tiles_y)
        rect = torch.stack([x0, y0, x1, y1], dim=-1).to(torch.int64)
        culled = (radii <= 0).any(dim=-1)
        rect[culled] = 0
    return rect
