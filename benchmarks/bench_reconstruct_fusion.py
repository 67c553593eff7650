"""One twin from 1, 5 and 20 demonstrations of one scene: its fidelity where it was recorded, and
at new poses, where the simulator says what the new demonstrations look like (issue 34).

    MANISPLAT_SIMENV=SIMENV/bin/python python -m benchmarks reconstruct_fusion [--counts 1,5,20]
        [--iters 3000] [--demos 5] [--shadow-receivers all|background] [--shadow-casters meshes|gaussians]
        [--rasterize-mode classic|antialiased] [--object-position-rate R] [--lambda-pose W]
        [--pose-rate-final F] [--light-response auto|on|off] [--supersample N] [--work DIR] [--out JSON]

1. **Data** (generated, not committed): ``shared/tools/sim/gen_demos.py --source
   shared/data/sim_pick_place_small --n 20 --seed-start 1 --place-range 0.02 0.02 0.4``: the
   shared scene and camera, the box started anywhere within +-8 cm, +-8 cm, +-45 deg of the
   sample's start and placed within +-2 cm of the mat's centre, turned up to 0.4 rad more.
2. **Twins**: ``manisplat-reconstruct`` of the first 1, 5 and 20 of them (``--iters``, the same
   for each; ``--shadow-receivers``, ``--shadow-casters``, ``--rasterize-mode``,
   ``--light-response``: manisplat-reconstruct's options of those names), each in its own process: wall time, its
   peak resident memory, metrics.json (held-out
   PSNR per region, the mean over episodes and episode_0001's; pose errors; the pose error with
   one offset for every episode).
3. **New poses**: ``manisplat-augment TWIN --sources episode_0001 --n DEMOS --seed 0`` from each
   twin (the same source and samples: the same new demonstrations, up to the few tenths of a
   millimetre the twins' poses of the source differ by, unless a twin's support map refuses a
   sample another accepts: ``new_poses_common_samples`` compares the samples all made), each executed by
   ``execute_episode.py --render``, the object started and aimed in the simulator's own frame
   (:func:`benchmarks.bench_augment_shared.in_simulator_frame`), and drawn by the simulator at
   the states the twin drew (``benchmarks/sim_render_states.py``: the same joints, fingers and
   object poses, posed without physics). Our images against both: PSNR per region (the
   simulator's masks). Against the executed states (``mean``) the figures hold what physics did
   differently (the arm lagging its targets, the object slipping in the pads); against the same
   states (``mean_same_states``) only how the twin draws them: the object region's is the figure
   issue 34 asks for. Each demonstration's view change (``manisplat-augment``'s: how far it turns
   the box from every view the twin's demonstrations had of it, :mod:`manisplat.augment.views`)
   is listed, and ``mean_same_states_seen_views`` averages those within 15 deg. A contact sheet
   shows one new demonstration: both simulator renders beside each twin's.
4. **Registration** of each episode's first frame to the first's (what a fused reconstruction
   starts each object from, :func:`manisplat.reconstruct.register.register_start`), against the
   ground truth's relative pose: rotation (deg) and position (mm) errors per episode.

5. **The state renderer's check**: the first episode's own states drawn by
   ``sim_render_states.py`` against its recorded images (``renderer_check``): what the scoring
   above gives a perfect twin.

With ``--supersample N`` the demonstrations are recorded as a camera would record them: their own
states (from the ground truth, as the renderer's check takes them) drawn ``N`` x ``N`` times finer
and averaged (``sim_render_states.py --supersample``: each pixel the mean over its area, where the
simulator filters its textures by mipmap level) in place of their colour images, depth and masks
kept (``DIR/demos_xN``); the twins learn from those, and the new demonstrations' states and the
renderer's check are drawn the same way. The executed states (``execute_episode.py --render``)
stay drawn by the simulator.

Ground truth is read only by the scoring (metrics.json's pose errors, the simulator's renders,
the renderer's check).
Writes ``benchmarks/results_reconstruct/reconstruct_fusion.json`` and
``reconstruct_fusion_sheet.png``.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._harness import BENCH_DIR, MissingBenchmarkData, machine_info, shared_dir, simulator_python
from benchmarks._simulator import SimJob, run_sim_jobs, sim_env, sim_tools
from manisplat.cli_args import bounded, non_negative, positive, shown_value
from manisplat.reconstruct.config import (LIGHT_RESPONSE_CHOICES, RASTERIZE_MODES, SHADOW_CASTERS, SHADOW_RECEIVERS,
                                          TrainConfig, resolve_light_response)

OWN_OPTIONS = True
SOURCE = "episode_0001"
STATE_RENDERER = BENCH_DIR / "sim_render_states.py"
PEAK_RSS = ("import resource, subprocess, sys; code = subprocess.run(sys.argv[1:]).returncode; "
            "print('peak_rss_kb', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); sys.exit(code)")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks reconstruct_fusion", description=__doc__.splitlines()[0])
    p.add_argument("--counts", default="1,5,20", help="episodes per twin (default 1,5,20)")
    p.add_argument("--iters", type=int, default=3000, help="training iterations of every twin (default 3000)")
    p.add_argument("--demos", type=int, default=5, help="new demonstrations rendered and executed per twin (default 5)")
    p.add_argument("--shadow-receivers", choices=SHADOW_RECEIVERS, default="all",
                   help="manisplat-reconstruct --shadow-receivers of every twin (default all)")
    p.add_argument("--shadow-casters", choices=SHADOW_CASTERS, default="gaussians",
                   help="manisplat-reconstruct --shadow-casters of every twin (default gaussians)")
    p.add_argument("--rasterize-mode", choices=RASTERIZE_MODES, default="classic",
                   help="manisplat-reconstruct --rasterize-mode of every twin (default classic, what auto gives one camera)")
    p.add_argument("--object-position-rate", type=positive(), default=TrainConfig.object_position_rate, metavar="R",
                   help="manisplat-reconstruct --object-position-rate of every twin (default the product's)")
    p.add_argument("--lambda-pose", type=non_negative(), default=TrainConfig.lambda_pose, metavar="W",
                   help="manisplat-reconstruct --lambda-pose of every twin (default the product's)")
    p.add_argument("--pose-rate-final", type=bounded(1e-6, 1.0), default=TrainConfig.pose_rate_final, metavar="F",
                   help="manisplat-reconstruct --pose-rate-final of every twin (default the product's)")
    p.add_argument("--light-response", choices=LIGHT_RESPONSE_CHOICES, default="auto",
                   help="manisplat-reconstruct --light-response of every twin (default auto: off, the camera is fixed)")
    p.add_argument("--supersample", type=int, default=1, metavar="N",
                   help="record the demonstrations and draw the states N x N finer, averaged (default 1: as the "
                        "simulator draws them)")
    p.add_argument("--work", type=Path, help="outputs (default a temporary folder; kept)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_reconstruct" / "reconstruct_fusion.json")
    args = p.parse_args(argv)
    if args.supersample < 1:
        p.error(f"--supersample takes 1 or more, not {args.supersample}")
    simenv = simulator_python()
    counts = [int(c) for c in args.counts.split(",")]
    work = (args.work or Path(tempfile.mkdtemp(prefix="reconstruct_fusion_"))).resolve()
    started = time.perf_counter()
    episodes = _demonstrations(simenv, work / "demos", max(counts))
    if args.supersample > 1:
        episodes = _supersampled(simenv, episodes, work / f"demos_x{args.supersample}", args.supersample)
    twins = {}
    for count in counts:
        twins[count] = _twin(episodes[:count], work / f"twin_{count}", args.iters,
                             {"shadow_receivers": args.shadow_receivers, "shadow_casters": args.shadow_casters,
                              "rasterize_mode": args.rasterize_mode,
                              "object_position_rate": f"{args.object_position_rate:g}",
                              "lambda_pose": f"{args.lambda_pose:g}",
                              "pose_rate_final": f"{args.pose_rate_final:g}",
                              "light_response": shown_value(resolve_light_response(args.light_response, riding=False))})
        print(f"{count} episodes: {json.dumps({k: twins[count][k] for k in ('wall_s', 'peak_rss_mb', 'psnr')})}",
              flush=True)
    for count in counts:
        twins[count]["new_poses"] = _new_poses(simenv, work / f"twin_{count}", work / f"aug_{count}", episodes[0],
                                               args.demos, args.supersample)
        print(f"{count} episodes, new poses: executed {json.dumps(twins[count]['new_poses']['mean'])}, "
              f"same states {json.dumps(twins[count]['new_poses']['mean_same_states'])}", flush=True)
    common = _common_samples({count: work / f"aug_{count}" for count in counts}, twins)
    print(f"the {len(common['samples'])} samples every twin made: {json.dumps(common['mean_same_states'])}", flush=True)
    renderer_check = _renderer_check(simenv, episodes[0], work / "renderer_check", args.supersample)
    print(f"the state renderer on {episodes[0].name}'s own states: {json.dumps(renderer_check)}", flush=True)
    registration = _registration(episodes) if len(episodes) > 1 else None  # one episode: nothing to register
    if registration is not None:
        print(f"registration: rotation error median {registration['rotation_deg_median']:.2f} deg, "
              f"max {registration['rotation_deg_max']:.2f}", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    sheet = args.out.with_name(args.out.stem + "_sheet.png")
    _sheet(work, counts, sheet)
    result = {"benchmark": "reconstruct_fusion", "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
              "command": "python -m benchmarks reconstruct_fusion " + " ".join(argv if argv is not None else sys.argv[1:]),
              "machine": machine_info(), "work": str(work), "iters": args.iters,
              "shadow_receivers": args.shadow_receivers, "shadow_casters": args.shadow_casters,
              "rasterize_mode": args.rasterize_mode, "object_position_rate": args.object_position_rate,
              "lambda_pose": args.lambda_pose, "pose_rate_final": args.pose_rate_final,
              "light_response": args.light_response,
              "supersample": args.supersample, "episodes": [e.name for e in episodes],
              "twins": {str(k): v for k, v in twins.items()},
              "new_poses_common_samples": common, "renderer_check": renderer_check, "registration": registration,
              "sheet": sheet.name, "wall_s": round(time.perf_counter() - started, 1)}
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


def _demonstrations(simenv: Path, out: Path, n: int) -> list[Path]:
    """``n`` scripted demonstrations of the shared scene (made once; kept in ``out``)."""
    found = sorted(p for p in out.glob("episode_*") if (p / "episode.json").exists()) if out.exists() else []
    if len(found) < n:
        cmd = [str(simenv), "gen_demos.py", "--source", str(shared_dir() / "data" / "sim_pick_place_small"),
               "--out", str(out), "--n", str(n + 5), "--seed-start", "1", "--place-range", "0.02", "0.02", "0.4"]
        subprocess.run(cmd, cwd=sim_tools(), check=True, stdout=subprocess.DEVNULL,
                       env=sim_env())
        found = sorted(p for p in out.glob("episode_*") if (p / "episode.json").exists())
    if len(found) < n:
        raise MissingBenchmarkData(f"gen_demos.py made {len(found)} demonstrations in {out}, {n} needed")
    return found[:n]


def _supersampled(simenv: Path, episodes: list[Path], out: Path, n: int) -> list[Path]:
    """Copies of ``episodes`` in ``out`` whose colour images are their own states drawn ``n`` x
    ``n`` finer and averaged (depth, masks and the rest kept; made once, kept)."""
    todo = [episode for episode in episodes if not (out / episode.name / "episode.json").exists()]
    for episode in todo:
        _ground_truth_states(episode, out / "states" / episode.name)
    run_sim_jobs(simenv, [SimJob(str(STATE_RENDERER), (str(out / "states" / episode.name), "--parent", str(episode),
                                                       "--render", str(out / "drawn" / episode.name),
                                                       "--supersample", str(n)),
                                 out / "drawn" / episode.name / "render.json") for episode in todo])
    for episode in todo:
        part = out / (episode.name + ".part")
        shutil.rmtree(part, ignore_errors=True)
        shutil.copytree(episode, part)
        recorded = sorted((part / "rgb").iterdir())
        drawn = sorted((out / "drawn" / episode.name / "rgb").iterdir())
        if [p.name for p in recorded] != [p.name for p in drawn]:
            raise MissingBenchmarkData(f"{episode}: its rgb/ and the supersampled drawing's differ in their files")
        for image in drawn:
            shutil.copy(image, part / "rgb" / image.name)
        part.rename(out / episode.name)
    return [out / episode.name for episode in episodes]


def _ground_truth_states(episode: Path, out: Path) -> None:
    """``episode``'s own states from its ground truth (joints, gap, object poses) as
    ``sim_render_states.py`` reads them, in ``out``."""
    from manisplat.augment.writer import OBJECT_POSES_FILE
    from manisplat.episode import Episode

    recorded = Episode.open(episode)
    gt = recorded.gt()
    out.mkdir(parents=True, exist_ok=True)
    shutil.copy(episode / "episode.json", out / "episode.json")
    with open(out / "frames.csv", "w", newline="") as f:
        rows = csv.writer(f)
        rows.writerow(["index", "t", *(f"q{j}" for j in range(1, 7)), "gripper"])
        rows.writerows([k, t, *q, gap] for k, (t, q, gap) in enumerate(zip(gt["t"], gt["q"], gt["gripper"])))
    np.savez(out / OBJECT_POSES_FILE, **{name: gt[f"T_base_{name}"] for name in recorded.meta.objects})


def _twin(episodes: list[Path], out: Path, iters: int, options: dict[str, str]) -> dict:
    """Reconstruct ``episodes`` into ``out`` in a process of its own, with manisplat-reconstruct's
    ``options`` (``shadow_receivers``, ``shadow_casters``, ``rasterize_mode``,
    ``object_position_rate``, ``lambda_pose``, ``pose_rate_final``, ``light_response``; a twin made
    before a setting was recorded: the default of then); its time, peak memory, figures."""
    if (out / "metrics.json").exists():
        metrics = json.loads((out / "metrics.json").read_text())
        light = metrics.get("light") or {}
        made = {"shadow_receivers": light.get("receivers", "background"),
                "shadow_casters": light.get("casters", "gaussians"),
                "rasterize_mode": metrics.get("rasterize_mode", "classic"),
                "object_position_rate": f"{metrics.get('object_position_rate', 1.0):g}",
                "lambda_pose": f"{metrics.get('lambda_pose', 1.0):g}",
                "pose_rate_final": f"{metrics.get('pose_rate_final', 1.0):g}",
                "light_response": shown_value(metrics.get("light_response", False))}
        if made != options:
            raise MissingBenchmarkData(f"{out} was made with {made}, not {options}: use another --work")
    else:
        from benchmarks._degraded import robot_of

        robot = robot_of(shared_dir() / "data" / "sim_pick_place_small")  # the demonstrations live elsewhere
        cmd = [sys.executable, "-c", PEAK_RSS, sys.executable, "-m", "manisplat.reconstruct.cli",
               *map(str, episodes), "--out", str(out), "--iters", str(iters), "--robot", robot,
               *[a for key, value in options.items() for a in (f"--{key.replace('_', '-')}", value)], "--overwrite", "-q"]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            raise MissingBenchmarkData(f"manisplat-reconstruct failed on {len(episodes)} episodes: {proc.stderr[-800:]}")
        peak = next(int(line.split()[1]) for line in proc.stdout.splitlines() if line.startswith("peak_rss_kb"))
        (out / "bench_run.json").write_text(json.dumps({"wall_s": time.perf_counter() - t0, "peak_rss_kb": peak}))
    run = json.loads((out / "bench_run.json").read_text())
    m = json.loads((out / "metrics.json").read_text())
    first = m["episodes"][SOURCE] if "episodes" in m else m
    return {"episodes": len(episodes), "wall_s": round(run["wall_s"], 1), "peak_rss_mb": round(run["peak_rss_kb"] / 1024),
            "ms_per_iter": m.get("ms_per_iter"), "psnr": m["psnr"], "psnr_colour_fitted": m.get("psnr_colour_fitted"),
            "psnr_source_episode": first["psnr"], "shadow": m.get("shadow"), "pose": m.get("pose"),
            "pose_anchored": _anchored(m.get("pose_anchored")), "pose_one_offset": m.get("pose_one_offset")}


def _anchored(anchored: dict | None) -> dict | None:
    return None if anchored is None else {k: {"et_cm": v["et_cm"], "er_deg": v["er_deg"], "final_et_cm": v["final"]["et_cm"]}
                                          for k, v in anchored.items()}


def _new_poses(simenv: Path, twin: Path, out: Path, parent: Path, demos: int, supersample: int = 1) -> dict:
    """``demos`` new demonstrations from ``twin`` (source episode_0001, seed 0), executed by the
    simulator with contact physics and drawn by it twice: the states physics made of their commands
    (``sim_render``) and their own states, posed without physics (``sim_states``, ``supersample``
    x ``supersample`` finer and averaged); our renders scored against both."""
    from benchmarks.bench_augment_shared import in_simulator_frame, render_scores
    from manisplat.augment.cli import main as augment
    from manisplat.augment.views import UNSEEN_WARN_DEG
    from manisplat.twin import Twin

    if not (out / "augment_report.json").exists():
        if augment([str(twin), "--n", str(demos), "--out", str(out), "--sources", SOURCE, "--seed", "0",
                    "--overwrite", "-q"]) != 0:
            raise MissingBenchmarkData(f"manisplat-augment failed on {twin}")
    source = Twin.load(twin).source(SOURCE)
    episodes = sorted(out.glob("episode_*"))
    inputs = [in_simulator_frame(path, source, parent, out / "sim_input" / path.name) for path in episodes]
    executed = [SimJob("execute_episode.py", (str(copy), "--parent", str(parent), "--render",
                                              str(out / "sim_render" / path.name)),
                       out / "sim_render" / path.name / "physics.json") for path, copy in zip(episodes, inputs)]
    posed = [SimJob(str(STATE_RENDERER), (str(copy), "--parent", str(parent), "--render",
                                          str(out / "sim_states" / path.name), "--supersample", str(supersample)),
                    out / "sim_states" / path.name / "render.json") for path, copy in zip(episodes, inputs)]
    run_sim_jobs(simenv, executed + posed)
    view_change = {s["episode"]: s.get("view_change_deg", {}).get("box")
                   for s in json.loads((out / "augment_report.json").read_text())["samples"] if s["valid"]}
    rows = {}
    for path, job in zip(episodes, executed):
        physics = json.loads(job.report.read_text())
        rows[path.name] = {**render_scores(path, out / "sim_render" / path.name),
                           "same_states": render_scores(path, out / "sim_states" / path.name),
                           "view_change_deg": view_change.get(path.name),
                           "success_clean": physics["success_clean"], "final_pos_err_cm": physics["final_pos_err_cm"]}
    keys = [k for k in next(iter(rows.values())) if k.startswith(("psnr_", "ssim_"))]
    seen = [r["same_states"] for r in rows.values() if r["view_change_deg"] is not None
            and r["view_change_deg"] <= UNSEEN_WARN_DEG]
    return {"demonstrations": rows, "mean": _means(list(rows.values()), keys),
            "mean_same_states": _means([r["same_states"] for r in rows.values()], keys),
            "mean_same_states_seen_views": {"demonstrations": len(seen), **(_means(seen, keys) if seen else {})},
            "success_clean": sum(r["success_clean"] for r in rows.values())}


def _common_samples(augmented: dict[int, Path], twins: dict[int, dict]) -> dict:
    """The new poses' figures per twin over the samples (``manisplat-augment`` seeds) that every
    twin turned into a demonstration: a twin's support map can refuse a sample another accepts,
    and then their five demonstrations are not all the same ones."""
    reports = {count: json.loads((folder / "augment_report.json").read_text()) for count, folder in augmented.items()}
    episode_of = {count: {s["seed"]: s["episode"] for s in report["samples"] if s["valid"]}
                  for count, report in reports.items()}
    seeds = sorted(set.intersection(*(set(found) for found in episode_of.values())))
    means: dict[str, dict[str, dict[str, float]]] = {"mean": {}, "mean_same_states": {}}
    for count, found in episode_of.items():
        rows = [twins[count]["new_poses"]["demonstrations"][found[seed]] for seed in seeds]
        keys = [k for k in rows[0] if k.startswith(("psnr_", "ssim_"))] if rows else []
        means["mean"][str(count)] = _means(rows, keys)
        means["mean_same_states"][str(count)] = _means([r["same_states"] for r in rows], keys)
    return {"samples": seeds, **means}


def _means(rows: list[dict], keys: list[str]) -> dict[str, float]:
    """The mean of each of ``keys`` over ``rows``, rounded to 3 decimals."""
    return {k: round(float(np.mean([r[k] for r in rows])), 3) for k in keys}


def _renderer_check(simenv: Path, episode: Path, work: Path, supersample: int = 1) -> dict[str, float]:
    """What the new poses' scoring gives a perfect twin: ``episode``'s own states (its ground
    truth's joints, gap and object poses) drawn by ``sim_render_states.py`` (``supersample`` x
    ``supersample`` finer and averaged), scored against its recorded images as the new
    demonstrations are scored against the simulator's."""
    from benchmarks.bench_augment_shared import render_scores

    states = work / "states"
    _ground_truth_states(episode, states)
    render = work / "render"
    run_sim_jobs(simenv, [SimJob(str(STATE_RENDERER), (str(states), "--parent", str(episode), "--render", str(render),
                                                       "--supersample", str(supersample)), render / "render.json")])
    return {k: round(v, 2) for k, v in render_scores(episode, render).items() if k.startswith("psnr_")}


