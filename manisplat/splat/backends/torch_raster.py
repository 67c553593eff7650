"""The reference backend: pure PyTorch with autograd. Slow but simple; the oracle in tests.

Gaussians are binned into tiles and sorted by depth; tiles are processed in chunks as padded
[tiles, pixels, splats] tensors. Transmittance is an exclusive cumulative product of (1 - alpha)
over each pixel's depth-ordered list, and a splat contributes only while the inclusive product
stays above 1e-4, which is gsplat's early stop written without a loop.
"""

from __future__ import annotations

import torch

from manisplat.splat.backends.tiles import tile_rects
from manisplat.splat.projection import ALPHA_THRESHOLD

MAX_ALPHA = 0.999
MIN_TRANSMITTANCE = 1e-4
CHUNK_ELEMENTS = 4_000_000  # tiles x pixels x splats per chunk (memory bound)


def _pairs(rect: torch.Tensor, order: torch.Tensor, tiles_x: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(tile id [M], gaussian id [M]) of every overlap, grouped by tile, depth-ordered within one."""
    r = rect[order]
    wx, wy = r[:, 2] - r[:, 0], r[:, 3] - r[:, 1]
    counts = (wx * wy).clamp_min(0)
    gauss = torch.repeat_interleave(order, counts)
    if gauss.numel() == 0:
        return gauss, gauss
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(gauss.numel(), device=rect.device) - torch.repeat_interleave(first, counts)
    rg = torch.repeat_interleave(torch.arange(len(order), device=rect.device), counts)
    tx = r[rg, 0] + local % wx[rg]
    ty = r[rg, 1] + local // wx[rg]
    tile = ty * tiles_x + tx
    tile_sorted, perm = torch.sort(tile, stable=True)
    return tile_sorted, gauss[perm]


def composite(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    depths: torch.Tensor,
    radii: torch.Tensor,
    width: int,
    height: int,
    tile_size: int = 16,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Image [H, W, D] and alpha [H, W] of one camera's projected Gaussians (autograd throughout)."""
    D = colors.shape[-1]
    dtype, device = colors.dtype, colors.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    image = torch.zeros(tiles_x * tiles_y, tile_size * tile_size, D, dtype=dtype, device=device)
    alpha = torch.zeros(tiles_x * tiles_y, tile_size * tile_size, dtype=dtype, device=device)

    order = torch.argsort(depths.detach(), stable=True)
    tile, gauss = _pairs(tile_rects(means2d, radii, width, height, tile_size), order, tiles_x)
    if tile.numel():
        used, counts = torch.unique_consecutive(tile, return_counts=True)
        starts = torch.cumsum(counts, 0) - counts
        pix = torch.arange(tile_size * tile_size, device=device)
        local_xy = torch.stack([pix % tile_size, pix // tile_size], -1).to(dtype) + 0.5  # [P, 2]
        i = 0
        while i < len(used):
            # grow the chunk while it fits the memory budget
            j, kmax = i + 1, int(counts[i])
            while j < len(used) and (j - i + 1) * tile_size**2 * max(kmax, int(counts[j])) <= CHUNK_ELEMENTS:
                kmax = max(kmax, int(counts[j]))
                j += 1
            image_c, alpha_c = _chunk(
                used[i:j], starts[i:j], counts[i:j], kmax, gauss, local_xy, tiles_x, tile_size,
                means2d, conics, opacities, colors,
            )
            image = image.index_put((used[i:j],), image_c)
            alpha = alpha.index_put((used[i:j],), alpha_c)
            i = j
    else:
        # nothing visible: keep the output attached to the inputs so backward() gives zeros, not an error
        attach = sum(t.sum() for t in (means2d, conics, opacities, colors)) * 0.0
        image, alpha = image + attach, alpha + attach
    image = image.reshape(tiles_y, tiles_x, tile_size, tile_size, D).permute(0, 2, 1, 3, 4)
    alpha = alpha.reshape(tiles_y, tiles_x, tile_size, tile_size).permute(0, 2, 1, 3)
    image = image.reshape(tiles_y * tile_size, tiles_x * tile_size, D)[:height, :width]
    alpha = alpha.reshape(tiles_y * tile_size, tiles_x * tile_size)[:height, :width]
    return image, alpha


def _chunk(tiles, starts, counts, kmax, gauss, local_xy, tiles_x, tile_size, means2d, conics, opacities, colors):
    """Composite a chunk of tiles: returns ([T, P, D], [T, P])."""
    k = torch.arange(kmax, device=tiles.device)
    present = k[None, :] < counts[:, None]  # [T, K]
    ids = gauss[(starts[:, None] + k[None, :]).clamp(max=gauss.numel() - 1)]  # [T, K]
    origin = torch.stack([tiles % tiles_x, tiles // tiles_x], -1).to(local_xy.dtype) * tile_size  # [T, 2]
    pixels = origin[:, None, :] + local_xy[None]  # [T, P, 2]
    d = means2d[ids][:, None, :, :] - pixels[:, :, None, :]  # [T, P, K, 2]
    con = conics[ids][:, None]  # [T, 1, K, 3]
    sigma = 0.5 * (con[..., 0] * d[..., 0] ** 2 + con[..., 2] * d[..., 1] ** 2) + con[..., 1] * d[..., 0] * d[..., 1]
    a = torch.clamp(opacities[ids][:, None, :] * torch.exp(-sigma), max=MAX_ALPHA)  # [T, P, K]
    use = present[:, None, :] & (sigma >= 0) & (a >= ALPHA_THRESHOLD)
    a = torch.where(use, a, torch.zeros_like(a))
    T_incl = torch.cumprod(1.0 - a, dim=-1)
    T_excl = torch.cat([torch.ones_like(T_incl[..., :1]), T_incl[..., :-1]], dim=-1)
    weight = a * T_excl * (T_incl > MIN_TRANSMITTANCE)
    image = (weight[..., None] * colors[ids][:, None]).sum(dim=2)  # [T, P, D]
    return image, weight.sum(dim=-1)
