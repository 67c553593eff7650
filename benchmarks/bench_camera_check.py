"""Issue 36: the camera check (``manisplat.reconstruct.extrinsic.refine_extrinsic``, the robot's
depth on its link surfaces) over the viewpoint development set (``benchmarks/_viewpoints.py``):
9 cameras where users mount them, each through the oak preset with 3 seeds, the check alone on
the training frames as ``manisplat-reconstruct`` runs it (no training).

``python -m benchmarks camera_check [--conditions oak,...] [--viewpoints NAME,...] [--seeds 1,2,3]
[--workers 2] [--out FILE]``

Per episode: the extrinsic's true error before and after the check (rotation deg, camera centre
mm, against the truth degrade_episode.py wrote beside the copy; and what it moves the workspace's
points by, :func:`workspace_error_mm`), the correction and its reported
1-sigma, whether the truth lies within the reported 2-sigma (``covered``: after-error <= 2 sigma
in rotation and in translation), whether the check applied its correction or kept the
calibration (and why). Conditions, to tell the causes apart: ``oak`` (the preset: every effect),
``extrinsic`` (the calibration error alone: perfect depth and images), ``stereo`` (the calibration
error and the stereo depth, nothing else).
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from benchmarks._harness import BENCH_DIR, BenchContext, MissingBenchmarkData, shared_dir
from benchmarks._viewpoints import TARGET, add_set_options, clean_episodes, root

OWN_OPTIONS = True
#: condition -> degrade_episode.py's effects (the seed draws the calibration error's axis)
CONDITIONS = {
    "oak": ["--preset", "oak"],
    "extrinsic": ["--extrinsic", "0.3,3.0"],
    "stereo": ["--extrinsic", "0.3,3.0", "--stereo-noise", "0.08"],
}


def degraded_copy(ctx: BenchContext, clean: Path, condition: str, seed: int) -> tuple[Path, np.ndarray]:
    """``clean`` through ``condition``'s effects with ``seed`` (made where missing), and the true T_mount_cam."""
    dst = root() / condition / f"{clean.name}_{condition}{seed}"
    truth = dst.with_name(dst.name + ".degrade.json")
    if not (dst / "episode.json").is_file() or not truth.is_file():
        tool = ctx.require_shared("tools", "degrade", "degrade_episode.py")
        proc = subprocess.run([sys.executable, str(tool), str(clean), str(dst), *CONDITIONS[condition],
                               "--seed", str(seed)], capture_output=True, text=True)
        if proc.returncode != 0:
            raise MissingBenchmarkData(f"degrade_episode.py failed for {dst.name}: {proc.stderr[-800:]}")
    return dst, np.asarray(json.loads(truth.read_text())["T_mount_cam_true"], dtype=np.float64)


#: the workspace whose points an extrinsic error moves: a 5 x 5 x 5 grid over TARGET +-0.2 m
#: sideways and 0-0.3 m above the table (base frame, m), where the objects and the gripper are
WORKSPACE = np.stack(np.meshgrid(np.linspace(TARGET[0] - 0.2, TARGET[0] + 0.2, 5),
                                 np.linspace(TARGET[1] - 0.2, TARGET[1] + 0.2, 5),
                                 np.linspace(0.0, 0.3, 5), indexing="ij"), -1).reshape(-1, 3)


def workspace_error_mm(T_true: np.ndarray, T_est: np.ndarray) -> tuple[float, float]:
    """RMS and largest displacement (mm) of the :data:`WORKSPACE` points that the camera-to-base
    ``T_est`` [4, 4] puts where ``T_true`` has them: what an extrinsic error does to what the camera
    measures there. A camera far from the workspace can move along a direction (turning about the
    workspace while sliding sideways) that moves its centre by millimetres and these points by
    a tenth of that; the camera centre's error alone does not say what the error costs."""
    in_camera = (WORKSPACE - T_true[:3, 3]) @ T_true[:3, :3]
    moved = np.linalg.norm(in_camera @ T_est[:3, :3].T + T_est[:3, 3] - WORKSPACE, axis=1)
    return 1e3 * float(np.sqrt(np.mean(moved ** 2))), 1e3 * float(moved.max())


def check_row(episode: Path, T_true: np.ndarray) -> dict:
    """The camera check on ``episode``'s training frames, scored against ``T_true``."""
    import torch

    from manisplat.reconstruct.data import load_episode_data
    from manisplat.reconstruct.extrinsic import pose_difference, refine_extrinsic
    from manisplat.reconstruct.plan import make_plan

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    data = load_episode_data(episode)
    c = refine_extrinsic(data, make_plan(data).train_frames)
    row = {"episode": episode.name, "check_s": round(time.perf_counter() - t0, 1)}
    if c is None:
        return {**row, "checked": False}
    before, after = pose_difference(T_true, c.T_before), pose_difference(T_true, c.T_after)
    fitted = pose_difference(T_true, c.T_fitted)
    row.update({
        "checked": True, "applied": c.applied, "reason": c.reason,
        "error_before_deg": before[0], "error_before_mm": before[1],
        "error_after_deg": after[0], "error_after_mm": after[1],
        "fit_error_deg": fitted[0], "fit_error_mm": fitted[1],
        "workspace_before_mm": workspace_error_mm(T_true, c.T_before),
        "workspace_after_mm": workspace_error_mm(T_true, c.T_after),
        "correction_deg": c.rotation_deg, "correction_mm": c.translation_mm,
        "sigma_deg": c.sigma_rotation_deg, "sigma_mm": c.sigma_translation_mm,
        # the fit's own error (applied or not) against its reported 2-sigma
        "covered": bool(fitted[0] <= 2 * c.sigma_rotation_deg and fitted[1] <= 2 * c.sigma_translation_mm),
        "time_offset_ms": None if c.time_offset_s is None else 1e3 * c.time_offset_s,
        "rms_before_mm": c.rms_before_mm, "rms_after_mm": c.rms_after_mm, "points": c.points, "frames": c.frames,
    })
    return row


