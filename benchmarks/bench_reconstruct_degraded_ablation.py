"""Each compensation for a real recording switched off in turn, on the oak-preset copy (seed 1)
of the shared pick-and-place, ``--iters 1000``: undistortion (camera.dist ignored), the per-frame
exposure gains (``--no-exposure``), the extrinsic and time-offset check
(``--keep-extrinsic``), the episode's masks (``--no-masks``: robot masks drawn from the model,
the object segmented from a point on it in frame 0). Then the camera check alone (no training) on every oak copy
of both episodes and on the generated test set's episode recorded with a 10 ms camera latency,
with its stereo-error weights switched off.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks._degraded import SOURCES, degraded, reconstruct, robot_of, row
from benchmarks._harness import BenchContext, MissingBenchmarkData
from benchmarks._testset import test_set
from manisplat.episode import Episode
from manisplat.reconstruct.data import load_episode_data
from manisplat.reconstruct.extrinsic import pose_difference, refine_extrinsic
from manisplat.reconstruct.plan import make_plan

THREADED = False
RUNS = {  # name -> (extra CLI arguments, whether camera.dist is removed from the copy)
    "all compensations": ((), False),
    "no undistortion": ((), True),
    "no exposure gains": (("--no-exposure",), False),
    "no extrinsic/time check": (("--keep-extrinsic",), False),
    # the box's centre pixel in frame 0, as in bench_reconstruct_inputs.py (undistorted image)
    "no episode masks (drawn)": (("--no-masks", "--object-point", "183.3,147.7"), False),
}
CHECKS = {"all": {}, "uniform depth weights": {"depth_weighting": False}}


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    iters = 40 if ctx.quick else 1000
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        source = SOURCES[0]
        robot = robot_of(ctx.require_shared("data", source))
        episode, truth = degraded(ctx, source, 1, root)
        T_true, T_recorded = np.asarray(truth["T_mount_cam_true"]), Episode.open(episode).camera.T_mount_cam
        for name, (extra, pinhole) in list(RUNS.items())[: 2 if ctx.quick else None]:
            target = episode
            if pinhole:
                target = root / f"{episode.name}_pinhole"
                shutil.copytree(episode, target)
                meta = json.loads((target / "episode.json").read_text())
                meta["camera"]["dist"] = []
                (target / "episode.json").write_text(json.dumps(meta))
            twin = reconstruct(target, root / f"twin_{len(rows)}", iters, robot, *extra)
            rows.append({"table": "training", "episode": episode.name, "run": name,
                         **row(twin, T_true, T_recorded, truth["gain"])})
        for source in SOURCES[:1] if ctx.quick else SOURCES:
            for seed in (1,) if ctx.quick else (1, 2, 3):
                episode, truth = degraded(ctx, source, seed, root / "checks")
                rows += _checks(episode, np.asarray(truth["T_mount_cam_true"]), robot)
    if not ctx.quick:
        try:
            late = next(e for e in test_set(ctx) if e.name == "noisy_latency_seed5")
        except MissingBenchmarkData as exc:
            ctx.notes.append(f"latency episode skipped: {exc}")
        else:
            rows += _checks(late, Episode.open(late).camera.T_mount_cam, None)
    ctx.notes.append(f"training rows: --iters {iters}; check rows: refine_extrinsic alone on the training frames "
                     "(truth: degrade_episode.py's T_mount_cam, or the episode's own for the latency episode, "
                     "recorded with --cam-latency 0.01: the true offset is -10 ms)")
    return rows


def _checks(episode: Path, T_true: np.ndarray, robot: str | None) -> list[dict]:
    data = load_episode_data(episode, robot=robot)
    frames = make_plan(data).train_frames
    out = []
    for name, options in CHECKS.items():
        c = refine_extrinsic(data, frames, **options)
        before, after = pose_difference(T_true, c.T_before), pose_difference(T_true, c.T_after)
        out.append({"table": "camera check", "episode": episode.name, "run": name,
                    "extrinsic_error_before_deg": before[0], "extrinsic_error_before_mm": before[1],
                    "extrinsic_error_after_deg": after[0], "extrinsic_error_after_mm": after[1],
                    "correction_sigma_deg": c.sigma_rotation_deg, "correction_sigma_mm": c.sigma_translation_mm,
                    "time_offset_ms": None if c.time_offset_s is None else 1e3 * c.time_offset_s,
                    "time_sigma_ms": None if c.sigma_time_offset_s is None else 1e3 * c.sigma_time_offset_s,
                    "rms_after_mm": c.rms_after_mm})
    return out
