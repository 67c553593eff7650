"""The recording's chroma subsampling: a render compared with an image as the image was stored.

JPEG and most video keep an image's brightness at every pixel but its colour (Cb, Cr) once per
block of pixels: 2 x 2 in the usual 4:2:0, which ``cv2.imencode`` and so ACT / Cobot Magic HDF5
files use. Decoding interpolates the colour back, so a colour edge in a recording is blurred over
about two pixels, and a small object seen from a metre away is a few blocks wide. On the
simulated Cobot Magic recordings the simulator's own renders of the recorded states, before the
recorder's JPEG, score 25.7 / 23.8 dB in the head camera's object region against the recording,
33.3 / 32.9 with their colour subsampled as here (``python -m benchmarks sim_shadow_map``). A
twin that draws the colours sharply, as a wrist camera a few centimetres away shows them, is
trained and scored against that blur unless its render is subsampled the same way before the
comparison; this module does that. The twin keeps its full colour: new images are encoded by
whatever writes them.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from manisplat.compilation import constant_tensor
from manisplat.episode.images import StoredChroma

#: full-range BT.601 RGB -> YCbCr as JPEG (JFIF) defines it, without the 0.5 offset of Cb and Cr,
#: which cancels, and its inverse
_RGB_TO_YCBCR = ((0.299, 0.587, 0.114), (-0.168736, -0.331264, 0.5), (0.5, -0.418688, -0.081312))
_YCBCR_TO_RGB = ((1.0, 0.0, 1.402), (1.0, -0.344136, -0.714136), (1.0, 1.772, 0.0))


def subsampled(stored: StoredChroma | None) -> StoredChroma | None:
    """``stored`` where it subsamples the colour, None where it keeps every pixel's (4:4:4) or
    nothing is known (None)."""
    return None if stored is None or stored.block == (1, 1) else stored


def subsample_chroma(image: torch.Tensor, stored: StoredChroma) -> torch.Tensor:
    """``image`` [H, W, 3] (RGB, any scale) with its colour kept as ``stored`` kept it: the
    chroma averaged over each block of pixels and interpolated back, as a JPEG decoder does
    (libjpeg's "fancy" upsampling: linear between the blocks' centres), in the colour space the
    encoder saw (red and blue swapped when it took RGB for BGR). Differentiable; the encoder's
    brightness is unchanged."""
    if stored.red_blue_swapped:
        image = image.flip(-1)
    h, w = image.shape[:2]
    ycbcr = image @ constant_tensor(_RGB_TO_YCBCR, image.dtype, image.device).T
    chroma = ycbcr[..., 1:].permute(2, 0, 1)[None]  # [1, 2, H, W]
    bx, by = stored.block
    coarse = F.avg_pool2d(chroma, (by, bx), ceil_mode=True)
    fine = F.interpolate(coarse, scale_factor=(by, bx), mode="bilinear", align_corners=False)[..., :h, :w]
    ycbcr = torch.cat([ycbcr[..., :1], fine[0].permute(1, 2, 0)], dim=-1)
    rgb = ycbcr @ constant_tensor(_YCBCR_TO_RGB, image.dtype, image.device).T
    return rgb.flip(-1) if stored.red_blue_swapped else rgb


__all__ = ["subsample_chroma", "subsampled"]
