"""Augmented episodes streamed by manisplat-replay on the simulated PiPER, with their tracking error.

``$MANISPLAT_BENCH_AUG``: a ``manisplat-augment --out`` folder (e.g. the one ``augment_shared``
keeps); its first 20 episodes (5 with ``--quick``) are replayed exactly as
:mod:`benchmarks.bench_replay_shared` replays the shared episodes (speed 1 unless the checks
refuse it; the simulated arm starts 3 deg away; real time, about 9 s each).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from benchmarks._harness import BenchContext, MissingBenchmarkData
from benchmarks.bench_replay_shared import replay_rows
from manisplat.drivers.piper.trajectory import ReplayLimits
from manisplat.robot import builtin_piper

THREADED = False


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    folder = os.environ.get("MANISPLAT_BENCH_AUG")
    if not folder or not Path(folder).is_dir():
        raise MissingBenchmarkData("set MANISPLAT_BENCH_AUG to a manisplat-augment output folder")
    episodes = sorted(p for p in Path(folder).iterdir() if p.name.startswith("episode_"))[: 5 if ctx.quick else 20]
    robot = builtin_piper(with_geometry=False)
    rows = []
    for path in episodes:
        rows += replay_rows(path, robot, ReplayLimits())
    ctx.notes.append("max/rms: worst joint, deg; 'lag' columns after removing the best constant delay")
    return rows
