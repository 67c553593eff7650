"""manisplat-augment --symmetry: grasps of symmetric objects on the face nearest the source's wrist.

Two scenes, each augmented with and without its object's symmetry at the same seeds: the 4 x 4 cm
box of shared/data/sim_pick_place_small (square: ``box=4``) and the can of the viewpoint set's
``high`` scene (``benchmarks/_viewpoints.py``, clean; ``can=round``). Twins: ``--twins BOX,CAN``
(manisplat-reconstruct outputs of those episodes) or made here (``--iters``, default 1000).

1. Plan only (``augment_trajectory``, no images), ``--n-plan`` samples (default 100) with the
   object's yaw within +-``--yaw`` deg (default 90; place yaw likewise): validity with reasons,
   and how far the grasp turned from the source's as the arm sees it (the pick's turn about the
   vertical less the change of azimuth of the object's axis: 0 keeps the source's grasp heading)
   and joint 6's change at the pick's last frame; median / 90th percentile / worst.
2. Physics (``$MANISPLAT_SIMENV``): ``--n`` demonstrations (default 20) written by
   ``manisplat-augment`` and executed with contact physics in the scene they come from
   (``execute_episode.py``): success and where the object was left against ``T_end``.

``python -m benchmarks augment_symmetry [--yaw 90] [--n-plan 100] [--n 20] [--twins BOX,CAN] [--out FILE]``
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._harness import BENCH_DIR, BenchContext, shared_dir, simulator_python

OWN_OPTIONS = True
SCENES = (("box", "4"), ("can", "round"))  # object, its symmetry
OBJECT_XY, PLACE_XY = 0.08, 0.025  # m: the policy benchmark's ranges (the place stays on the mat)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks augment_symmetry", description=__doc__.splitlines()[0])
    p.add_argument("--yaw", type=float, default=90.0, help="object and place yaw half-range, deg (default 90)")
    p.add_argument("--n-plan", type=int, default=100, help="planned samples per scene and setting (default 100)")
    p.add_argument("--n", type=int, default=20, help="demonstrations executed in physics per scene and setting (default 20)")
    p.add_argument("--twins", help="BOX_TWIN,CAN_TWIN: reconstructions to reuse (default: made here)")
    p.add_argument("--iters", type=int, default=1000, help="iterations of twins made here (default 1000)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_augment" / "augment_symmetry.json")
    args = p.parse_args(argv)
    options = sys.argv[1:] if argv is None else argv
    simenv = simulator_python()  # the episodes and the physics need it
    ctx = BenchContext(threads=2, quick=False, shared=shared_dir(), out_dir=args.out.parent)
    logging.disable(logging.WARNING)
    rows, t0 = [], time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        episodes = _episodes(ctx)
        twins = [Path(t) for t in args.twins.split(",")] if args.twins else [None] * len(SCENES)
        for (obj, symmetry), episode, twin in zip(SCENES, episodes, twins):
            twin = twin or _reconstruct(episode, Path(tmp) / f"{obj}_twin", args.iters)
            for declared in ((), (f"{obj}={symmetry}",)):
                row = {"object": obj, "episode": episode.name, "symmetry": declared[0] if declared else "none",
                       "plan": _plan(twin, obj, declared, args.n_plan, args.yaw),
                       **_physics_row(twin, episode, declared, args, ctx, simenv, Path(tmp) / f"{obj}_{len(declared)}")}
                rows.append(row)
                print(json.dumps(row, default=float), flush=True)
    result = {"benchmark": "augment_symmetry", "command": " ".join(["python -m benchmarks augment_symmetry", *options]),
              "ranges": {"object_m_m_deg": [OBJECT_XY, OBJECT_XY, args.yaw], "place_m_m_deg": [PLACE_XY, PLACE_XY, args.yaw]},
              "rows": rows, "wall_s": round(time.perf_counter() - t0, 1)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    return 0


def _episodes(ctx: BenchContext) -> list[Path]:
    from benchmarks._viewpoints import clean_episodes, select

    return [ctx.require_shared("data", "sim_pick_place_small"), clean_episodes(ctx, select("high"))[0]]


def _reconstruct(episode: Path, out: Path, iters: int) -> Path:
    from benchmarks._degraded import robot_of
    from manisplat.reconstruct.cli import main as reconstruct

    if reconstruct([str(episode), "--out", str(out), "--iters", str(iters), "-q", "--robot", robot_of(episode)]) != 0:
        raise RuntimeError(f"manisplat-reconstruct failed on {episode}")
    return out


def _plan(twin_dir: Path, obj: str, declared: tuple[str, ...], n: int, yaw_deg: float) -> dict:
    """Validity and the grasp's turn seen from the arm over ``n`` planned samples (seeds 0..n-1)."""
    from manisplat.augment.symmetry import parse_symmetries, yaw_of
    from manisplat.augment.trajectory import AugmentConfig, Rejected, augment_trajectory, augmenter_for, sample_targets
    from manisplat.twin import Twin

    twin = Twin.load(twin_dir)
    augmenter = augmenter_for(twin)
    src = augmenter.src
    spec = next(s for s in src.skills if s.object == obj and s.role == "pick")
    axis = np.r_[augmenter.symmetry_axis(obj), 1.0]
    config = AugmentConfig(symmetries=parse_symmetries(list(declared)))
    yaw = math.radians(yaw_deg)
    reasons: dict[str, int] = {}
    turns, q6 = [], []
    for seed in range(n):
        targets = sample_targets(twin, np.random.default_rng(seed), (OBJECT_XY, OBJECT_XY, yaw), (PLACE_XY, PLACE_XY, yaw))
        try:
            traj = augment_trajectory(twin, targets, config)
        except Rejected as exc:
            reasons[exc.reason] = reasons.get(exc.reason, 0) + 1
            continue
        pick = next(s for s in traj.segments if s["name"] == spec.name)
        D = np.array(pick["T"])
        a_src, a_new = src.objects[obj].T_rest @ axis, targets[obj].T_start @ axis
        azimuth = math.atan2(a_new[1], a_new[0]) - math.atan2(a_src[1], a_src[0])
        turn = yaw_of(D[:3, :3]) - azimuth
        turns.append(abs(math.degrees(math.atan2(math.sin(turn), math.cos(turn)))))
        q6.append(abs(math.degrees(traj.q[pick["frames"][1], 5] - src.q[spec.last, 5])))
    return {"samples": n, "valid": n - sum(reasons.values()), "reasons": reasons,
            "grasp_turn_from_source_deg": _spread(turns), "joint6_change_deg": _spread(q6)}


