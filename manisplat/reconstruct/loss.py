"""The ManiSplat loss of one training frame, as one pure tensor function.

``L = L_render + l_app * L_app + l_mask * L_mask + l_pose * L_pose``: L_render is (1 - s) L1 +
s D-SSIM on the frame; L_app the same over the dynamic pixels (robot and objects in the recorded
mask); L_mask the L1 between the dynamic nodes' rendered alpha and that mask; L_pose the object
corrections' squared SE(3) distance to the pseudo ground truth. With per-frame exposure the render
is first scaled by the frame's gains, fitted in closed form on its static pixels
(:mod:`manisplat.reconstruct.exposure`); then it is compared as the camera records it: its colour
subsampled as the recording's was (:mod:`manisplat.reconstruct.chroma`), and a render brighter
than a clipped recorded channel counting as that channel (:mod:`manisplat.reconstruct.sensor`).
:func:`frame_loss` is :func:`~manisplat.compilation.compilable`: compiled, the whole of it (and
its backward) is a few fused kernels.
"""

from __future__ import annotations

import kornia
import torch

from manisplat.compilation import compilable
from manisplat.episode.images import StoredChroma
from manisplat.reconstruct.chroma import subsample_chroma
from manisplat.reconstruct.exposure import fit_gains, relative_gains
from manisplat.reconstruct.poses import pose_penalty
from manisplat.reconstruct.sensor import as_recorded, clipped


@compilable
def frame_loss(image: torch.Tensor, dynamic_alpha: torch.Tensor, target: torch.Tensor,
               dynamic_mask: torch.Tensor | None, valid: torch.Tensor | None,
               exposure: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None, twists: list[torch.Tensor],
               weights: tuple[float, float, float, float],
               chroma: StoredChroma | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The loss of one frame and its fitted exposure gains.

    Args:
        image: [H, W, 3] render in [0, 1] (the scene, before the frame's exposure).
        dynamic_alpha: [H, W] rendered alpha of the robot and objects.
        target: [H, W, 3] uint8 recorded image.
        dynamic_mask: [H, W] bool, the recorded robot and object pixels (None: no masks; no
            appearance or mask term).
        valid: [H, W] float 0/1, the pixels the recording covers (None: all).
        exposure: (gains fitted so far [T, 3], this frame's index [] int64, each frame's weight in
            the training frames' mean [T]) or None (no exposure compensation).
        twists: [6] float64 pose corrections of the objects at this frame.
        weights: (ssim_weight, lambda_app, lambda_mask, lambda_pose).
        chroma: how the recording subsampled the colour (None: it did not, or it is not known).
    Returns (loss [] float32, this frame's gains [3] as fitted, to be kept; None without exposure).
    """
    ssim_weight, lambda_app, lambda_mask, lambda_pose = weights
    clip = clipped(target)
    target = target.float() / 255.0
    dynamic = None if dynamic_mask is None else dynamic_mask.float()
    gains = None
    if exposure is not None:
        static = None if dynamic is None else 1 - dynamic
        if valid is not None:
            static = valid if static is None else static * valid
        gains = fit_gains(image.detach(), target, static, clip)
        image = image * relative_gains(gains, *exposure)
    if chroma is not None:
        image = subsample_chroma(image, chroma)
    l1, ssim = error_maps(as_recorded(image, target, clip), target)  # computed once for the render and appearance terms
    loss = photometric(l1, ssim, valid, ssim_weight)
    if dynamic is not None:
        mask_error = (dynamic_alpha - dynamic).abs()
        if valid is not None:
            dynamic, mask_error = dynamic * valid, mask_error * valid
        # 0 in a frame without dynamic pixels (a weighted mean: nothing is read back to decide)
        loss = loss + lambda_app * photometric(l1, ssim, dynamic, ssim_weight) + lambda_mask * mask_error.mean()
    if twists:
        loss = loss + lambda_pose * sum(pose_penalty(xi) for xi in twists).float()
    return loss, gains


def error_maps(image: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel L1 [H, W] and SSIM [H, W] (11 x 11 Gaussian window, sigma 1.5) of [H, W, 3] images."""
    return (image - target).abs().mean(-1), ssim_map(image, target)


def ssim_map(x: torch.Tensor, y: torch.Tensor, window_size: int = 11) -> torch.Tensor:
    """SSIM [H, W] (channel mean) of images [H, W, C] in [0, 1], as ``kornia.metrics.ssim`` computes it
    (Gaussian window sigma 1.5, reflect padding, C1 = 0.01^2, C2 = 0.03^2, eps 1e-12), with the five
    local moments filtered in one grouped convolution: about twice as fast as kornia's five
    filters on the CPU (README, the CPU iteration), and one launch instead of ten on a GPU."""
    k = _gaussian_window(window_size, x.device, x.dtype)
    H, W, C = x.shape
    stack = torch.stack([x, y, x * x, y * y, x * y]).permute(0, 3, 1, 2).reshape(1, 5 * C, H, W)
    pad = window_size // 2
    stack = torch.nn.functional.pad(stack, (pad, pad, pad, pad), mode="reflect")
    stack = torch.nn.functional.conv2d(stack, k.view(1, 1, 1, -1).expand(5 * C, 1, 1, window_size), groups=5 * C)
    stack = torch.nn.functional.conv2d(stack, k.view(1, 1, -1, 1).expand(5 * C, 1, window_size, 1), groups=5 * C)
    mu1, mu2, xx, yy, xy = stack.view(5, C, H, W)
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    num = (2.0 * mu12 + c1) * (2.0 * (xy - mu12) + c2)
    den = (mu1_sq + mu2_sq + c1) * ((xx - mu1_sq) + (yy - mu2_sq) + c2)
    return (num / (den + 1e-12)).mean(0)


_WINDOWS: dict[tuple[int, str, torch.dtype], torch.Tensor] = {}


def _gaussian_window(size: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """[size] kornia's Gaussian window (sigma 1.5), made once per device when run eagerly (kornia
    copies sigma from the host on every call, which waits for a GPU); compiled, a constant."""
    if torch.compiler.is_compiling():
        return kornia.filters.get_gaussian_kernel1d(size, 1.5, device=device, dtype=dtype)[0]
    key = (size, str(device), dtype)
    if key not in _WINDOWS:
        _WINDOWS[key] = kornia.filters.get_gaussian_kernel1d(size, 1.5, device=device, dtype=dtype)[0]
    return _WINDOWS[key]


def photometric(l1: torch.Tensor, ssim: torch.Tensor, region: torch.Tensor | None, ssim_weight: float) -> torch.Tensor:
    """(1 - w) L1 + w (1 - SSIM) over the image, or averaged over the pixels of ``region`` [H, W]
    (float weights 0/1; 0 when it is empty), without selecting them (no synchronisation)."""
    if region is None:
        return (1 - ssim_weight) * l1.mean() + ssim_weight * (1 - ssim.mean())
    count = region.sum()
    mean_l1 = (l1 * region).sum() / count.clamp_min(1)
    mean_dssim = ((1 - ssim) * region).sum() / count.clamp_min(1)
    return (1 - ssim_weight) * mean_l1 + ssim_weight * mean_dssim