def _registration(episodes: list[Path]) -> dict:
    """Each later episode's object start as registered to the first's and those before it
    (:func:`~manisplat.reconstruct.register.register_starts`, as a fused reconstruction does),
    against the truth: ``T_k = G_k G_0^-1 T_0`` with ``G`` the ground-truth pose at the first frame and ``T_0`` the
    canonical frame (the first episode's points' centroid, the base's axes)."""
    from benchmarks._degraded import robot_of
    from manisplat.reconstruct.data import load_episode_data, load_ground_truth
    from manisplat.reconstruct.init import object_points
    from manisplat.reconstruct.register import register_starts

    robot = robot_of(shared_dir() / "data" / "sim_pick_place_small")
    first = load_episode_data(episodes[0], robot=robot)
    name, label = next((n, v) for v, n in first.labels.objects.items())
    p0, c0, _ = object_points(first, label, 0)
    T0 = np.eye(4)
    T0[:3, 3] = p0.mean(0).numpy()
    G0 = load_ground_truth(episodes[0])[f"T_base_{name}"][0]
    rows = {}
    seen = [object_points(load_episode_data(path, robot=robot), label, 0)[:2] for path in episodes[1:]]
    registered = register_starts(p0.numpy() - T0[:3, 3], c0.numpy(), [(p.numpy(), c.numpy()) for p, c in seen])
    for path, reg in zip(episodes[1:], registered):
        found = reg.T_base_obj
        truth = load_ground_truth(path)[f"T_base_{name}"][0] @ np.linalg.inv(G0) @ T0
        cos = (np.trace(truth[:3, :3].T @ found[:3, :3]) - 1) / 2
        rows[path.name] = {"rotation_deg": round(float(np.degrees(np.arccos(np.clip(cos, -1, 1)))), 3),
                           "position_mm": round(float(1e3 * np.linalg.norm(truth[:3, 3] - found[:3, 3])), 2)}
    rot = [r["rotation_deg"] for r in rows.values()]
    pos = [r["position_mm"] for r in rows.values()]
    return {"object": name, "episodes": rows, "rotation_deg_median": float(np.median(rot)),
            "rotation_deg_max": float(max(rot)), "position_mm_median": float(np.median(pos)),
            "position_mm_max": float(max(pos))}


