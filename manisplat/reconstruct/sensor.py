"""The camera's white level: a recorded channel at it says only that the light reached it.

A sensor clips: every surface brighter than its white level is recorded as white. On the simulated
pick-and-places a quarter of the pixels have a clipped red channel (46 % of the Cobot Magic table
in the head camera), and real cameras clip bright tables and white objects under auto-exposure
as well. Fitted against the clipped values as if they were exact, a bright surface's colour is
pulled down to white, and its shadow, recorded unclipped, then looks weaker than it is: the
learned shadow strength drops, and the colours absorb what the weak shadow leaves. Here a render
brighter than a clipped recording counts as the recorded value (no error, no gradient), a darker
one keeps its error, and the exposure gains are fitted on unclipped channels only; the colour
behind a clipped channel is learned from its other frames (in shadow, at another exposure).
A twin's render is clipped to [0, 1] like the recording.
"""

from __future__ import annotations

import torch

#: 8-bit value at and above which a recorded channel counts as clipped: JPEG's ringing leaves a
#: clipped region a few values under 255
WHITE_LEVEL = 250


def clipped(target: torch.Tensor) -> torch.Tensor:
    """[..., 3] bool: the channels of a recorded image (uint8, or float in [0, 1]) at the white level."""
    if target.dtype == torch.uint8:
        return target >= WHITE_LEVEL
    return target >= (WHITE_LEVEL - 0.5) / 255.0


def as_recorded(image: torch.Tensor, target: torch.Tensor, clip: torch.Tensor) -> torch.Tensor:
    """The render [H, W, 3] as the sensor would record it against ``target`` [H, W, 3] (float in
    [0, 1]) whose clipped channels are ``clip`` [H, W, 3] bool: where a channel is clipped, a
    brighter render is the recorded value (no error, no gradient); elsewhere it is unchanged."""
    return torch.where(clip, torch.minimum(image, target), image)


__all__ = ["WHITE_LEVEL", "as_recorded", "clipped"]
