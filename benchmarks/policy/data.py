"""Demonstrations as training tensors, read the way a user reads them (``manisplat.episode``).

Each frame gives the policy's input, the camera image's workspace (:class:`Viewport`, the same at
evaluation) and the joint state ``q1..q6, gripper``, and its target, the next ``chunk`` commanded
actions ``a1..a6, a_gripper`` (held at the last one past the episode's end)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from manisplat.episode import Episode

IMAGE_SIZE = (160, 120)  # (width, height) the policy sees
OBJECT_LABEL_PREFIX = "object/"


@dataclass(frozen=True)
class Viewport:
    """The part of the camera image the policy sees: rows ``top..top+height``, columns
    ``left..left+width``, resized to ``size`` (width, height) with OpenCV's area filter (no-op at
    the same size). The whole image resized to 128x96 left the 4 cm box about 5 pixels wide, too
    few to see its yaw, and the policy closed its fingers on nothing (0 of 10 from the simulator's
    own 50 demonstrations; 5 of 10 with this crop at 160x120)."""

    top: int
    left: int
    height: int
    width: int
    size: tuple[int, int] = IMAGE_SIZE

    def view(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 camera image -> (size[1], size[0], 3) uint8 policy input."""
        part = np.ascontiguousarray(rgb[self.top:self.top + self.height, self.left:self.left + self.width])
        if (part.shape[1], part.shape[0]) == self.size:
            return part
        return cv2.resize(part, self.size, interpolation=cv2.INTER_AREA)

    @property
    def tag(self) -> str:
        """A short name for file names: ``v<left>_<top>_<width>x<height>_<size>``."""
        return f"v{self.left}_{self.top}_{self.width}x{self.height}_{self.size[0]}x{self.size[1]}"


def workspace_viewport(source: Path, reach_m: float, size: tuple[int, int] = IMAGE_SIZE) -> Viewport:
    """The viewport of the source episode's workspace: where its objects' masks are in the first and
    the last frame (picked up, put down), grown by ``reach_m`` (how far the evaluation moves the
    objects) at their depth, then to ``size``'s aspect and at least ``size`` pixels (no upsampling),
    kept inside the image. Reads what a recording has (masks, depth, intrinsics), no ground truth."""
    ep = Episode.open(source)
    if not ep.has_masks or not ep.has_depth:
        raise ValueError(f"{source}: the workspace viewport needs the episode's masks and depth")
    objects = [int(k) for k, name in ep.meta.labels.items() if str(name).startswith(OBJECT_LABEL_PREFIX)]
    rows, cols, depths = [], [], []
    for i in (0, len(ep) - 1):
        hit = np.isin(ep.mask(i), objects)
        r, c = np.nonzero(hit)
        rows += [r.min(), r.max()] if len(r) else []
        cols += [c.min(), c.max()] if len(c) else []
        depth = ep.depth(i)[hit]
        depths += list(depth[depth > 0])
    if not rows or not depths:
        raise ValueError(f"{source}: no object pixels with depth in the first and last frames")
    grow = ep.camera.K[0, 0] * reach_m / float(np.median(depths))
    aspect = size[0] / size[1]
    width = max(max(cols) - min(cols) + 2 * grow, (max(rows) - min(rows) + 2 * grow) * aspect, size[0])
    width = min(width, ep.camera.width, ep.camera.height * aspect)
    height = width / aspect
    centre_c, centre_r = (min(cols) + max(cols)) / 2, (min(rows) + max(rows)) / 2
    left = int(round(min(max(centre_c - width / 2, 0), ep.camera.width - width)))
    top = int(round(min(max(centre_r - height / 2, 0), ep.camera.height - height)))
    return Viewport(top, left, int(round(height)), int(round(width)), size)


@dataclass
class Demonstrations:
    """Frames of several episodes, concatenated.

    Attributes:
        images: (F, 3, h, w) uint8.
        state: (F, 7) float32, q1..q6 (rad) and gripper gap (m).
        actions: (F, 7) float32 commanded targets at each frame.
        episode: (F,) int64 index of the frame's episode; ``ends[e]`` is one past its last frame.
        names: episode folder names.
        viewport: how ``images`` were cut from the camera images (the policy sees the same).
    """

    images: torch.Tensor
    state: torch.Tensor
    actions: torch.Tensor
    episode: torch.Tensor
    ends: torch.Tensor
    names: list[str]
    viewport: Viewport

    def __len__(self) -> int:
        return len(self.state)

    def chunks(self, index: torch.Tensor, chunk: int) -> torch.Tensor:
        """(B,) frame indices -> (B, chunk, 7) actions from each frame on, the episode's last repeated."""
        steps = index[:, None] + torch.arange(chunk)[None, :]
        last = self.ends[self.episode[index]][:, None] - 1
        return self.actions[torch.minimum(steps, last)]


def load_demonstrations(folders: list[Path], viewport: Viewport) -> Demonstrations:
    """Read episode folders (format v1, with ``a1..a6, a_gripper`` in frames.csv) into tensors, each
    image as ``viewport`` shows it."""
    images, state, actions, episode, ends = [], [], [], [], []
    total = 0
    for e, folder in enumerate(folders):
        ep = Episode.open(folder)
        acts = ep.frames.actions
        if acts is None:
            raise ValueError(f"{folder}: frames.csv has no a1..a6, a_gripper columns (the commanded targets)")
        images.append(np.stack([viewport.view(ep.rgb(i)) for i in range(len(ep))]))
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
        viewport=viewport,
    )


def episode_folders(root: Path) -> list[Path]:
    """The ``episode_*`` folders under ``root`` (or ``root`` itself when it is one), sorted."""
    if (root / "episode.json").exists():
        return [root]
    found = sorted(p for p in root.iterdir() if p.name.startswith("episode_") and (p / "episode.json").exists())
    if not found:
        raise FileNotFoundError(f"{root}: no episode folders")
    return found
