"""Shared by the reconstruction benchmarks: one timed ``manisplat-reconstruct`` run as a table row."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from manisplat.reconstruct.data import load_episode_data
from manisplat.reconstruct.outputs import write_evaluation
from manisplat.reconstruct.pipeline import build
from manisplat.reconstruct.plan import make_plan
from manisplat.reconstruct.trainer import TrainConfig


def reconstruct_row(episode: Path, config: TrainConfig, *, force_tracking: bool = False) -> dict:
    """Run the pipeline as the CLI does and return its figures.

    Columns: setup_s (loading, plan, initialisation, phases, tracking), train_s, wall_s (both),
    gaussians at the end, held-out psnr/ssim per region, and per object et_cm / er_deg (ours) and
    base_et_cm / base_er_deg (the per-frame baseline), anchored_* (start-anchored: the mean over the
    frames after the object first moves, and final_*: where it is left) and pseudo_* (the pseudo
    ground truth alone, both definitions) when ``gt.npz`` exists. Writing outputs
    (evaluation) is not counted. ``force_tracking`` tracks every object even where the plan would
    give it one static pose (to measure what the plan saves).
    """
    start = time.perf_counter()
    data = load_episode_data(episode)
    plan = make_plan(data)
    if force_tracking:
        for obj in plan.objects:
            obj.moves, obj.reason = True, "forced by the benchmark"
    rec, alignments = build(data, plan, config)
    setup = time.perf_counter() - start
    rec.train(progress=False)
    wall = time.perf_counter() - start
    with tempfile.TemporaryDirectory() as tmp:
        metrics = write_evaluation(rec, alignments, Path(tmp), wall_s=wall)
    row = {"iters": config.iters, "setup_s": setup, "train_s": wall - setup, "wall_s": wall,
           "gaussians": sum(len(n.gaussians) for n in rec.graph.nodes()),
           "pose_params": sum(t.n_params for t in rec.trajectories.values())}
    for region in ("full", "robot", "object"):
        row[f"psnr_{region}"] = metrics["psnr"].get(region)
    row["ssim_full"] = metrics["ssim"].get("full")
    for name, err in metrics.get("pose", {}).items():
        row["object"] = name
        row["et_cm"], row["er_deg"] = err["et_cm"], err["er_deg"]
        base = metrics.get("pose_baseline", {}).get(name)
        if base:
            row["base_et_cm"], row["base_er_deg"] = base["et_cm"], base["er_deg"]
        anchored = metrics.get("pose_anchored", {}).get(name)
        if anchored:
            row["anchored_et_cm"], row["anchored_er_deg"] = anchored["et_cm"], anchored["er_deg"]
            row["anchored_final_et_cm"], row["anchored_final_er_deg"] = (anchored["final"]["et_cm"],
                                                                         anchored["final"]["er_deg"])
        pseudo = metrics.get("pose_pseudo", {}).get(name)
        if pseudo:
            row["pseudo_et_cm"], row["pseudo_er_deg"] = pseudo["fitted"]["et_cm"], pseudo["fitted"]["er_deg"]
            if pseudo["anchored"]:
                row["pseudo_anchored_et_cm"] = pseudo["anchored"]["et_cm"]
                row["pseudo_anchored_er_deg"] = pseudo["anchored"]["er_deg"]
    return row


def plot_budget(rows: list[dict], path: Path) -> None:
    """PSNR (full, robot, object) and pose error against wall time, one point per budget."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [r["wall_s"] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.5))
    for key, marker in (("psnr_full", "o-"), ("psnr_robot", "s-"), ("psnr_object", "^-")):
        a.plot(t, [r[key] for r in rows], marker, label=key.removeprefix("psnr_"))
    a.axhline(30, color="grey", ls="--", lw=0.8)
    for r in rows:
        a.annotate(str(r["iters"]), (r["wall_s"], r["psnr_full"]), fontsize=7)
    a.set(xlabel="wall time (s)", ylabel="held-out PSNR (dB)", title="image quality")
    a.legend(fontsize=8)
    if "et_cm" in rows[0]:
        b.plot(t, [r["et_cm"] for r in rows], "o-", label="Et (cm)")
        b.plot(t, [r["er_deg"] for r in rows], "s-", label="ER (deg)")
        b.axhline(0.6, color="C0", ls="--", lw=0.8)
        b.axhline(5.0, color="C1", ls="--", lw=0.8)
        b.set(xlabel="wall time (s)", title="object pose error (targets dashed)")
        b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
