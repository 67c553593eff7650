"""What the plan saves on shared/data sim_reach_only_small: the box never moves, so it gets one
static pose and no tracking. Compared with the same run forced to track it per frame: time spent
(setup = loading, initialisation, alignment; training) and the error kept (held-out PSNR, pose).
Runs at the current torch thread count.
"""

from __future__ import annotations

from benchmarks._reconstruct import reconstruct_row
from manisplat.reconstruct.trainer import TrainConfig

THREADED = False


def run(ctx) -> list[dict]:
    episode = ctx.require_shared("data", "sim_reach_only_small")
    iters = 60 if ctx.quick else TrainConfig.iters
    rows = [
        {"run": "plan (static: one pose)", **reconstruct_row(episode, TrainConfig(iters=iters))},
        {"run": "forced per-frame tracking", **reconstruct_row(episode, TrainConfig(iters=iters), force_tracking=True)},
    ]
    ctx.notes.append("pose errors are after the one constant offset, as metrics.json; the baseline columns are "
                     "tracking alone")
    return rows
