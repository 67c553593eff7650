"""Reconstruction run time against error on shared/data sim_pick_place_small, per iteration budget.

One full run per budget (the learning-rate and densification schedules scale with it): held-out
PSNR/SSIM per region and the box's pose error (after the one constant offset) against wall time.
Writes ``reconstruct_budget_<threads>t.png``. The issue's targets: full PSNR >= 30 dB,
Et <= 0.6 cm, ER <= 5 deg within 15 minutes on the 2-core CPU.
"""

from __future__ import annotations

from benchmarks._reconstruct import plot_budget, reconstruct_row
from manisplat.reconstruct.trainer import TrainConfig

THREADED = True
BUDGETS = (250, 500, 1000, 2000, 3000)


def run(ctx) -> list[dict]:
    episode = ctx.require_shared("data", "sim_pick_place_small")
    budgets = (40, 80) if ctx.quick else BUDGETS
    rows = [reconstruct_row(episode, TrainConfig(iters=n)) for n in budgets]
    plot_budget(rows, ctx.out_dir / f"reconstruct_budget_{ctx.threads}t.png")
    ctx.notes.append("targets (issue 7): full PSNR >= 30 dB, Et <= 0.6 cm, ER <= 5 deg within 900 s (2 threads); "
                     "the paper: 32.31 dB, 0.5864 cm, 5.185 deg on its own benchmark")
    ctx.notes.append("wall_s = setup_s (load, plan, init, phases, tracking) + train_s; writing outputs is not counted")
    return rows
