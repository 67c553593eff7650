"""How much of the new demonstrations' visual loss (benchmarks/bench_augment_shared.py: our
renders against the simulator's of the same commanded trajectories) is the simulated arm's lag
and not the twin. The twin renders the source demonstration at its recorded joints (where the
arm was: what the recorded images show) and at its commanded joints (``a1..a6``: where it was
told to be, which is what an augmented episode's joints are and what the simulator's arm
trails), both against the recorded images, over all frames.

The twin: ``$MANISPLAT_BENCH_RECON`` (a manisplat-reconstruct output of
shared/data/sim_pick_place_small), e.g. the one augment_shared made (its notes name it).
"""

from __future__ import annotations

import csv
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks._harness import BenchContext, MissingBenchmarkData

THREADED = False


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    from manisplat.episode import Episode
    from manisplat.twin import Twin

    parent = ctx.require_shared("data", "sim_pick_place_small")
    if not os.environ.get("MANISPLAT_BENCH_RECON"):
        raise MissingBenchmarkData("set MANISPLAT_BENCH_RECON to a reconstruction of sim_pick_place_small")
    twin, source = Twin.load(Path(os.environ["MANISPLAT_BENCH_RECON"])), Episode.open(parent)
    rows_csv = list(csv.DictReader(open(parent / "frames.csv")))
    commanded = np.array([[float(r[f"a{j}"]) for j in range(1, 7)] for r in rows_csv])
    labels = source.meta.labels
    robot_values = [v for v, name in labels.items() if name.startswith("robot/")]
    object_values = [v for v, name in labels.items() if name.startswith("object/") and name[7:] in twin.objects]
    frames = range(0, twin.n_frames, 4 if ctx.quick else 1)
    recorded: dict[str, list[float]] = {}
    lagged: dict[str, list[float]] = {}
    for i in frames:
        image, mask = source.rgb(i), source.mask(i)
        poses = {k: v[i] for k, v in twin.object_poses.items()}
        _scores(twin.render_frame(i).rgb, image, mask, robot_values, object_values, recorded)
        _scores(twin.render(commanded[i], twin.gripper[i], poses).rgb, image, mask, robot_values, object_values, lagged)
    lag = np.degrees(np.abs(commanded - twin.q).max(1))
    ctx.notes.append(f"commanded vs recorded joints: largest joint difference per frame median {np.median(lag):.2f} deg, "
                     f"max {lag.max():.2f} deg")
    return [{"row": f"twin at the recorded joints vs the recorded images ({len(frames)} frames)",
             **{k: float(np.nanmean(v)) for k, v in recorded.items()}},
            {"row": "twin at the commanded joints (a1..a6) vs the recorded images: with the arm's lag",
             **{k: float(np.nanmean(v)) for k, v in lagged.items()}}]


def _scores(pred: np.ndarray, target: np.ndarray, mask: np.ndarray, robot_values, object_values,
            scores: dict[str, list[float]]) -> None:
    """PSNR / SSIM of uint8 images [H, W, 3], full and over the robot's and object's ``mask`` pixels."""
    from manisplat.reconstruct.metrics import psnr, ssim

    pred_t, target_t = (torch.from_numpy(x).float() / 255 for x in (pred, target))
    regions = {"full": None, "robot": torch.from_numpy(np.isin(mask, robot_values)),
               "object": torch.from_numpy(np.isin(mask, object_values))}
    for key, region in regions.items():
        scores.setdefault(f"psnr_{key}", []).append(psnr(pred_t, target_t, region))
        scores.setdefault(f"ssim_{key}", []).append(ssim(pred_t, target_t, region))


def _lag_split(recon: Path, parent: Path) -> list[dict[str, Any]]:
    """How much of the new demonstrations' loss is the simulated arm's lag, not the twin: the
    twin renders the source at its recorded joints (where the arm was: what the images show) and
    at its commanded joints (``a1..a6``, where it was told to be: what an augmented episode's
    joints are, and what the simulator's arm trails), both against the recorded images, all frames."""
    import csv

    from manisplat.episode import Episode
    from manisplat.twin import Twin

    twin, source = Twin.load(recon), Episode.open(parent)
    rows_csv = list(csv.DictReader(open(parent / "frames.csv")))
    commanded = np.array([[float(r[f"a{j}"]) for j in range(1, 7)] for r in rows_csv])
    labels = source.meta.labels
    robot_values = [v for v, name in labels.items() if name.startswith("robot/")]
    object_values = [v for v, name in labels.items() if name.startswith("object/") and name[7:] in twin.objects]
    recorded: dict[str, list[float]] = {}
    lagged: dict[str, list[float]] = {}
    for i in range(twin.n_frames):
        image, mask = source.rgb(i), source.mask(i)
        poses = {k: v[i] for k, v in twin.object_poses.items()}
        _scores(twin.render_frame(i).rgb, image, mask, robot_values, object_values, recorded)
        _scores(twin.render(commanded[i], twin.gripper[i], poses).rgb, image, mask, robot_values, object_values, lagged)
    return [{"row": f"twin at the recorded joints vs the recorded images (all {twin.n_frames} frames)",
             **{k: float(np.nanmean(v)) for k, v in recorded.items()}},
            {"row": "twin at the commanded joints (a1..a6) vs the recorded images: the arm's lag",
             **{k: float(np.nanmean(v)) for k, v in lagged.items()}}]