def _spread(values: list[float]) -> dict:
    if not values:
        return {}
    v = np.asarray(values)
    return {"median": round(float(np.median(v)), 2), "p90": round(float(np.percentile(v, 90)), 2),
            "max": round(float(v.max()), 2)}


def _physics_row(twin_dir: Path, episode: Path, declared: tuple[str, ...], args: argparse.Namespace,
                 ctx: BenchContext, simenv: Path, work: Path) -> dict:
    from benchmarks.bench_augment_shared import _physics
    from manisplat.augment.cli import main as augment
    from manisplat.twin import Twin

    out = work / "aug"
    augment([str(twin_dir), "--n", str(args.n), "--out", str(out), "--workers", "2", "--seed", "0", "-q",
             "--object-range", f"{OBJECT_XY},{OBJECT_XY},{args.yaw}", "--target-range", f"{PLACE_XY},{PLACE_XY},{args.yaw}",
             *(f"--symmetry={d}" for d in declared)])
    report = json.loads((out / "augment_report.json").read_text())
    demos = sorted(d for d in out.iterdir() if d.name.startswith("episode_"))
    row = {"written": report["valid"], "drawn": report["drawn"], "physics_n": 0, "physics_success_clean": 0}
    if demos:
        row.update(_physics(simenv, demos, episode, ctx, Twin.load(twin_dir), work / "sim_input"))
    return row


if __name__ == "__main__":
    sys.exit(main())
