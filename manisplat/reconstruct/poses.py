"""Trainable object trajectories around the pseudo ground truth.

``T_obj(t) = T_pseudo(t) @ exp(xi_k(t))`` with a correction twist ``xi`` (object frame): one shared
by every frame of a static stretch (an object at rest has one pose), one per frame where it moves.
The pose loss is the squared SE(3) distance to the pseudo pose in units of ``sigma_t`` and
``sigma_r``. Held-out frames are never rendered in training, so their corrections are
interpolated from the nearest trained frames of the same stretch.
"""

from __future__ import annotations

import numpy as np
import torch

from manisplat.align.pseudo_gt import STATIC
from manisplat.geometry import se3_exp

SIGMA_T = 0.01  # m
SIGMA_R = 0.05  # rad (about 3 deg)


class ObjectTrajectory(torch.nn.Module):
    """Per-frame object poses: pseudo poses [T, 4, 4] plus trainable twists.

    Args:
        pseudo: T_base_obj [T, 4, 4] (float64).
        source: per frame "static", "attached" or "tracked"; consecutive static frames share a twist.
        static: the object never moves: one twist for the whole episode.
    """

    def __init__(self, pseudo: np.ndarray, source: list[str], *, static: bool = False) -> None:
        super().__init__()
        T = len(pseudo)
        index, k = np.zeros(T, dtype=np.int64), -1
        for i in range(T):
            shared = static or (i > 0 and source[i] == STATIC and source[i - 1] == STATIC)
            if not (shared and k >= 0):
                k += 1
            index[i] = k
        self.register_buffer("pseudo", torch.as_tensor(np.asarray(pseudo), dtype=torch.float64))
        self.register_buffer("index", torch.as_tensor(index))
        self.xi = torch.nn.Parameter(torch.zeros(k + 1, 6, dtype=torch.float64))

    @property
    def n_params(self) -> int:
        return len(self.xi)

    def pose(self, t: int) -> torch.Tensor:
        """T_base_obj [4, 4] (float64) at frame ``t``."""
        return self.pseudo[t] @ se3_exp(self.xi[self.index[t]])

    def pose_loss(self, t: int) -> torch.Tensor:
        xi = self.xi[self.index[t]]
        return (xi[:3].norm() / SIGMA_T) ** 2 + (xi[3:].norm() / SIGMA_R) ** 2

    @torch.no_grad()
    def evaluation_poses(self, trained: list[int]) -> np.ndarray:
        """Poses [T, 4, 4] for every frame; frames whose own twist was never trained take the
        twist interpolated (linearly, in time) between the nearest trained frames."""
        trained_twists = {int(self.index[j]) for j in trained}
        anchors = sorted(trained)
        xi = self.xi[self.index].clone()  # [T, 6]
        for i in range(len(xi)):
            if int(self.index[i]) in trained_twists or not anchors:
                continue
            left = max((j for j in anchors if j < i), default=None)
            right = min((j for j in anchors if j > i), default=None)
            if left is None or right is None:  # before the first or after the last trained frame
                xi[i] = xi[right if left is None else left]
            else:
                w = (i - left) / (right - left)
                xi[i] = (1 - w) * xi[left] + w * xi[right]
        return (self.pseudo @ se3_exp(xi)).numpy()
