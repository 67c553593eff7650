"""Issue 36's development set: pick-and-place episodes from the simulator
(shared/tools/sim/gen_pick_place.py) seen from cameras where users mount them (front, sides,
high, behind left and right; 0.6-1.3 m from the workspace; 320x240 and 640x480; box and can),
each copied through shared/tools/degrade's oak preset with several seeds (distortion, exposure,
noise, blur, JPEG, stereo depth, a 0.3 deg / 3 mm calibration error whose truth stays beside the
copy, by ``benchmarks/bench_camera_check.py``). Generated, not committed: into ``$MANISPLAT_VIEWPOINTS`` (default
``~/.cache/manisplat/viewpoints``) with the python of ``$MANISPLAT_SIMENV`` (a venv with mujoco
4.0.0: shared/tools/sim/README.md); about 40 s per 320x240 episode and 2 minutes per 640x480 one
on 2 cores."""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks._harness import BenchContext
from benchmarks._testset import simulated_episodes

#: the middle of the workspace (between the objects' start and the mat), base frame, m
TARGET = (0.28, 0.03, 0.03)
DEGRADE_SEEDS = (1, 2, 3)


@dataclass(frozen=True)
class Viewpoint:
    """One camera of the set: where it is (base frame, m), the image size, the object, the layout seed."""

    name: str
    position: tuple[float, float, float]
    size: tuple[int, int]
    obj: str
    seed: int

    @property
    def distance_m(self) -> float:
        return float(np.linalg.norm(np.subtract(self.position, TARGET)))

    def generator_args(self) -> list[str]:
        return ["--width", str(self.size[0]), "--height", str(self.size[1]), "--fps", "16", "--frames", "120",
                "--png-optimize", "--object", self.obj, "--seed", str(self.seed),
                "--cam-pos", *map(str, self.position), "--cam-target", *map(str, TARGET)]


VIEWPOINTS = (
    Viewpoint("front_near", (0.70, -0.15, 0.40), (320, 240), "box", 11),
    Viewpoint("front_far", (1.15, 0.00, 0.70), (640, 480), "can", 12),
    Viewpoint("right", (0.30, -0.90, 0.62), (320, 240), "box", 13),
    Viewpoint("left", (0.30, 0.85, 0.55), (640, 480), "box", 14),
    Viewpoint("high", (0.40, -0.05, 1.05), (320, 240), "can", 15),
    Viewpoint("behind_left", (-0.40, 0.35, 0.70), (640, 480), "box", 16),
    Viewpoint("behind_right", (-0.35, -0.40, 0.60), (320, 240), "can", 17),
    Viewpoint("front_left_high", (0.85, 0.50, 0.75), (320, 240), "can", 18),
    Viewpoint("right_far", (0.75, -0.85, 0.80), (320, 240), "box", 19),
)


def root() -> Path:
    return Path(os.environ.get("MANISPLAT_VIEWPOINTS", Path.home() / ".cache" / "manisplat" / "viewpoints"))


def clean_episodes(ctx: BenchContext, viewpoints=VIEWPOINTS, workers: int = 2) -> list[Path]:
    """The simulator's episodes of ``viewpoints`` (made where missing); raises MissingBenchmarkData
    without a simulator."""
    return simulated_episodes(ctx, root() / "clean", {v.name: v.generator_args() for v in viewpoints}, workers)


def select(names: str) -> list[Viewpoint]:
    """The viewpoints named in the comma-separated ``names`` (an argparse ``type``: an unknown name
    is refused with the known ones)."""
    by_name = {v.name: v for v in VIEWPOINTS}
    if unknown := [n for n in names.split(",") if n not in by_name]:
        raise argparse.ArgumentTypeError(f"unknown viewpoints {unknown}; choose from {', '.join(by_name)}")
    return [by_name[n] for n in names.split(",")]


def add_set_options(parser: argparse.ArgumentParser, workers_help: str) -> None:
    """``--viewpoints`` (default: all), ``--seeds`` (the degrade seeds, default
    :data:`DEGRADE_SEEDS`) and ``--workers`` (default 2), as the benchmarks over the whole set take
    them."""
    parser.add_argument("--viewpoints", type=select, default=",".join(v.name for v in VIEWPOINTS))
    parser.add_argument("--seeds", default=",".join(map(str, DEGRADE_SEEDS)), help="degrade seeds (default 1,2,3)")
    parser.add_argument("--workers", type=int, default=2, help=workers_help)
