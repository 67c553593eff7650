"""Rendering and writing new demonstrations from the twin: frames per second with 1 and 2
worker processes (``manisplat-augment --workers``), 320x240 RGB + depth + masks, PNG.

The twin: ``$MANISPLAT_BENCH_RECON`` (a manisplat-reconstruct output of
shared/data/sim_pick_place_small). Each run writes the same ``--n`` demonstrations (seed 0) into
a fresh folder; the rate is ``augment_report.json``'s rendered frames over its
render-and-write time (planning excluded).
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

from benchmarks._harness import BenchContext, MissingBenchmarkData

THREADED = False


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    from manisplat.augment.cli import main as augment

    if not os.environ.get("MANISPLAT_BENCH_RECON"):
        raise MissingBenchmarkData("set MANISPLAT_BENCH_RECON to a reconstruction of sim_pick_place_small")
    recon = Path(os.environ["MANISPLAT_BENCH_RECON"])
    n = 2 if ctx.quick else 6
    rows = []
    for workers in (1, 2):
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "aug"
            augment([str(recon), "--n", str(n), "--out", str(out), "--workers", str(workers), "--seed", "0", "-q"])
            report = json.loads((out / "augment_report.json").read_text())
            frames = sum(sum(1 for _ in open(p / "frames.csv")) - 1 for p in out.iterdir() if p.name.startswith("episode_"))
        seconds = report["timing_s"]["render_and_write"]
        rows.append({"workers": workers, "demonstrations": report["written"], "frames": frames,
                     "render_write_s": seconds, "frames_per_s": frames / seconds,
                     "ms_per_frame": 1000 * seconds / frames})
    ctx.notes.append("each worker is a process rendering whole demonstrations with the C++ CPU rasterizer")
    return rows
