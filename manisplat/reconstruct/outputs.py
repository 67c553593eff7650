"""What ``manisplat-reconstruct`` writes into its output folder.

* ``<node>.ply`` per node (background in the base frame, ``robot_<link>.ply`` in link frames,
  ``object_<name>.ply`` in the canonical object frame), 3DGS layout.
* ``object_poses.csv`` per object: ``frame, t, source, T_base_obj`` (16 numbers, row-major).
* ``phases.csv``: ``frame, t, phase`` per object.
* ``renders/test/NNNNNN.png``: the rendered RGB of every held-out frame, named by frame index;
  ``renders/sheets/NNNNNN.png``: ground truth | render | error.
* ``pose_plot.png``: rotation and translation per frame (ours, the phase-free baseline, ground truth).
* ``metrics.json``: ``psnr`` / ``ssim`` ({"full", "robot", "object"}), ``pose`` and
  ``pose_baseline`` ({object: {"et_cm", "er_deg"}}) when ground truth exists, ``wall_s``,
  ``iters``, ``plan``.
"""

from __future__ import annotations

import csv
import json
import logging
import math
from pathlib import Path

import cv2
import numpy as np
import torch

from manisplat.align.phases import phase_of_frames
from manisplat.reconstruct.metrics import fit_constant_offset, pose_errors, psnr, ssim
from manisplat.reconstruct.pipeline import ObjectAlignment
from manisplat.reconstruct.trainer import Reconstruction
from manisplat.splat import save_ply

log = logging.getLogger(__name__)


def write_outputs(rec: Reconstruction, alignments: dict[str, ObjectAlignment], out: Path, *, wall_s: float) -> dict:
    """Write everything listed in the module docstring; return the metrics dict."""
    out.mkdir(parents=True, exist_ok=True)
    for node in rec.graph.nodes():
        save_ply(out / f"{node.name.replace('/', '_')}.ply", node.gaussians.ply_dict())
    evaluation = rec.evaluation_poses()
    for name, poses in evaluation.items():
        _write_poses(out / (f"object_poses_{name}.csv" if len(evaluation) > 1 else "object_poses.csv"),
                     rec.data.t.numpy(), poses, alignments[name].pseudo.source)
    _write_phases(out / "phases.csv", rec.data.t.numpy(), alignments)
    metrics = {"psnr": {}, "ssim": {}, "iters": rec.step, "wall_s": round(wall_s, 1), "plan": rec.plan.to_dict()}
    metrics.update(_image_metrics(rec, evaluation, out))
    if rec.data.gt is not None:
        metrics.update(_pose_metrics(rec, evaluation, alignments, out))
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
    return metrics


def _write_poses(path: Path, t: np.ndarray, poses: np.ndarray, source: list[str]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "t", "source"] + [f"T{r}{c}" for r in range(4) for c in range(4)])
        for i, (ti, T) in enumerate(zip(t, poses)):
            w.writerow([i, f"{ti:.6f}", source[i]] + [repr(float(x)) for x in T.reshape(-1)])


def _write_phases(path: Path, t: np.ndarray, alignments: dict[str, ObjectAlignment]) -> None:
    names = {obj: phase_of_frames(a.segments, len(t)) for obj, a in alignments.items()}
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "t"] + [f"phase_{obj}" if len(names) > 1 else "phase" for obj in names])
        for i, ti in enumerate(t):
            w.writerow([i, f"{ti:.6f}"] + [names[obj][i] for obj in names])


@torch.no_grad()
def _image_metrics(rec: Reconstruction, evaluation: dict[str, np.ndarray], out: Path) -> dict:
    renders, sheets = out / "renders" / "test", out / "renders" / "sheets"
    renders.mkdir(parents=True, exist_ok=True)
    sheets.mkdir(parents=True, exist_ok=True)
    scores = {k: {"full": [], "robot": [], "object": []} for k in ("psnr", "ssim")}
    for f in rec.plan.test_frames:
        image = rec.render(f, evaluation)[0].clamp(0, 1)
        target = rec.data.image(f)
        rgb8 = (image.numpy() * 255 + 0.5).astype(np.uint8)
        cv2.imwrite(str(renders / f"{f:06d}.png"), cv2.cvtColor(rgb8, cv2.COLOR_RGB2BGR))
        error = ((image - target).abs().mean(-1, keepdim=True).expand(-1, -1, 3) * 4).clamp(0, 1)
        sheet = (torch.cat([target, image, error], dim=1).numpy() * 255 + 0.5).astype(np.uint8)
        cv2.imwrite(str(sheets / f"{f:06d}.png"), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
        masks = {"full": None}
        if rec.data.masks is not None or rec.data.eval_masks is not None:
            masks.update({k: rec.data.eval_region(f, k) for k in ("robot", "object")})
        for key, region in masks.items():
            scores["psnr"][key].append(psnr(image, target, region))
            scores["ssim"][key].append(ssim(image, target, region))
    summary = {}
    for metric, by_region in scores.items():
        summary[metric] = {k: _nanmean(v) for k, v in by_region.items() if v}
    return summary


def _nanmean(values: list[float]) -> float | None:
    finite = [v for v in values if not math.isnan(v)]
    return round(float(np.mean(finite)), 4) if finite else None


def _pose_metrics(rec: Reconstruction, evaluation: dict[str, np.ndarray], alignments: dict[str, ObjectAlignment],
                  out: Path) -> dict:
    gt = rec.data.gt
    pose, baseline, plots = {}, {}, {}
    for name, ours in evaluation.items():
        key = f"T_base_{name}"
        if key not in gt:
            continue
        pose[name] = {k: round(v, 4) for k, v in pose_errors(ours, gt[key]).items()}
        base = alignments[name].baseline
        if base is not None:
            baseline[name] = {k: round(v, 4) for k, v in pose_errors(base, gt[key]).items()}
        plots[name] = (ours, base, gt[key])
    if plots:
        _pose_plot(out / "pose_plot.png", rec.data.t.numpy(), plots)
    result = {"pose": pose}
    if baseline:
        result["pose_baseline"] = baseline
    return result


def _pose_plot(path: Path, t: np.ndarray, plots: dict) -> None:
    """Per object: translation (x, y, z, cm) and rotation angle from the start (deg) per frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from manisplat.geometry import rotation_error

    fig, axes = plt.subplots(len(plots), 2, figsize=(11, 3.2 * len(plots)), squeeze=False)
    for row, (name, (ours, base, gt)) in enumerate(plots.items()):
        series = {"ours": ours, "per-frame baseline": base, "ground truth": gt}
        for label, poses in series.items():
            if poses is None:
                continue
            aligned = poses if label == "ground truth" else poses @ fit_constant_offset(poses, gt)
            style = {"ours": "-", "per-frame baseline": ":", "ground truth": "--"}[label]
            trans = aligned[:, :3, 3] * 100
            for k, axis in enumerate("xyz"):
                axes[row, 0].plot(t, trans[:, k], style, color=f"C{k}", label=f"{axis} {label}" if k == 0 or label == "ours" else None)
            angle = np.degrees(rotation_error(torch.as_tensor(aligned[:1, :3, :3]).expand(len(aligned), 3, 3),
                                              torch.as_tensor(aligned[:, :3, :3])).numpy())
            axes[row, 1].plot(t, angle, style, color="k", label=label)
        axes[row, 0].set(title=f"{name}: translation", xlabel="t (s)", ylabel="cm")
        axes[row, 1].set(title=f"{name}: rotation from the first frame", xlabel="t (s)", ylabel="deg")
        axes[row, 0].legend(fontsize=7, ncol=2)
        axes[row, 1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