def _sheet(work: Path, counts: list[int], path: Path, demo: str = "episode_0000") -> None:
    """Three frames of one new demonstration in columns: the simulator's render of what physics made
    of it, of its own states, then each twin's."""
    import cv2

    aug = work / f"aug_{counts[0]}"
    executed = sorted((aug / "sim_render" / demo / "rgb").iterdir())
    posed = sorted((aug / "sim_states" / demo / "rgb").iterdir())
    ours = {c: sorted((work / f"aug_{c}" / demo / "rgb").iterdir()) for c in counts}
    n = min(len(executed), len(posed), *(len(v) for v in ours.values()))
    rows = []
    for i in (n // 4, n // 2, 3 * n // 4):
        tiles = [cv2.imread(str(executed[i])), cv2.imread(str(posed[i]))] + [cv2.imread(str(ours[c][i])) for c in counts]
        for tile, label in zip(tiles, ["simulator, executed", "simulator, same states",
                                       *(f"twin of {c} episode{'s' * (c > 1)}" for c in counts)]):
            cv2.putText(tile, f"{label}  frame {i}", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1,
                        cv2.LINE_AA)
        rows.append(np.concatenate(tiles, axis=1))
    if not cv2.imwrite(str(path), np.concatenate(rows, axis=0)):
        raise MissingBenchmarkData(f"could not write {path}")


if __name__ == "__main__":
    sys.exit(main())
