"""Reconstruction without the episode's masks or depth on shared/data sim_pick_place_small, as
``manisplat-reconstruct`` runs it (``--iters 1000``, the current thread count): the default
(masks + depth), ``--no-masks`` with a point prompt on the box (robot masks drawn from its
Gaussians, the object from depth), ``--no-depth`` (monocular start, the gripper prior), and both
off with a box prompt. Region metrics use the episode's own masks in every run. Prompts: the
box's centre pixel in frame 0 and a box around it.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

from benchmarks._harness import BenchContext

THREADED = False
RUNS = {
    "masks + depth (default)": [],
    "--no-masks --object-point 183.3,147.7": ["--no-masks", "--object-point", "183.3,147.7"],
    "--no-depth": ["--no-depth"],
    "--no-depth --no-masks --object-box 170,131,197,164": ["--no-depth", "--no-masks", "--object-box", "170,131,197,164"],
}


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    from manisplat.reconstruct.cli import main as reconstruct

    episode = ctx.require_shared("data", "sim_pick_place_small")
    iters = "60" if ctx.quick else "1000"
    rows = []
    for name, flags in RUNS.items():
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "recon"
            assert reconstruct([str(episode), "--out", str(out), "--iters", iters, "-q", *flags]) == 0
            m = json.loads((out / "metrics.json").read_text())
        pose, anchored = m["pose"]["box"], m.get("pose_anchored", {}).get("box", {})
        rows.append({"run": name, "wall_s": m["wall_s"], **{f"psnr_{k}": v for k, v in m["psnr"].items()},
                     "et_cm": pose["et_cm"], "er_deg": pose["er_deg"],
                     "anchored_et_cm": anchored.get("et_cm"), "anchored_er_deg": anchored.get("er_deg"),
                     "base_et_cm": m["pose_baseline"]["box"]["et_cm"], "base_er_deg": m["pose_baseline"]["box"]["er_deg"]})
    ctx.notes.append(f"--iters {iters}; pose: fitted offset (et/er) and start-anchored (anchored_*); base_*: the "
                     "per-frame baseline")
    return rows
