"""Demonstrations as training tensors, read the way a user reads them (``manisplat.episode``).

Each frame gives the policy's input, the camera image resized to the policy's size (OpenCV's area
filter, the same as at evaluation) and the joint state ``q1..q6, gripper``, and its target, the next
``chunk`` commanded actions ``a1..a6, a_gripper`` (held at the last one past the episode's end)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from manisplat.episode import Episode

IMAGE_SIZE = (128, 96)  # (width, height) the policy sees


def resize(rgb: np.ndarray, size: tuple[int, int] = IMAGE_SIZE) -> np.ndarray:
    """(H, W, 3) uint8 -> (size[1], size[0], 3) uint8, area filter (no-op at the same size)."""
    if (rgb.shape[1], rgb.shape[0]) == size:
        return rgb
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)


@dataclass
class Demonstrations:
    """Frames of several episodes, concatenated.

    Attributes:
        images: (F, 3, h, w) uint8.
        state: (F, 7) float32, q1..q6 (rad) and gripper gap (m).
        actions: (F, 7) float32 commanded targets at each frame.
        episode: (F,) int64 index of the frame's episode; ``ends[e]`` is one past its last frame.
        names: episode folder names.
    """

    images: torch.Tensor
    state: torch.Tensor
    actions: torch.Tensor
    episode: torch.Tensor
    ends: torch.Tensor
    names: list[str]

    def __len__(self) -> int:
        return len(self.state)

    def chunks(self, index: torch.Tensor, chunk: int) -> torch.Tensor:
        """(B,) frame indices -> (B, chunk, 7) actions from each frame on, the episode's last repeated."""
        steps = index[:, None] + torch.arange(chunk)[None, :]
        last = self.ends[self.episode[index]][:, None] - 1
        return self.actions[torch.minimum(steps, last)]


def load_demonstrations(folders: list[Path], size: tuple[int, int] = IMAGE_SIZE) -> Demonstrations:
    """Read episode folders (format v1, with ``a1..a6, a_gripper`` in frames.csv) into tensors."""
    images, state, actions, episode, ends = [], [], [], [], []
    total = 0
    for e, folder in enumerate(folders):
        ep = Episode.open(folder)
        acts = ep.frames.actions
        if acts is None:
            raise ValueError(f"{folder}: frames.csv has no a1..a6, a_gripper columns (the commanded targets)")
        images.append(np.stack([resize(ep.rgb(i), size) for i in range(len(ep))]))
        state.append(np.concatenate([ep.frames.q, ep.frames.gripper[:, None]], axis=1))
        actions.append(acts)
        episode.append(np.full(len(ep), e))
        total += len(ep)
        ends.append(total)
    return Demonstrations(
        images=torch.from_numpy(np.concatenate(images)).permute(0, 3, 1, 2).contiguous(),
        state=torch.from_numpy(np.concatenate(state)).float(),
        actions=torch.from_numpy(np.concatenate(actions)).float(),
        episode=torch.from_numpy(np.concatenate(episode)).long(),
        ends=torch.tensor(ends, dtype=torch.long),
        names=[f.name for f in folders],
    )


def episode_folders(root: Path) -> list[Path]:
    """The ``episode_*`` folders under ``root`` (or ``root`` itself when it is one), sorted."""
    if (root / "episode.json").exists():
        return [root]
    found = sorted(p for p in root.iterdir() if p.name.startswith("episode_") and (p / "episode.json").exists())
    if not found:
        raise FileNotFoundError(f"{root}: no episode folders")
    return found
