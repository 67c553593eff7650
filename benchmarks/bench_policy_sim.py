"""Policy in the loop: success of one policy trained on A (source), B (source + augmented), C (oracle), D (B in sim renders).

    python -m benchmarks policy_sim [--source EP] [--n 50 [200]] [--eval-seeds 1000-1049] [--work DIR] [--quick]
        [--augment-start-range DEG] [--augment-sampling even|random] [--state-noise RAD] [--train-seed S[,S...]] [--image-transforms]
        (and the options of --help)

From one source episode of ``gen_pick_place.py`` (default shared/data/sim_pick_place_small), each
data condition trains the same policy (``benchmarks/policy``: ACT-style chunks, small CNN, the
training frames' joint states jittered by 0.1 rad; same budget, once per training seed), then
drives ``policy_env.PickPlaceEnv`` closed loop from the evaluation seeds' start poses (object
within +-8 cm, +-8 cm, +-45 deg; no training demonstration starts there):

- **A** the source demonstration alone;
- **B** the source plus N demonstrations written by ``manisplat-augment`` from a twin that
  ``manisplat-reconstruct`` made of the source (the twin's renders; objects within +-10 cm,
  +-55 deg and the arm's start scattered by up to 10 deg per joint, spread evenly, as
  docs/training-policies.md recommends);
- **C** N scripted demonstrations of ``gen_demos.py`` over the same ranges (the reference: as many
  real demonstrations);
- **D** B's demonstrations with the simulator's renders of the same motions (``execute_episode.py
  --render``): what the images cost against what the trajectories cost.

Everything is read as a user reads it (``manisplat.episode``: rgb, frames.csv's q, gripper and
commanded a1..a6, a_gripper); no ground truth reaches training or the policy; the environment
scores. Each stage's output is kept in ``--work`` and reused when the same command runs again.
Needs ``$MANISPLAT_SIMENV``, the python of a venv with mujoco 4.0.0 (shared/tools/sim/README.md).
Writes ``policy_sim.json`` (and ``policy_sim_quick.json`` with --quick), the heatmaps and a contact
sheet to ``--out`` (default benchmarks/results_policy). With B, the JSON's ``fidelity`` also holds
how the twin drew B's first frames against the simulator's renders of the same starts, by the
start's turn and distance (``benchmarks/policy/fidelity.py``; ``--fidelity-only`` computes just that,
into ``policy_fidelity.json`` and its sheet of the worst starts). Each row's ``coverage`` counts
successes by how far each evaluation start lies from the nearest training demonstration's start
(``benchmarks/policy/coverage.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks._harness import BENCH_DIR, MissingBenchmarkData, machine_info, shared_dir
from manisplat.augment.draws import SAMPLINGS
from manisplat.augment.timing import PROFILES
from manisplat.cli_args import bounded, finite_numbers, positive

OWN_OPTIONS = True  # python -m benchmarks policy_sim [options] calls main()
OBJECT_RANGE = (0.08, 0.08, 45.0)  # m, m, deg: policy_env's reset(seed) ranges
PLACE_RANGE = (0.025, 0.025, 45.0)  # within the 6 cm mat with 1 cm to spare from the source's place
AUGMENT_OBJECT_RANGE = (0.10, 0.10, 55.0)  # m, m, deg: B's and D's object starts, 2 cm and 10 deg past the evaluation's
AUGMENT_START_RANGE = 10.0  # deg: manisplat-augment --start-range, as docs/training-policies.md recommends
STATE_NOISE = 0.1  # rad: the learner's jitter of the training frames' joint states
CONDITIONS = ("A", "B", "C", "D")
ENVS = 2  # environments rendering side by side (one per core)
CHUNK = 16  # actions per predicted chunk: benchmarks.policy.train.Budget.chunk (not imported: --help stays fast)


def _seeds(text: str) -> list[int]:
    """'1000-1049', '1000,1003,1010' or '0,1' -> seeds (distinct, >= 0)."""
    seeds: list[int] = []
    try:
        for part in text.split(","):
            low, _, high = part.partition("-")
            seeds += list(range(int(low), int(high) + 1)) if high else [int(low)]
    except ValueError:
        seeds = []
    if not seeds or len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"{text!r}: distinct seeds >= 0, e.g. 1000-1049 or 0,1")
    return seeds


def _size(text: str) -> tuple[int, int]:
    """'160x120' -> (160, 120)."""
    width, _, height = text.partition("x")
    if not (width.isdigit() and height.isdigit() and int(width) >= 32 and int(height) >= 24):
        raise argparse.ArgumentTypeError(f"{text!r}: WIDTHxHEIGHT in pixels, at least 32x24, e.g. 160x120")
    return int(width), int(height)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks policy_sim", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    p.add_argument("--source", type=Path, help="a gen_pick_place.py episode (default shared/data/sim_pick_place_small)")
    p.add_argument("--n", type=positive(int), nargs="+", help="demonstrations in B, C and D (default 50; --quick 4)")
    p.add_argument("--eval-seeds", type=_seeds, help="evaluation start seeds (default 1000-1049; --quick 1000-1003)")
    p.add_argument("--conditions", default="C,B,A,D", help="which conditions to run, in order (default C,B,A,D)")
    p.add_argument("--steps", type=positive(int), help="training steps per condition (default 9000: 48 passes over 50 demonstrations; --quick 150)")
    p.add_argument("--image-size", type=_size,
                   help="the policy's view of the workspace, WIDTHxHEIGHT (default 160x120: benchmarks.policy.data)")
    p.add_argument("--augment-speed", type=bounded(0.05, 1.0), default=1.0,
                   help="manisplat-augment --speed for B and D: fraction 0.05-1 of the joint limits (default 1.0, its own)")
    p.add_argument("--augment-profile", choices=PROFILES, default=PROFILES[0],
                   help="manisplat-augment --profile for B and D: how re-planned motions are timed "
                        "(default %(default)s)")
    p.add_argument("--augment-object-range", type=finite_numbers((3,)), metavar="X,Y,DEG",
                   default=AUGMENT_OBJECT_RANGE,
                   help="manisplat-augment --object-range for B and D: half-ranges (m, m, deg) of the augmented "
                        "objects' starts (default %s: past the evaluation's 0.08,0.08,45, so that its edges are "
                        "covered from both sides)" % ",".join(f"{v:g}" for v in AUGMENT_OBJECT_RANGE))
    p.add_argument("--augment-start-range", type=bounded(0.0, 90.0), default=AUGMENT_START_RANGE, metavar="DEG",
                   help="manisplat-augment --start-range for B and D: each augmented demonstration's arm starts up "
                        "to +-DEG from the source's start on every joint (default %(default)g; 0: the source's "
                        "start; the evaluation always starts there)")
    p.add_argument("--augment-sampling", choices=SAMPLINGS, default="even",
                   help="manisplat-augment --sampling for B and D: an even spread over the ranges or random draws "
                        "(default %(default)s, its own; even gets its own folders, random keeps those of the runs "
                        "before 2026-12-03)")
    p.add_argument("--twin-iters", type=positive(int), help="reconstruction iterations (default 1000; --quick 300)")
    p.add_argument("--twin-episodes", type=positive(int), default=1,
                   help="demonstrations of the scene the twin is made of: the source and gen_demos.py ones (seeds 501-); "
                        "augmentation still starts from the source alone (default 1)")
    p.add_argument("--object-position-rate", type=positive(), metavar="R",
                   help="manisplat-reconstruct --object-position-rate of the twin (default: the product's; another "
                        "value gets its own twin, demonstrations, policies and rollouts)")
    p.add_argument("--symmetry", action="append", default=[], metavar="OBJECT=ORDER|round",
                   help="manisplat-augment --symmetry for B and D (e.g. box=4: the 4 x 4 cm box's grasps on the face "
                        "nearest the source's wrist; default none)")
    p.add_argument("--train-seed", type=_seeds, default=[0], metavar="S[,S...]",
                   help="the policies' training seeds (default 0): each condition is trained and run once per seed "
                        "and reported per seed and over all of them (one seed against another moves a result by "
                        "up to 18 in 50: compare over two or more)")
    p.add_argument("--state-noise", type=bounded(0.0, 0.5), default=STATE_NOISE, metavar="RAD",
                   help="Gaussian noise (rad) on the joint states of the training frames, every condition "
                        "(default %(default)g; 0: none)")
    p.add_argument("--image-transforms", action="store_true",
                   help="train every condition with LeRobot's image transforms (its --dataset.image_transforms.enable"
                        "=true: three of brightness, contrast, saturation, hue and sharpness jitter per image)")
    p.add_argument("--n-action-steps", type=bounded(1, CHUNK, int), metavar="K",
                   help="run the first K actions of each predicted chunk open loop, then predict again (LeRobot's "
                        "n_action_steps; default: ACT's temporal ensembling, a chunk every step)")
    p.add_argument("--fidelity-only", action="store_true",
                   help="only score the twin's first frames of B's demonstrations against the simulator's renders of "
                        "the same starts, by the start's turn and distance (benchmarks/policy/fidelity.py; about a "
                        "minute once the twin and demonstrations exist), then stop: no policy is trained")
    p.add_argument("--work", type=Path, help="stage outputs, reused when present (default a new temporary folder)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_policy", help="JSON and plots")
    p.add_argument("--quick", action="store_true", help="a smoke run: 4 demonstrations, short training, 4 rollouts")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if min(args.augment_object_range) < 0:
        parser.error(f"--augment-object-range: half-ranges must be >= 0, got {args.augment_object_range}")
    quick = args.quick
    shared = shared_dir()
    source = (args.source or shared / "data" / "sim_pick_place_small").resolve()
    simenv = os.environ.get("MANISPLAT_SIMENV")
    if not (source / "episode.json").exists():
        raise MissingBenchmarkData(f"{source}: not an episode folder")
    if not simenv:
        raise MissingBenchmarkData("set MANISPLAT_SIMENV to the python of a venv with mujoco (shared/tools/sim)")
    conditions = [c.strip() for c in args.conditions.split(",")]
    if set(conditions) - set(CONDITIONS):
        raise SystemExit(f"--conditions: choose among {','.join(CONDITIONS)}")
    ns = sorted(args.n or ([4] if quick else [50]))
    eval_seeds = args.eval_seeds or (list(range(1000, 1004)) if quick else list(range(1000, 1050)))
    steps = args.steps or (150 if quick else 9000)
    work = (args.work or Path(tempfile.mkdtemp(prefix="policy_sim_"))).resolve()
    work.mkdir(parents=True, exist_ok=True)
    print(f"policy_sim: source {source}, N {ns}, evaluation seeds {_seed_text(eval_seeds)}, "
          f"{steps} training steps, work folder {work}", flush=True)

    from benchmarks.policy.stages import Stages

    seeded = [Stages(source=source, work=work, simenv=Path(simenv), tools=shared / "tools" / "sim",
                     object_range=OBJECT_RANGE, place_range=PLACE_RANGE, twin_iters=args.twin_iters or
                     (300 if quick else 1000), image_size=args.image_size, augment_speed=args.augment_speed,
                     augment_profile=args.augment_profile, augment_object_range=args.augment_object_range,
                     twin_episodes=args.twin_episodes, object_position_rate=args.object_position_rate,
                     symmetry=tuple(args.symmetry),
                     train_seed=seed, state_noise=args.state_noise, image_transforms=args.image_transforms,
                     augment_start_range=args.augment_start_range, augment_sampling=args.augment_sampling,
                     action_steps=args.n_action_steps) for seed in args.train_seed]
    started = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    suffix = "_quick" if quick else ""
    if args.fidelity_only:
        for n in ns:
            _write_fidelity(args, argv, seeded[0], n, suffix)
        return 0
    rows: list[dict[str, Any]] = []
    rollouts: dict[str, list] = {}
    fidelity: dict[str, Any] = {}
    for n in ns:
        for condition in conditions:
            if condition == "A" and n != ns[0]:
                continue  # the source alone does not depend on N
            if condition == "B":
                fidelity[seeded[0].key_over_seeds("B", n)] = _print_fidelity(seeded[0].fidelity(n))
            for stages in seeded:
                row, runs = stages.condition(condition, n, steps, eval_seeds, envs=ENVS)
                rows.append(row)
                rollouts[row["condition"]] = runs
                print(f"  {row['condition']}: {row['successes']}/{row['rollouts']} = {row['success_rate']:.0%} "
                      f"(95 % {row['ci95'][0]:.0%}-{row['ci95'][1]:.0%}), trained {row['train_s']:.0f} s", flush=True)
                print("    by the distance to the nearest training start (evaluation half-ranges): " + ", ".join(
                    f"{name} {b['successes']}/{b['starts']}" for name, b in row["coverage"]["bins"].items()), flush=True)
                path = _write(args, argv, seeded, source, eval_seeds, steps, rows, rollouts, fidelity, started, suffix)
    for total in over_seeds(rows):
        print(f"  {total['data']} over training seeds {total['train_seeds']}: {total['successes']}/{total['rollouts']}"
              f" = {total['success_rate']:.0%} ({', '.join(map(str, total['per_seed']))})")
    print(f"wrote {path} ({time.perf_counter() - started:.0f} s)")
    return 0


def over_seeds(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One total per condition's data (rows' ``data``) over the training seeds it ran with: successes
    and rollouts summed, the successes per seed in ``per_seed`` (their spread is the seed's effect)."""
    totals: dict[str, dict[str, Any]] = {}
    for row in rows:
        total = totals.setdefault(row["data"], {"data": row["data"], "train_seeds": [], "per_seed": [],
                                                "successes": 0, "rollouts": 0})
        total["train_seeds"].append(row["train_seed"])
        total["per_seed"].append(row["successes"])
        total["successes"] += row["successes"]
        total["rollouts"] += row["rollouts"]
    for total in totals.values():
        total["success_rate"] = total["successes"] / total["rollouts"]
    return list(totals.values())


