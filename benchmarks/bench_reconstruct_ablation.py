"""The paper's loss ablation (its Table 3) on shared/data sim_pick_place_small: none / +pose / +app / +mask.

"none" trains with the render loss alone (object poses start at the pseudo ground truth and move
freely); each row adds one term with weight 1: the pose prior, the masked appearance loss, the
dynamic-mask loss (the last row is the paper's weights; the command's default weighs the pose
prior 0.01). Held-out PSNR/SSIM and the box's pose error.
Runs at the current torch thread count (the default on the 2-core machine: 2).
"""

from __future__ import annotations

from benchmarks._reconstruct import reconstruct_row
from manisplat.reconstruct.trainer import TrainConfig

THREADED = False
ROWS = {
    "none": dict(lambda_pose=0.0, lambda_app=0.0, lambda_mask=0.0),
    "+pose": dict(lambda_pose=1.0, lambda_app=0.0, lambda_mask=0.0),
    "+app": dict(lambda_pose=1.0, lambda_app=1.0, lambda_mask=0.0),
    "+mask": dict(lambda_pose=1.0, lambda_app=1.0, lambda_mask=1.0),
}


def run(ctx) -> list[dict]:
    episode = ctx.require_shared("data", "sim_pick_place_small")
    iters = 60 if ctx.quick else TrainConfig.iters
    rows = []
    for name, weights in ROWS.items():
        rows.append({"losses": name, **reconstruct_row(episode, TrainConfig(iters=iters, **weights))})
    ctx.notes.append("the paper's Table 3 reports the same four rows on its benchmark")
    return rows
