"""Issue 36, item 3: whole reconstructions over the viewpoint development set
(``benchmarks/_viewpoints.py``, the oak-preset copies of ``python -m benchmarks camera_check``):
held-out PSNR / SSIM per region, the object's pose error fitted and start-anchored, the
extrinsic error before and after the camera check, wall time; ``manisplat-reconstruct`` with its
default budget (``--iters 3000`` on the CPU), one episode after the other.

The copies' colour went through the oak preset's JPEG step (OpenCV's default, 4:2:0) and was
stored as PNG. ``--colour declared`` (the default) reconstructs each from a copy whose
``episode.json`` says so (``manisplat-episode set-chroma``), as a recording stored as JPEG files,
or by a recorder that knows its camera's encoding, would; ``--colour unknown`` from the copy as the
degrade tool wrote it.

``python -m benchmarks reconstruct_viewpoints [--viewpoints NAME,...] [--seeds 1] [--iters 3000]
[--colour declared|unknown] [--threads N] [--lambda-pose L] [--out FILE]``
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._harness import BENCH_DIR, BenchContext, shared_dir
from benchmarks._viewpoints import clean_episodes, select
from benchmarks.bench_camera_check import degraded_copy
from manisplat.cli_args import non_negative, positive

OWN_OPTIONS = True
#: the 320x240 viewpoints (a 640x480 run takes about four times as long on 2 cores)
DEFAULT_VIEWPOINTS = ("front_near", "right", "high", "behind_right", "front_left_high", "right_far")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks reconstruct_viewpoints", description=__doc__.splitlines()[0])
    p.add_argument("--viewpoints", type=select, default=",".join(DEFAULT_VIEWPOINTS))
    p.add_argument("--seeds", default="1", help="degrade seeds (default 1)")
    p.add_argument("--iters", type=int, default=3000, help="training iterations (default 3000, the CPU default)")
    p.add_argument("--colour", choices=("declared", "unknown"), default="declared",
                   help="the copies say their colour was stored 4:2:0 (default), or say nothing")
    p.add_argument("--threads", type=positive(int), help="manisplat-reconstruct --threads (default: the command's)")
    p.add_argument("--lambda-pose", type=non_negative(), help="manisplat-reconstruct --lambda-pose (default: the command's)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_reconstruct" / "reconstruct_viewpoints.json")
    args = p.parse_args(argv)
    extra = (*(() if args.lambda_pose is None else ("--lambda-pose", str(args.lambda_pose))),
             *(() if args.threads is None else ("--threads", str(args.threads))))
    options = sys.argv[1:] if argv is None else argv  # as run, for the result's command
    from benchmarks._degraded import reconstruct, robot_of, row  # after the arguments: --help stays quick
    from manisplat.episode import Episode
    from manisplat.episode.images import describe_chroma

    viewpoints = args.viewpoints
    ctx = BenchContext(threads=2, quick=False, shared=shared_dir(), out_dir=args.out.parent)
    logging.disable(logging.WARNING)
    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for v, clean in zip(viewpoints, clean_episodes(ctx, viewpoints)):
            for seed in map(int, args.seeds.split(",")):
                episode, T_true = degraded_copy(ctx, clean, "oak", seed)
                if args.colour == "declared":
                    episode = declared_copy(episode, Path(tmp) / "episodes")
                recorded = Episode.open(episode)
                twin = reconstruct(episode, Path(tmp) / episode.name, args.iters, robot_of(episode), *extra)
                r = {"viewpoint": v.name, "distance_m": round(v.distance_m, 3), "size": f"{v.size[0]}x{v.size[1]}",
                     "degrade_seed": seed, "colour": describe_chroma(recorded.chroma_subsampling()),
                     **row(twin, T_true, recorded.camera.T_mount_cam),
                     "lambda_pose": json.loads((twin / "metrics.json").read_text())["lambda_pose"]}
                rows.append(r)
                print(json.dumps(r, default=float), flush=True)
    keys = [k for k in rows[0] if isinstance(rows[0][k], float) and k != "lambda_pose"]
    summary = {k: {"mean": float(np.mean([r[k] for r in rows if r.get(k) is not None])),
                   "p90": float(np.percentile([r[k] for r in rows if r.get(k) is not None], 90))}
               for k in keys if any(r.get(k) is not None for r in rows)}
    result = {"benchmark": "reconstruct_viewpoints",
              "command": " ".join(["python -m benchmarks reconstruct_viewpoints", *options]),
              "threads": args.threads or "manisplat-reconstruct's default (the cores free)",
              "summary": summary, "rows": rows,
              "wall_s": round(time.perf_counter() - t0, 1)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    return 0


def declared_copy(episode: Path, folder: Path) -> Path:
    """A copy of ``episode`` in ``folder`` whose ``episode.json`` says its colour was stored 4:2:0
    (what the oak preset's JPEG step, ``cv2.imencode`` of the BGR image, keeps)."""
    from manisplat.episode.chroma import set_chroma_subsampling

    copy = folder / episode.name
    shutil.copytree(episode, copy)
    set_chroma_subsampling(copy, "4:2:0")
    return copy
