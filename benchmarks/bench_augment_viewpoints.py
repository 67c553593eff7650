"""Issue 36, item 4: augmentation over scenes the project was not developed on. For each chosen
viewpoint of the development set (``benchmarks/_viewpoints.py``; its oak-preset copy, seed 1): a
twin (``manisplat-reconstruct --iters 1000``), ``manisplat-augment --n N --seed 0`` from it, and
every new demonstration executed with contact physics in the scene its episode was generated in
(``execute_episode.py``, ``$MANISPLAT_SIMENV``; the objects' poses put in the simulator's object
frame first, :func:`benchmarks.bench_augment_shared.in_simulator_frame`): validity with reasons,
physics success, where the object was left against the demonstration's promise.

``python -m benchmarks augment_viewpoints [--viewpoints NAME,...] [--n 20] [--out FILE]``
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

from benchmarks._harness import BENCH_DIR, BenchContext, MissingBenchmarkData, shared_dir
from benchmarks._viewpoints import clean_episodes, select
from benchmarks.bench_camera_check import degraded_copy

OWN_OPTIONS = True
DEFAULT_VIEWPOINTS = "front_near,right,high,behind_right,front_left_high"


def main(argv: list[str] | None = None) -> int:
    from manisplat.augment.cli import main as augment
    from manisplat.reconstruct.cli import main as reconstruct

    p = argparse.ArgumentParser(prog="python -m benchmarks augment_viewpoints", description=__doc__.splitlines()[0])
    p.add_argument("--viewpoints", type=select, default=DEFAULT_VIEWPOINTS)
    p.add_argument("--n", type=int, default=20, help="new demonstrations per scene (default 20)")
    p.add_argument("--iters", type=int, default=1000, help="the twins' training iterations (default 1000)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_augment" / "augment_viewpoints.json")
    args = p.parse_args(argv)
    options = sys.argv[1:] if argv is None else argv  # as run, for the result's command
    from benchmarks.bench_augment_shared import _physics  # after the arguments: --help stays quick
    from manisplat.twin import Twin

    simenv = os.environ.get("MANISPLAT_SIMENV")
    if not simenv:
        raise MissingBenchmarkData("set MANISPLAT_SIMENV to a mujoco venv's python: the physics check needs it")
    ctx = BenchContext(threads=2, quick=False, shared=shared_dir(), out_dir=args.out.parent)
    logging.disable(logging.WARNING)
    rows, t0 = [], time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for v, clean in zip(args.viewpoints, clean_episodes(ctx, args.viewpoints)):
            episode, _ = degraded_copy(ctx, clean, "oak", 1)
            twin, out = Path(tmp) / f"{v.name}_twin", Path(tmp) / f"{v.name}_aug"
            assert reconstruct([str(episode), "--out", str(twin), "--iters", str(args.iters), "-q"]) == 0
            augment([str(twin), "--n", str(args.n), "--out", str(out), "--workers", "2", "--seed", "0", "-q"])
            report = json.loads((out / "augment_report.json").read_text())
            demos = sorted(d for d in out.iterdir() if d.name.startswith("episode_"))
            # physics in the scene the episode was generated in (the clean original: the same scene and truth)
            row = {"viewpoint": v.name, "object": v.obj, "requested": report["requested"], "valid": report["valid"],
                   "reasons": report["reasons"], "physics_n": 0, "physics_success_clean": 0}
            if demos:  # a twin whose every draw was refused leaves nothing to execute
                row.update(_physics(Path(simenv), demos, clean, ctx, Twin.load(twin),
                                    Path(tmp) / f"{v.name}_sim_input"))
            rows.append(row)
            print(json.dumps(row, default=float), flush=True)
    n = sum(r["physics_n"] for r in rows)
    result = {"benchmark": "augment_viewpoints",
              "command": " ".join(["python -m benchmarks augment_viewpoints", *options]),
              "summary": {"scenes": len(rows), "demonstrations": n,
                          "physics_success_clean": sum(r["physics_success_clean"] for r in rows),
                          "physics_success_rate": sum(r["physics_success_clean"] for r in rows) / max(n, 1)},
              "rows": rows, "wall_s": round(time.perf_counter() - t0, 1)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    return 0
