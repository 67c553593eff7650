"""What a new demonstration's commands cost in contact physics: the source's command relation kept
(``manisplat-augment``'s commands) against the next frame's joints (its commands before).

    MANISPLAT_SIMENV=SIMENV/bin/python python -m benchmarks augment_commands [--source EP] [--twin DIR]
        [--n 40] [--work DIR] [--out JSON]

From a ``gen_pick_place.py`` episode (default shared/data/sim_pick_place_small) and its twin
(``--twin``, else ``manisplat-reconstruct --iters 1000`` here), ``--n`` demonstrations are planned
twice from the same samples (``AugmentConfig(seed=1)``, sample ``k`` drawn from
``default_rng(1_000_003 + k)``, manisplat-augment's default ranges): once with the twin's
:class:`~manisplat.twin.commands.CommandRelation` (every command led by the source's lead, skills
pressing as the source pressed) and once without it (every command the next frame's joints).
Each is executed by ``shared/tools/sim/execute_episode.py`` from its commands (``frames.csv``'s
``a1..a6, a_gripper`` and ``augmentation.json``'s object poses; no images are rendered): success
(the object grasped, carried, left within 1.5 cm / 10 deg of where the demonstration leaves it,
upright), clean (no robot contact with the table, the mug or the object but by the fingers), the
final errors. Writes ``benchmarks/results_augment/augment_commands.json``.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks._harness import BENCH_DIR, MissingBenchmarkData, machine_info, shared_dir, simulator_python
from benchmarks._simulator import SimJob, run_sim_jobs

OWN_OPTIONS = True
MODES = ("recorded", "next_frame")
SAMPLE_SEED = 1_000_003


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks augment_commands", description=__doc__.splitlines()[0])
    p.add_argument("--source", type=Path, help="a gen_pick_place.py episode (default shared/data/sim_pick_place_small)")
    p.add_argument("--twin", type=Path, help="its manisplat-reconstruct output (default: made here, --iters 1000)")
    p.add_argument("--n", type=int, default=40, help="demonstrations planned per mode (default 40)")
    p.add_argument("--work", type=Path, help="outputs (default a temporary folder)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_augment" / "augment_commands.json")
    args = p.parse_args(argv)
    simenv = simulator_python()
    source = (args.source or shared_dir() / "data" / "sim_pick_place_small").resolve()
    if not (source / "episode.json").exists():
        raise MissingBenchmarkData(f"{source}: not an episode folder")
    work = (args.work or Path(tempfile.mkdtemp(prefix="augment_commands_"))).resolve()
    started = time.perf_counter()

    from manisplat.reconstruct.cli import main as reconstruct
    from manisplat.twin import Twin

    twin_dir = args.twin
    if twin_dir is None:
        twin_dir = work / "twin"
        if not (twin_dir / "twin.json").exists() and reconstruct([str(source), "--out", str(twin_dir), "--iters",
                                                                  "1000", "-q"]) != 0:
            raise MissingBenchmarkData(f"manisplat-reconstruct failed on {source}")
    twin = Twin.load(twin_dir)
    if twin.commands is None:
        raise MissingBenchmarkData(f"{twin_dir}: the twin keeps no recorded commands (reconstruct it again)")
    relation = twin.commands
    modes = {}
    for mode in MODES:
        # a twin object of its own (augment_trajectory keeps a planner per twin)
        planned = twin.with_demonstration(replace(twin.demonstration, commands=relation if mode == "recorded" else None))
        plan = _plan(planned, args.n)
        physics = _execute_all(simenv, source, plan.pop("trajectories"), work / mode)
        modes[mode] = {**plan, **_summary(physics), "runs": physics}
        print(f"{mode}: {modes[mode]['success']}/{modes[mode]['executed']} succeed, "
              f"{modes[mode]['success_clean']} clean", flush=True)
    result = {"benchmark": "augment_commands", "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
              "command": "python -m benchmarks augment_commands " + " ".join(argv if argv is not None else sys.argv[1:]),
              "machine": machine_info(), "source": str(source), "twin": str(twin_dir),
              "relation": {"lead_frames": relation.lead, "press_max_rad": float(np.abs(relation.press).max())},
              "modes": modes, "wall_s": round(time.perf_counter() - started, 1)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


def _plan(twin, n: int) -> dict:
    """``n`` valid demonstrations of the twin as manisplat-augment plans them, samples drawn in order."""
    from manisplat.augment.sampling import sample_targets
    from manisplat.augment.trajectory import AugmentConfig, Rejected, augment_trajectory

    trajectories, reasons, drawn = [], {}, 0
    while len(trajectories) < n and drawn < 3 * n:
        rng = np.random.default_rng(SAMPLE_SEED + drawn)
        drawn += 1
        try:
            trajectories.append(augment_trajectory(twin, sample_targets(twin, rng), AugmentConfig(seed=1)))
        except Rejected as exc:
            reasons[exc.reason] = reasons.get(exc.reason, 0) + 1
    return {"drawn": drawn, "valid": len(trajectories), "reasons": reasons, "trajectories": trajectories}


def _execute_all(simenv: Path, parent: Path, trajectories: list, out: Path) -> list[dict]:
    """execute_episode.py on each demonstration's commands, two at a time; its JSON per
    demonstration (the commands are written afresh, so are their reports)."""
    jobs = []
    for k, traj in enumerate(trajectories):
        folder = out / f"demo_{k:04d}"
        folder.mkdir(parents=True, exist_ok=True)
        _write_commands(folder, traj)
        (folder / "physics.json").unlink(missing_ok=True)
        jobs.append(SimJob("execute_episode.py", (str(folder), "--parent", str(parent)), folder / "physics.json"))
    run_sim_jobs(simenv, jobs)
    return [json.loads(job.report.read_text()) for job in jobs]


def _write_commands(folder: Path, traj) -> None:
    """What execute_episode.py reads of a demonstration: frames.csv's times and commands, and
    augmentation.json's object poses (base frame)."""
    with open(folder / "frames.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["index", "t", "a1", "a2", "a3", "a4", "a5", "a6", "a_gripper"])
        for k in range(len(traj.t)):
            writer.writerow([k, repr(float(traj.t[k])), *(repr(float(v)) for v in traj.action_q[k]),
                             repr(float(traj.action_gripper[k]))])
    (folder / "augmentation.json").write_text(json.dumps({"objects": traj.objects}))


def _summary(physics: list[dict]) -> dict:
    pos = np.array([r["final_pos_err_cm"] for r in physics]) if physics else np.zeros(1)
    return {"executed": len(physics), "success": sum(r["success"] for r in physics),
            "success_clean": sum(r["success_clean"] for r in physics),
            "final_pos_err_cm_median": float(np.median(pos)), "final_pos_err_cm_max": float(pos.max()),
            "failures": {r["episode"]: {k: r[k] for k in ("final_pos_err_cm", "final_rot_err_deg", "upright",
                                                          "collisions")}
                         for r in physics if not r["success_clean"]}}


if __name__ == "__main__":
    sys.exit(main())
