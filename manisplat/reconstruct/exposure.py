"""Per-frame exposure and white-balance compensation: an affine colour transform per frame,
``c' = (I + A_f) c + b_f``, applied to the rendered image before it is compared with frame f.

Auto-exposure and white balance change a real camera's gain from frame to frame; without this
the Gaussians' colours would flicker to follow it, or average it away and lose PSNR everywhere.
The transforms are regularised towards identity (``strength * mean((A_f, b_f)^2)``), which also
fixes the gauge between them and the Gaussians' own colours. Only training frames are learned.
A held-out frame takes the transform interpolated in time between the training frames beside it
(exposure drifts smoothly), so no pixel of a held-out frame reaches it. The twin itself (renders of
new states, augmentation) uses the identity: the scene's own colours.
"""

from __future__ import annotations

import numpy as np
import torch


class FrameColour(torch.nn.Module):
    """Affine colour transforms of ``n_frames`` frames, learned on ``train_frames``.

    Attributes:
        delta: [T, 3, 4] float32 parameter, (A_f | b_f), zero at the start (identity).
    """

    def __init__(self, n_frames: int, train_frames: list[int], device: torch.device | str = "cpu") -> None:
        super().__init__()
        if not train_frames:
            raise ValueError("per-frame colour needs at least one training frame")
        self.delta = torch.nn.Parameter(torch.zeros(n_frames, 3, 4, device=device))
        lower, upper, weight = _interpolation(n_frames, sorted(train_frames))
        self.register_buffer("_lower", torch.as_tensor(lower, device=device))
        self.register_buffer("_upper", torch.as_tensor(upper, device=device))
        self.register_buffer("_weight", torch.as_tensor(weight, dtype=torch.float32, device=device))

    def transform(self, frame: int) -> torch.Tensor:
        """[3, 4] (A_f | b_f) of ``frame``: learned for a training frame, interpolated otherwise."""
        w = self._weight[frame]
        return (1 - w) * self.delta[self._lower[frame]] + w * self.delta[self._upper[frame]]

    def apply(self, image: torch.Tensor, frame: int) -> torch.Tensor:
        """[H, W, 3] image as frame ``frame``'s camera saw it."""
        d = self.transform(frame)
        return image + image @ d[:, :3].T + d[:, 3]

    def penalty(self, frame: int) -> torch.Tensor:
        """Mean square of frame ``frame``'s transform away from identity (scalar)."""
        return self.delta[frame].square().mean()

    def gains(self) -> np.ndarray:
        """[T, 3] per-channel gain (diagonal of I + A_f) of every frame, held-out ones interpolated."""
        with torch.no_grad():
            d = torch.stack([self.transform(f) for f in range(len(self.delta))])
            return (1 + torch.diagonal(d[:, :, :3], dim1=1, dim2=2)).cpu().numpy().astype(np.float64)


def _interpolation(n: int, train: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every frame the training frames before and after it and the weight of the later one
    (training frames: themselves, weight 0; before the first / after the last: the nearest)."""
    train_arr = np.asarray(train)
    frames = np.arange(n)
    after = np.clip(np.searchsorted(train_arr, frames), 0, len(train_arr) - 1)
    before = np.clip(after - 1, 0, len(train_arr) - 1)
    exact = train_arr[after] == frames
    before = np.where(exact, after, before)
    lo, hi = train_arr[before], train_arr[after]
    span = np.maximum(hi - lo, 1)
    weight = np.where(hi > lo, np.clip((frames - lo) / span, 0.0, 1.0), 0.0)
    weight = np.where(frames > hi, 0.0, weight)
    lo = np.where(frames > hi, hi, lo)
    return lo.astype(np.int64), hi.astype(np.int64), weight


__all__ = ["FrameColour"]