def _print_fidelity(report: dict[str, Any]) -> dict[str, Any]:
    """Print :meth:`Stages.fidelity`'s bins; return them."""
    print(f"  the twin's first frames against the simulator's ({report['object']} region dB, outline IoU, "
          "the twin's area over the simulator's, rest dB):")
    for name, b in report["bins"].items():
        print(f"    {name:34s} {b['starts']:3d} starts  {b['object_psnr']:6.2f}  {b['outline_iou']:.3f}  "
              f"{b['area_ratio']:.3f}  {b['rest_psnr']:6.2f}", flush=True)
    return report["bins"]


def _write_fidelity(args: argparse.Namespace, argv: list[str] | None, stages: Any, n: int, suffix: str) -> Path:
    """``--fidelity-only``: B's ``n`` demonstrations scored (:meth:`Stages.fidelity`), the JSON and
    its sheet of the worst starts copied to ``--out`` as ``policy_fidelity{suffix}.json``."""
    report = stages.fidelity(n)
    _print_fidelity(report)
    sheet = args.out / f"policy_fidelity{suffix}.png"
    shutil.copyfile(stages.work / f"fidelity_{n}{stages.variant_tag}.png", sheet)
    result = {"benchmark": "policy_sim --fidelity-only", "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
              "command": "python -m benchmarks policy_sim " + " ".join(argv if argv is not None else sys.argv[1:]),
              "machine": machine_info(), "source": str(stages.source), "n": n, "data": stages.key_over_seeds("B", n),
              **{k: v for k, v in report.items() if k != "sheet"}, "sheet": sheet.name, "work": str(stages.work)}
    path = args.out / f"policy_fidelity{suffix}.json"
    path.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {path} and {sheet.name}")
    return path


