"""Reconstruction on shared/data: held-out PSNR and object pose error against run time.

Trains ``sim_pick_place_small`` once and, at several iteration budgets, evaluates everything
``metrics.json`` reports (held-out PSNR/SSIM per region, pose error after the constant offset),
with the wall time spent so far. Writes ``reconstruct_budget.png`` (PSNR and pose error against
seconds). Threads follow the harness (1 and 2 by default; the 15-minute target is for 2).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from manisplat.reconstruct.data import load_episode_data
from manisplat.reconstruct.metrics import pose_errors, psnr, ssim
from manisplat.reconstruct.pipeline import build
from manisplat.reconstruct.plan import make_plan
from manisplat.reconstruct.trainer import Reconstruction, TrainConfig

THREADED = True
BUDGETS = (250, 500, 1000, 2000, 3000)


def evaluate(rec: Reconstruction) -> dict:
    """Held-out PSNR/SSIM (full, robot, object) and pose error per object, as metrics.json."""
    evaluation = rec.evaluation_poses()
    scores = {"psnr_full": [], "psnr_robot": [], "psnr_object": [], "ssim_full": []}
    for f in rec.plan.test_frames:
        image = rec.render(f, evaluation)[0].detach().clamp(0, 1)
        target = rec.data.image(f)
        scores["psnr_full"].append(psnr(image, target))
        scores["ssim_full"].append(ssim(image, target))
        scores["psnr_robot"].append(psnr(image, target, rec.data.eval_region(f, "robot")))
        scores["psnr_object"].append(psnr(image, target, rec.data.eval_region(f, "object")))
    out = {k: float(np.nanmean(v)) for k, v in scores.items()}
    for name, poses in evaluation.items():
        key = f"T_base_{name}"
        if rec.data.gt is not None and key in rec.data.gt:
            err = pose_errors(poses, rec.data.gt[key])
            out["et_cm"], out["er_deg"] = err["et_cm"], err["er_deg"]
    out["gaussians"] = sum(len(n.gaussians) for n in rec.graph.nodes())
    return out


def train_with_budgets(episode: Path, config: TrainConfig, budgets) -> list[dict]:
    """One training run; a row of metrics at each budget (evaluation time excluded from wall_s)."""
    start = time.perf_counter()
    data = load_episode_data(episode)
    plan = make_plan(data)
    rec, _ = build(data, plan, config)
    rows, paused = [], 0.0
    setup = time.perf_counter() - start
    for budget in budgets:
        rec.config.iters = budget
        rec.train(progress=False)
        t_eval = time.perf_counter()
        rows.append({"iters": budget, "wall_s": t_eval - start - paused, "setup_s": setup, **evaluate(rec)})
        paused += time.perf_counter() - t_eval
    return rows


def run(ctx) -> list[dict]:
    episode = ctx.require_shared("data", "sim_pick_place_small")
    budgets = (50, 100) if ctx.quick else BUDGETS
    config = TrainConfig(iters=budgets[-1])
    rows = train_with_budgets(episode, config, budgets)
    _plot(rows, ctx.out_dir / f"reconstruct_budget_{ctx.threads}t.png")
    ctx.notes.append("targets (issue 7): held-out full PSNR >= 30 dB, Et <= 0.6 cm, ER <= 5 deg within 15 min "
                     "(the paper: 32.31 dB, 0.5864 cm, 5.185 deg on its own benchmark)")
    ctx.notes.append("wall_s counts setup (loading, initialisation, phases, tracking) and training, not evaluation; "
                     "writing outputs adds about 10 s")
    return rows


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [r["wall_s"] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.5))
    a.plot(t, [r["psnr_full"] for r in rows], "o-", label="full")
    a.plot(t, [r["psnr_robot"] for r in rows], "s-", label="robot")
    a.plot(t, [r["psnr_object"] for r in rows], "^-", label="object")
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
        b.set(xlabel="wall time (s)", title="object pose error")
        b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
