"""Training with a fixed budget (steps x batch) and seed, the same for every data condition."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F

from benchmarks.policy.data import Demonstrations, Viewport
from benchmarks.policy.model import ChunkPolicy

IMAGE_MEAN, IMAGE_STD = 0.5, 0.25
SHIFT_PX = 6  # random-shift augmentation (DrQ; the diffusion policy's crop): +-6 px at 160 x 120


@dataclass(frozen=True)
class Budget:
    """The training budget: optimiser steps, batch size, chunk length, learning rate, seed.

    9000 steps of 32 frames are 48 passes over the 6000 frames of 50 demonstrations: with 3000
    (16 passes) the policy did the task from 25 of 50 evaluation starts with the simulator's own
    50 demonstrations, with 9000 from 42 (31 with training seed 1; docs/benchmarks.md)."""

    steps: int = 9000
    batch: int = 32
    chunk: int = 16
    lr: float = 1e-3
    seed: int = 0
    state_noise: float = 0.0  # rad: Gaussian noise added to the training frames' joint states (see add_state_noise)
    image_transforms: bool = False  # LeRobot's colour and sharpness jitter on the training images (see jitter_images)


@dataclass
class Normaliser:
    """Mean and standard deviation of the state and the actions over the training frames."""

    state_mean: torch.Tensor
    state_std: torch.Tensor
    action_mean: torch.Tensor
    action_std: torch.Tensor

    @classmethod
    def fit(cls, demos: Demonstrations) -> Normaliser:
        floor = torch.tensor([1e-2] * 6 + [1e-3])  # rad, m: a joint that never moves keeps a sane scale
        return cls(demos.state.mean(0), demos.state.std(0).clamp_min(floor),
                   demos.actions.mean(0), demos.actions.std(0).clamp_min(floor))

    def state(self, state: torch.Tensor) -> torch.Tensor:
        return (state - self.state_mean) / self.state_std

    def action(self, action: torch.Tensor) -> torch.Tensor:
        return (action - self.action_mean) / self.action_std

    def unaction(self, action: torch.Tensor) -> torch.Tensor:
        return action * self.action_std + self.action_mean


def image_input(images: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) uint8 -> float, about [-2, 2]."""
    return normalised(images.float() / 255.0)


def normalised(images: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) float in [0, 1] -> about [-2, 2]."""
    return (images - IMAGE_MEAN) / IMAGE_STD


def lerobot_image_transforms() -> tuple[torch.nn.Module, ...]:
    """LeRobot's default dataset image transforms (what ``--dataset.image_transforms.enable=true``
    switches on), in its order, as kornia augmentations: brightness x0.8-1.2, contrast x0.8-1.2,
    saturation x0.5-1.5, hue +-0.05 turn, sharpness 0.5-1.5 (0 blurred, 1 as it is)."""
    import kornia.augmentation as K

    return (K.ColorJitter(brightness=(0.8, 1.2), p=1.0), K.ColorJitter(contrast=(0.8, 1.2), p=1.0),
            K.ColorJitter(saturation=(0.5, 1.5), p=1.0), K.ColorJitter(hue=(-0.05, 0.05), p=1.0),
            K.RandomSharpness(sharpness=(0.5, 1.5), p=1.0))


def jitter_images(images: torch.Tensor, generator: torch.Generator, transforms: tuple[torch.nn.Module, ...],
                  per_image: int = 3) -> torch.Tensor:
    """(B, 3, H, W) float images in [0, 1], each through ``per_image`` of ``transforms`` drawn
    at random (LeRobot's ``max_num_transforms``, 3 by default), applied in the order given.

    Why: a policy trained on the twin's renders is run on other images (the simulator's here, a
    camera's on a robot); jittered colour and sharpness keep it from keying on the renders' own
    shading and softness."""
    chosen = torch.rand(len(images), len(transforms), generator=generator).argsort(dim=1)[:, :per_image]
    out = images.clone()
    for k, transform in enumerate(transforms):
        rows = (chosen == k).any(dim=1)
        if bool(rows.any()):
            out[rows] = transform(out[rows])
    return out


def random_shift(images: torch.Tensor, generator: torch.Generator, pad: int = SHIFT_PX) -> torch.Tensor:
    """Each of the (B, C, H, W) images shifted by up to +-pad pixels, edge pixels repeated."""
    b, c, h, w = images.shape
    padded = F.pad(images, (pad, pad, pad, pad), mode="replicate")
    dx = torch.randint(0, 2 * pad + 1, (b,), generator=generator).tolist()
    dy = torch.randint(0, 2 * pad + 1, (b,), generator=generator).tolist()
    return torch.stack([padded[i, :, y:y + h, x:x + w] for i, (x, y) in enumerate(zip(dx, dy))])


def add_state_noise(state: torch.Tensor, sigma_rad: float, generator: torch.Generator) -> torch.Tensor:
    """(B, 7) joint states (rad) and gripper gap (m) with N(0, sigma_rad) added to the six joints.

    Why: a policy trained on motions that run along a straight joint line from one start learns to
    read its target off the state once the arm moves (the direction it has taken) and stops looking
    at the image, so an early misjudgement is never corrected; jittered states make the state an
    unreliable guide to the target, leaving the image as the one that says where the object is."""
    if sigma_rad <= 0:
        return state
    noise = torch.randn(state.shape, generator=generator) * sigma_rad
    noise[:, 6:] = 0.0
    return state + noise


@dataclass
class TrainedPolicy:
    model: ChunkPolicy
    normaliser: Normaliser
    budget: Budget
    seconds: float
    final_loss: float
    frames: int
    viewport: Viewport


def load_saved(path: Path, chunk: int) -> tuple[ChunkPolicy, Normaliser, dict]:
    """A policy the benchmark saved (``work/policies/*.pt``): its model (in eval mode), normaliser
    and the saved record (training seconds, loss, frames)."""
    saved = torch.load(path, weights_only=False)
    model = ChunkPolicy(chunk=chunk)
    model.load_state_dict(saved["model"])
    model.eval()
    return model, Normaliser(**saved["normaliser"]), saved


def train(demos: Demonstrations, budget: Budget, progress: bool = True) -> TrainedPolicy:
    """Train a ChunkPolicy on ``demos``: L1 on normalised action chunks, AdamW, cosine decay."""
    torch.manual_seed(budget.seed)
    generator = torch.Generator().manual_seed(budget.seed)
    norm = Normaliser.fit(demos)
    model = ChunkPolicy(chunk=budget.chunk)
    optimiser = torch.optim.AdamW(model.parameters(), lr=budget.lr, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimiser, lambda s: 0.5 * (1 + math.cos(math.pi * min(s / budget.steps, 1.0))))
    start, losses = time.perf_counter(), []
    transforms = lerobot_image_transforms() if budget.image_transforms else ()
    from tqdm import tqdm

    for _ in tqdm(range(budget.steps), desc="train", disable=not progress, mininterval=5):
        index = torch.randint(0, len(demos), (budget.batch,), generator=generator)
        images = demos.images[index].float() / 255.0
        if transforms:
            images = jitter_images(images, generator, transforms)
        images = random_shift(normalised(images), generator)
        target = norm.action(demos.chunks(index, budget.chunk))
        state = norm.state(add_state_noise(demos.state[index], budget.state_noise, generator))
        loss = F.l1_loss(model(images, state), target)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        schedule.step()
        losses.append(loss.item())
    model.eval()
    tail = losses[-max(1, len(losses) // 20):]
    return TrainedPolicy(model, norm, budget, time.perf_counter() - start, sum(tail) / len(tail), len(demos),
                         demos.viewport)
