"""Per-frame exposure and white-balance compensation: a gain per colour channel and frame,
``c' = g_f * c``, applied to the rendered image before it is compared with frame f.

Auto-exposure and white balance scale a camera's channels from frame to frame (gains in linear
light stay gains after the sRGB curve); without this the Gaussians' colours would flicker to
follow them, or average them away and lose PSNR everywhere. A training frame's gains are fitted in
closed form each time it is trained, on its static pixels (the moving robot and objects are what
is being learned), by least squares with a ridge towards 1 (:data:`RIDGE`). The gains used are
relative to their mean over the training frames, which fixes the gauge between them and the
Gaussians' own colours: the Gaussians learn the scene under the episode's mean exposure (with the
raw gains they drifted 2-6 % darker on the clean shared pick-and-place, and a new state rendered
at gain 1 came out too dark). A held-out frame takes the gains interpolated in time between the
training frames beside it, so no pixel of a held-out frame reaches them. The twin itself
(renders of new states, augmentation) uses gain 1.

A first version learned a 3 x 4 affine transform per frame by gradient descent: on the
oak-preset copy of the shared pick-and-place (1000 iterations, each frame trained about ten
times) its brightness followed the true gains with a correlation of 0.72 against 0.91 for the
closed form, and held-out PSNR was 29.8 dB against 32.2 (measured while developing, not kept as a
benchmark).
"""

from __future__ import annotations

import numpy as np
import torch

from manisplat.reconstruct.sensor import clipped

#: weight of the prior gain 1 against the frame's pixels (per pixel, in the normal equations)
RIDGE = 0.01


class FrameExposure:
    """Per-channel gains of ``n_frames`` frames, fitted on ``train_frames``.

    Attributes:
        fitted: [T, 3] float32 gains as last fitted, before normalisation (1 where never fitted).
    """

    def __init__(self, n_frames: int, train_frames: list[int], device: torch.device | str = "cpu") -> None:
        if not train_frames:
            raise ValueError("per-frame exposure needs at least one training frame")
        self.fitted = torch.ones(n_frames, 3, device=device)
        lower, upper, weight = _interpolation(n_frames, sorted(train_frames))
        self._lower = torch.as_tensor(lower, device=device)
        self._upper = torch.as_tensor(upper, device=device)
        self._weight = torch.as_tensor(weight, dtype=torch.float32, device=device)[:, None]
        self._train = torch.as_tensor(sorted(train_frames), device=device)
        self._frames = torch.arange(n_frames, device=device)
        self._train_weight = torch.zeros(n_frames, device=device)
        self._train_weight[self._train] = 1.0 / len(self._train)

    def to(self, device: torch.device | str) -> "FrameExposure":
        for name in ("fitted", "_lower", "_upper", "_weight", "_train", "_frames", "_train_weight"):
            setattr(self, name, getattr(self, name).to(device))
        return self

    def fit(self, frame: int, render: torch.Tensor, target: torch.Tensor, region: torch.Tensor | None) -> torch.Tensor:
        """Fit and keep frame ``frame``'s gains from a render and the recorded image [H, W, 3] over
        ``region`` [H, W] (0/1 weights; None: every pixel); return them normalised [3]
        (:meth:`gains_of`). The render is not differentiated."""
        gains = fit_gains(render.detach(), target, region)
        self.keep(frame, gains)
        return gains / self._mean()

    def keep(self, frame: int, gains: torch.Tensor) -> None:
        """Keep ``gains`` [3] (as :func:`fit_gains` fitted them) as frame ``frame``'s."""
        self.fitted[frame] = gains

    def fit_inputs(self, frame: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """What :func:`relative_gains` needs for training frame ``frame``: (the gains fitted so far
        [T, 3], the frame's index [] int64, each frame's weight in the training frames' mean [T]),
        without a host-to-device copy."""
        return self.fitted, self._frames[frame], self._train_weight

    def gains_of(self, frame: int) -> torch.Tensor:
        """[3] gains of ``frame`` relative to the training frames' mean: as fitted for a training
        frame, interpolated otherwise."""
        w = self._weight[frame]
        return ((1 - w) * self.fitted[self._lower[frame]] + w * self.fitted[self._upper[frame]]) / self._mean()

    def gains(self) -> np.ndarray:
        """[T, 3] gains of every frame (held-out ones interpolated) relative to the training
        frames' mean, float64."""
        w = self._weight
        both = ((1 - w) * self.fitted[self._lower] + w * self.fitted[self._upper]) / self._mean()
        return both.cpu().numpy().astype(np.float64)

    def _mean(self) -> torch.Tensor:
        """[3] mean fitted gain over the training frames (the gauge)."""
        return self.fitted[self._train].mean(0)


def fit_gains(render: torch.Tensor, target: torch.Tensor, region: torch.Tensor | None,
              clip: torch.Tensor | None = None) -> torch.Tensor:
    """[3] the gains that best map ``render`` onto ``target`` ([H, W, 3], float in [0, 1]) over
    ``region`` [H, W] (0/1 weights; None: every pixel), by least squares with a ridge of
    :data:`RIDGE` towards 1. A channel the sensor clipped (``clip`` [H, W, 3] bool, where the
    caller has it; else :func:`~manisplat.reconstruct.sensor.clipped` of ``target``) is left out
    of its channel's fit: its recorded value is not its brightness."""
    w = torch.ones_like(render[..., 0]) if region is None else region
    w = w[..., None] * (~(clipped(target) if clip is None else clip)).to(render.dtype)  # [H, W, 3]
    count = w.sum((0, 1)).clamp_min(1.0)
    rt = (render * target * w).sum((0, 1))
    rr = (render * render * w).sum((0, 1))
    return (rt + RIDGE * count) / (rr + RIDGE * count)


def relative_gains(gains: torch.Tensor, fitted: torch.Tensor, frame: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """[3] a training frame's new ``gains`` relative to the training frames' mean with them in
    place of the frame's old ones (``fitted`` [T, 3], ``frame`` [] its index, ``weight`` [T]
    each frame's share of the mean): what :meth:`FrameExposure.fit` returns, as tensor algebra."""
    this = torch.arange(len(fitted), device=fitted.device) == frame
    updated = torch.where(this[:, None], gains, fitted)
    return gains / (weight[:, None] * updated).sum(0)


def _interpolation(n: int, train: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every frame the training frames before and after it and the weight of the later one
    (training frames: themselves, weight 0; before the first / after the last: the nearest)."""
    train_arr = np.asarray(train)
    frames = np.arange(n)
    after = np.clip(np.searchsorted(train_arr, frames), 0, len(train_arr) - 1)
    before = np.clip(after - 1, 0, len(train_arr) - 1)
    before = np.where(train_arr[after] == frames, after, before)
    lo, hi = train_arr[before], train_arr[after]
    weight = np.where(hi > lo, np.clip((frames - lo) / np.maximum(hi - lo, 1), 0.0, 1.0), 0.0)
    weight = np.where(frames > hi, 0.0, weight)
    lo = np.where(frames > hi, hi, lo)
    return lo.astype(np.int64), hi.astype(np.int64), weight


__all__ = ["FrameExposure", "RIDGE", "fit_gains", "relative_gains"]