def summary(rows: list[dict]) -> dict:
    """Distribution of the errors before / after (median, 90th percentile, worst), the 2-sigma
    coverage of the fit, how often the calibration was kept."""
    checked = [r for r in rows if r.get("checked")]
    out: dict = {"episodes": len(rows), "checked": len(checked),
                 "viewpoints": len({r["viewpoint"] for r in rows}),
                 "kept": sum(not r["applied"] for r in checked),
                 "covered_fraction": float(np.mean([r["covered"] for r in checked])) if checked else None}
    for key in ("error_before_deg", "error_before_mm", "error_after_deg", "error_after_mm", "fit_error_deg",
                "fit_error_mm", "workspace_before_mm", "workspace_after_mm"):
        values = np.array([r[key][0] if key.startswith("workspace") else r[key] for r in checked])
        if len(values):
            out[key] = {"median": float(np.median(values)), "p90": float(np.percentile(values, 90)),
                        "max": float(values.max())}
    return out


def plot_coverage(rows: list[dict], path: Path) -> None:
    """The fit's true error against its reported 2-sigma, rotation and translation, one point per
    episode coloured by viewpoint: a point below the diagonal is covered."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    checked = [r for r in rows if r.get("checked")]
    names = sorted({r["viewpoint"] for r in checked})
    colours = dict(zip(names, plt.get_cmap("tab10").colors))
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    for ax, unit in zip(axes, ("deg", "mm")):
        for name in names:
            mine = [r for r in checked if r["viewpoint"] == name]
            ax.scatter([2 * r[f"sigma_{unit}"] for r in mine], [r[f"fit_error_{unit}"] for r in mine],
                       color=colours[name], label=name, s=25)
        top = max(max(2 * r[f"sigma_{unit}"] for r in checked), max(r[f"fit_error_{unit}"] for r in checked)) * 1.1
        ax.plot([0, top], [0, top], "k--", lw=1)
        ax.set(xlim=(0, top), ylim=(0, top), xlabel=f"reported 2-sigma ({unit})", ylabel=f"true error of the fit ({unit})",
               title="rotation" if unit == "deg" else "camera centre")
    axes[1].legend(fontsize=7, loc="upper left")
    fig.suptitle("Camera check over the viewpoint set: below the line = the truth within the reported 2-sigma")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _run_one(task: tuple[str, float, str, list[int], str, int, str]) -> dict:
    episode, distance, size, position, obj, seed, viewpoint = task
    logging.disable(logging.WARNING)
    row = check_row(Path(episode), np.asarray(json.loads(Path(episode + ".degrade.json").read_text())
                                              ["T_mount_cam_true"], dtype=np.float64))
    return {"viewpoint": viewpoint, "distance_m": round(distance, 3), "size": size, "position": position,
            "object": obj, "degrade_seed": seed, **row}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks camera_check", description=__doc__.splitlines()[0])
    p.add_argument("--conditions", default="oak", help=f"comma-separated, of {', '.join(CONDITIONS)} (default oak)")
    add_set_options(p, "episodes checked at once (one process each)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_reconstruct" / "camera_check.json")
    args = p.parse_args(argv)
    options = sys.argv[1:] if argv is None else argv  # as run, for the result's command
    viewpoints = args.viewpoints
    conditions = args.conditions.split(",")
    if unknown := [c for c in conditions if c not in CONDITIONS]:
        p.error(f"unknown conditions {unknown}; choose from {', '.join(CONDITIONS)}")
    ctx = BenchContext(threads=1, quick=False, shared=shared_dir(), out_dir=args.out.parent)
    tasks = []
    for v, clean in zip(viewpoints, clean_episodes(ctx, viewpoints)):
        for condition in conditions:
            for seed in map(int, args.seeds.split(",")):
                episode, _ = degraded_copy(ctx, clean, condition, seed)
                tasks.append((str(episode), v.distance_m, f"{v.size[0]}x{v.size[1]}", list(v.position), v.obj, seed,
                              v.name))
    t0 = time.perf_counter()
    with ProcessPoolExecutor(args.workers) as pool:
        rows = list(pool.map(_run_one, tasks))
    for r, task in zip(rows, tasks):
        r["condition"] = next(c for c in conditions if f"/{c}/" in task[0])
    result = {"benchmark": "camera_check", "command": " ".join(["python -m benchmarks camera_check", *options]),
              "summary": {c: summary([r for r in rows if r["condition"] == c]) for c in conditions},
              "rows": rows, "wall_s": round(time.perf_counter() - t0, 1)}
    for r in rows:
        if r.get("checked"):
            print(f"{r['condition']:9s} {r['episode']:28s} {r['distance_m']:.2f} m  before {r['error_before_deg']:.3f} deg "
                  f"{r['error_before_mm']:.2f} mm -> fit {r['fit_error_deg']:.3f} deg {r['fit_error_mm']:.2f} mm "
                  f"(+- {r['sigma_deg']:.3f} / {r['sigma_mm']:.2f}), workspace {r['workspace_after_mm'][0]:.2f} mm "
                  f"{'applied' if r['applied'] else 'KEPT'} "
                  f"{'covered' if r['covered'] else 'NOT covered'}")
    print(json.dumps(result["summary"], indent=1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    plot_coverage(rows, args.out.with_suffix(".png"))
    return 0
