"""Planned + validated new demonstrations per minute (no rendering), validity rate with reasons.

Twins: the built-in sample (64 frames, 160x120, reconstructed here with a short training: planning
needs the phases, poses and Gaussians' geometry, not image quality) and, when one is available,
a reconstruction of shared/data/sim_pick_place_small (``$MANISPLAT_BENCH_RECON`` or
``shared/recon/sim_pick_place_small``; skipped otherwise). Samples: object +-8 cm, +-8 cm,
+-45 deg; place +-5 cm, +-5 cm, +-45 deg (``sample_targets`` with seed = sample index).
"Threads" are worker processes here (planning is Python-bound: processes, not torch threads,
are what scales); each worker builds its collision scene once (``setup_s``, not in the rate).

Columns: twin, workers, n samples, valid, validity, reasons (count per Rejected reason),
valid_per_min and samples_per_min (wall clock of the batch), mean seconds per sample in IK,
planning (incl. collision checks of the path), timing (toppra) and validation, frames per valid
demonstration.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

OBJECT_RANGE = (0.08, 0.08, math.radians(45))
TARGET_RANGE = (0.05, 0.05, math.radians(45))

_TWIN_DIRS: dict[str, Path] = {}
_TMP: list[tempfile.TemporaryDirectory] = []
_WORKER = None


def _sample_twin(quick: bool) -> Path:
    if "sample" in _TWIN_DIRS:
        return _TWIN_DIRS["sample"]
    from manisplat.episode.synthetic import write_sample_episode
    from manisplat.reconstruct.data import load_episode_data
    from manisplat.reconstruct.outputs import write_twin
    from manisplat.reconstruct.pipeline import build
    from manisplat.reconstruct.plan import make_plan
    from manisplat.reconstruct.trainer import TrainConfig

    tmp = tempfile.TemporaryDirectory(prefix="bench_augment_")
    _TMP.append(tmp)
    root = Path(tmp.name)
    episode = write_sample_episode(root / "ep")
    data = load_episode_data(episode)
    rec, alignments = build(data, make_plan(data), TrainConfig(iters=30 if quick else 100))
    rec.train(progress=False)
    write_twin(rec, alignments, root / "twin")
    _TWIN_DIRS["sample"] = root / "twin"
    return root / "twin"


def _sim_twin(ctx) -> Path | None:
    env = os.environ.get("MANISPLAT_BENCH_RECON")
    for cand in ([Path(env)] if env else []) + [ctx.shared / "recon" / "sim_pick_place_small"]:
        if (cand / "twin.json").is_file():
            return cand
    return None


def _init(twin_dir: str) -> None:
    global _WORKER
    import torch

    torch.set_num_threads(1)
    from manisplat.augment.source import source_demo
    from manisplat.augment.trajectory import AugmentConfig, ObjectTarget, augment_trajectory
    from manisplat.twin import Twin

    twin = Twin.load(twin_dir)
    t0 = time.perf_counter()
    src = source_demo(twin)
    zero = {k: ObjectTarget(o.T_rest, o.T_placed) for k, o in src.objects.items() if o.manipulated}
    try:  # builds the scene once (kinematics, collision model, allowed pairs)
        augment_trajectory(twin, zero, AugmentConfig())
    except Exception:
        pass
    _WORKER = (twin, time.perf_counter() - t0)


def _setup_time(_: int) -> float:
    return _WORKER[1]


def _one(index: int) -> dict:
    from manisplat.augment.trajectory import AugmentConfig, Rejected, augment_trajectory, sample_targets

    twin = _WORKER[0]
    targets = sample_targets(twin, np.random.default_rng(index), OBJECT_RANGE, TARGET_RANGE)
    t0 = time.perf_counter()
    try:
        traj = augment_trajectory(twin, targets, AugmentConfig(seed=index))
    except Rejected as exc:
        return {"reason": exc.reason, "wall": time.perf_counter() - t0}
    return {"reason": None, "wall": time.perf_counter() - t0, "times": traj.planner["times_s"], "frames": len(traj.t),
            "skill_mm": traj.validation["skill_error_mm"], "skill_deg": traj.validation["skill_error_deg"]}


def _row(name: str, twin_dir: Path, workers: int, n: int) -> dict:
    with ProcessPoolExecutor(max_workers=workers, initializer=_init, initargs=(str(twin_dir),)) as pool:
        setup = max(pool.map(_setup_time, range(workers)))
        t0 = time.perf_counter()
        results = list(pool.map(_one, range(n), chunksize=1))
        wall = time.perf_counter() - t0
    valid = [r for r in results if r["reason"] is None]
    reasons = Counter(r["reason"] for r in results if r["reason"] is not None)
    mean = lambda key: float(np.mean([r["times"][key] for r in valid])) if valid else None  # noqa: E731
    return {"twin": name, "workers": workers, "n": n, "valid": len(valid), "validity": len(valid) / n,
            "reasons": ", ".join(f"{k} {v}" for k, v in sorted(reasons.items())) or "-",
            "valid_per_min": len(valid) / wall * 60, "samples_per_min": n / wall * 60, "setup_s": setup,
            "ik_s": mean("ik_s"), "planning_s": mean("planning_s"), "timing_s": mean("timing_s"),
            "validation_s": mean("validation_s"),
            "frames": float(np.mean([r["frames"] for r in valid])) if valid else None,
            "skill_err_mm_max": max((r["skill_mm"] for r in valid), default=None),
            "skill_err_deg_max": max((r["skill_deg"] for r in valid), default=None)}


def run(ctx) -> list[dict]:
    n = 20 if ctx.quick else 100
    workers = ctx.threads
    rows = [_row("sample", _sample_twin(ctx.quick), workers, n)]
    sim = _sim_twin(ctx)
    if sim is not None:
        rows.append(_row("sim_pick_place_small", sim, workers, n))
    elif "no sim twin" not in " ".join(ctx.notes):
        ctx.notes.append("no sim twin: no reconstruction of sim_pick_place_small found (set MANISPLAT_BENCH_RECON to "
                         "a manisplat-reconstruct output folder)")
    ctx.notes.append("threads = worker processes; rates exclude each worker's one-time scene setup (setup_s)")
    return rows