def _write(args: argparse.Namespace, argv: list[str] | None, seeded: list[Any], source: Path, eval_seeds: list[int],
           steps: int, rows: list[dict[str, Any]], rollouts: dict[str, list], fidelity: dict[str, Any], started: float,
           suffix: str) -> Path:
    """The results so far (rewritten after every condition and seed): JSON, heatmaps, contact sheet
    (``seeded``: the stages of each training seed, which share their data; ``fidelity``: B's
    images against the simulator's, per B data set)."""
    from benchmarks.policy.report import contact_sheet, heatmaps
    from benchmarks.policy.stages import ENV_OPTIONS

    stages = seeded[0]
    training_starts = {key: starts for each in seeded for key, starts in each.training_starts.items()}
    plots = [heatmaps(rollouts, training_starts, args.out / f"policy_sim_heatmap{suffix}.png"),
             contact_sheet(rollouts, args.out / f"policy_sim_rollouts{suffix}.png")]
    result = {
        "benchmark": "policy_sim", "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "quick": args.quick,
        "command": "python -m benchmarks policy_sim " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": machine_info(), "source": str(source), "eval_seeds": eval_seeds,
        "ranges": {"object_m_m_deg": OBJECT_RANGE, "place_m_m_deg": PLACE_RANGE,
                   "augmented_object_m_m_deg": stages.augment_object_range},
        "budget": stages.budget_of(steps).__dict__, "viewport": stages.viewport.__dict__, "env_options": ENV_OPTIONS,
        "action_steps": stages.action_steps, "train_seeds": args.train_seed, "rows": rows,
        "over_training_seeds": over_seeds(rows),
        "data": {key: report for each in seeded for key, report in each.data_report.items()},
        "fidelity": fidelity,
        "rollouts": {k: [{"seed": r.seed, "phase": r.phase, **{f: r.result[f] for f in (
            "success", "object_start", "dist_to_mat_m", "tilt_deg", "lifted_m", "steps", "failed")}} for r in v]
            for k, v in rollouts.items()},
        "plots": [p.name for p in plots], "wall_s": round(time.perf_counter() - started, 1), "work": str(stages.work),
    }
    path = args.out / f"policy_sim{suffix}.json"
    path.write_text(json.dumps(result, indent=1, default=float) + "\n")
    return path


def _seed_text(seeds: list[int]) -> str:
    return f"{seeds[0]}-{seeds[-1]}" if seeds == list(range(seeds[0], seeds[-1] + 1)) else ",".join(map(str, seeds))


def run(ctx: Any) -> list[dict[str, Any]]:
    """``python -m benchmarks policy_sim`` runs :func:`main` with its own options instead."""
    raise MissingBenchmarkData("run it as: python -m benchmarks policy_sim [options] (see --help)")


if __name__ == "__main__":
    sys.exit(main())
