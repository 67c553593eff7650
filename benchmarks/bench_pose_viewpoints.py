"""Issue 36, item 3: the object's pseudo ground truth over the viewpoint development set
(``benchmarks/_viewpoints.py``: 9 cameras where users mount them, each through the oak preset
with seeds 1-3), as ``manisplat-reconstruct`` makes it before training: the camera check, the
masks, the phases, the gripper prior, tracking and the depth's fits (one iteration of training,
whose poses are the pseudo ones). Errors against the simulator's truth, start-anchored and
fitted (``manisplat.reconstruct.metrics``); the joint optimisation moves them by well under a
millimetre (``python -m benchmarks reconstruct_viewpoints`` for whole reconstructions).

``python -m benchmarks pose_viewpoints [--viewpoints NAME,...] [--seeds 1,2,3] [--workers 2]
[--out FILE]``
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from benchmarks._harness import BENCH_DIR, BenchContext, shared_dir
from benchmarks._viewpoints import add_set_options, clean_episodes
from benchmarks.bench_camera_check import degraded_copy

OWN_OPTIONS = True
KEYS = ("anchored_et_cm", "anchored_er_deg", "anchored_et_max_cm", "final_et_cm", "fitted_et_cm", "fitted_er_deg")


def pose_row(episode: Path) -> dict:
    """The object's pseudo-pose errors of one ``manisplat-reconstruct --iters 1`` run."""
    from benchmarks._degraded import reconstruct, robot_of  # torch and the pipeline: not for --help

    logging.disable(logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        twin = reconstruct(episode, Path(tmp) / "twin", 1, robot_of(episode), "--threads", "1")
        metrics = json.loads((twin / "metrics.json").read_text())
    (name, pseudo), = metrics["pose_pseudo"].items()
    anchored, fitted = pseudo["anchored"], pseudo["fitted"]
    return {"object": name, "anchored_et_cm": anchored["et_cm"], "anchored_er_deg": anchored["er_deg"],
            "anchored_et_max_cm": anchored["et_cm_max"], "final_et_cm": anchored["final"]["et_cm"],
            "fitted_et_cm": fitted["et_cm"], "fitted_er_deg": fitted["er_deg"],
            "phases_et_cm": {k: v["et_cm"] for k, v in anchored.get("phases", {}).items()},
            "wall_s": round(time.perf_counter() - t0, 1)}


def _run_one(task: tuple[str, str, float, str, int]) -> dict:
    episode, viewpoint, distance, size, seed = task
    return {"viewpoint": viewpoint, "distance_m": round(distance, 3), "size": size, "degrade_seed": seed,
            **pose_row(Path(episode))}


def summary(rows: list[dict]) -> dict:
    """Median, 90th percentile and worst of each error over ``rows``."""
    return {k: {"median": float(np.median([r[k] for r in rows])), "p90": float(np.percentile([r[k] for r in rows], 90)),
                "max": float(max(r[k] for r in rows))} for k in KEYS}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks pose_viewpoints", description=__doc__.splitlines()[0])
    add_set_options(p, "episodes at once (one process each, one thread)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_reconstruct" / "pose_viewpoints.json")
    args = p.parse_args(argv)
    options = sys.argv[1:] if argv is None else argv  # as run, for the result's command
    ctx = BenchContext(threads=1, quick=False, shared=shared_dir(), out_dir=args.out.parent)
    tasks = []
    for v, clean in zip(args.viewpoints, clean_episodes(ctx, args.viewpoints)):
        for seed in map(int, args.seeds.split(",")):
            episode, _ = degraded_copy(ctx, clean, "oak", seed)
            tasks.append((str(episode), v.name, v.distance_m, f"{v.size[0]}x{v.size[1]}", seed))
    t0 = time.perf_counter()
    with ProcessPoolExecutor(args.workers) as pool:
        rows = list(pool.map(_run_one, tasks))
    for r in rows:
        print(f"{r['viewpoint']:16s} oak{r['degrade_seed']} {r['object']:4s} start-anchored "
              f"{r['anchored_et_cm']:.2f} cm (worst frame {r['anchored_et_max_cm']:.2f}, where left "
              f"{r['final_et_cm']:.2f}), fitted {r['fitted_et_cm']:.2f} cm")
    result = {"benchmark": "pose_viewpoints", "command": " ".join(["python -m benchmarks pose_viewpoints", *options]),
              "summary": summary(rows), "rows": rows, "wall_s": round(time.perf_counter() - t0, 1)}
    print(json.dumps(result["summary"], indent=1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    return 0
