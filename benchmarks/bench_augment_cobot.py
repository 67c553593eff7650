"""Issue 33, item 3: augmentation of a two-arm, three-camera Cobot Magic demonstration, checked in
contact physics. The shared sample is imported as a user does (``manisplat-episode import-act
--calib``), reconstructed with every camera (``manisplat-reconstruct --no-masks``, each object
prompted by one pixel in the head camera's first frame), augmented (``manisplat-augment --n N``)
and exported (``manisplat-episode export --format act-hdf5``: 14-D actions, three cameras); every
exported demonstration is then executed by ``shared/tools/sim/execute_bimanual.py`` in the scene
the sample was made in, with each object's new start and intended end: the source's
(``episode_0.objects.json``, read only to score) moved by the same world transforms the
demonstration moved the twin's object by. For the first ``--render-check`` demonstrations the
simulator also renders every camera twice, at the executed states (``renders_vs_simulator``: what
physics made of the commands; the arms lag their targets, and a wrist camera's whole image moves
with its link) and at the demonstration's own states, posed without physics
(``renders_vs_simulator_same_states``, ``benchmarks/sim_render_bimanual_states.py``: how the twin
draws what it was asked to), and the twin's images are scored against both per region (the
simulator's masks).

``--planned M`` executes M more demonstrations that are planned (the planner manisplat-augment
runs, its default ranges, another seed) but not rendered: their commands, as the export writes
them (each arm's ``a1..a6, a_gripper``), go to the simulator directly. Rendering takes about
86 s per two-arm demonstration on a core, planning under a second. ``--source-seed S`` makes the
source with ``gen_bimanual.py --seed S`` (the sample's task) instead of reading the shared sample.

``MANISPLAT_SIMENV=SIMENV/bin/python python -m benchmarks augment_cobot [--sample cobot_dual_small] [--n 100]
[--planned 0] [--source-seed S] [--iters 1000] [--lambda-mask L] [--lambda-pose L] [--lambda-smooth L]
[--pose-rate-final F] [--light-response auto|on|off] [--render-check 10] [--work DIR] [--out FILE]``
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import cv2
import h5py
import numpy as np

from benchmarks._harness import BENCH_DIR, shared_dir, simulator_python
from benchmarks._simulator import SimJob, run_sim_jobs, sim_tools
from benchmarks.bench_reconstruct_cobot import (CAMERAS, add_ground_truth, add_training_flags, reconstruct,
                                                training_options)
from manisplat.cli_args import shown_value

if TYPE_CHECKING:  # the planner and the twin load torch and the robot model: not for --help
    from manisplat.augment.bimanual import BimanualTrajectory
    from manisplat.twin import Twin

OWN_OPTIONS = True


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks augment_cobot", description=__doc__.splitlines()[0])
    p.add_argument("--sample", default="cobot_dual_small", help="a shared Cobot Magic sample (default cobot_dual_small)")
    p.add_argument("--n", type=int, default=100, help="demonstrations written by manisplat-augment (default 100)")
    p.add_argument("--planned", type=int, default=0, help="more demonstrations planned only, executed in physics (default 0)")
    p.add_argument("--source-seed", type=int, help="make the source with gen_bimanual.py --seed S instead")
    p.add_argument("--iters", type=int, default=1000, help="reconstruction iterations (default 1000)")
    add_training_flags(p)
    p.add_argument("--render-check", type=int, default=10, help="demonstrations the simulator also renders (default 10)")
    p.add_argument("--work", type=Path, help="stage outputs, reused when present (default a temporary folder)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_augment" / "augment_cobot.json")
    args = p.parse_args(argv)
    from manisplat.augment.cli import main as augment_main
    from manisplat.episode.cli import main as episode_main
    from manisplat.twin import Twin

    simenv = simulator_python()
    work = (args.work or Path(tempfile.mkdtemp(prefix="augment_cobot_"))).resolve()
    work.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    stages: dict[str, float] = {}
    source = shared_dir() / "data" / args.sample
    if args.source_seed is not None:
        source = generated_source(simenv, source, args.source_seed, work / "source")

    episode, twin_dir, aug, act = work / "episode", work / "twin", work / "aug", work / "act"
    if not (episode / "episode.json").exists():
        if episode_main(["import-act", str(source / "episode_0.hdf5"), "--calib", str(source / "episode_0.calib.json"),
                         "--out", str(episode)]) != 0:
            raise RuntimeError(f"{args.sample}: import failed")
    prompts = add_ground_truth(episode, source) if not (episode / "gt.npz").exists() else _prompts(episode, source)
    asked = {"lambda_mask": args.lambda_mask, "lambda_pose": args.lambda_pose, "lambda_smooth": args.lambda_smooth,
             "light_response": args.light_response, "fixed_camera_share": args.fixed_camera_share,
             "pose_rate_final": args.pose_rate_final}
    options = training_options(args)
    if not (twin_dir / "twin.json").exists():
        t0 = time.perf_counter()
        recon = reconstruct(episode, twin_dir, CAMERAS, prompts, args.iters, options)
        stages["reconstruct_s"] = round(time.perf_counter() - t0, 1)
        print(json.dumps({k: recon[k] for k in ("wall_s", "ms_per_iter", "pose_anchored")}, default=float), flush=True)
    settings = training_settings(twin_dir, asked, args.iters)
    if not (aug / "augment_report.json").exists():
        t0 = time.perf_counter()
        augment_main([str(twin_dir), "--n", str(args.n), "--out", str(aug), "--workers", "2", "--seed", "0", "-q",
                      "--overwrite"])
        stages["augment_s"] = round(time.perf_counter() - t0, 1)
    report = json.loads((aug / "augment_report.json").read_text())
    episodes = sorted(aug.glob("episode_*"))
    if not episodes:
        raise RuntimeError(f"no demonstration written: {report['valid']} valid of {report['drawn']} drawn "
                           f"({report['reasons']}; {aug / 'augment_report.json'})")
    if not (act / "augmentation.json").exists():
        if episode_main(["export", *map(str, episodes), "--format", "act-hdf5", "--compress", "--out", str(act),
                         "--overwrite"]) != 0:
            raise RuntimeError("export failed")
    t0 = time.perf_counter()
    twin = Twin.load(twin_dir)
    physics = execute_all(simenv, source, twin, episodes, act, work / "physics", args.render_check)
    stages["physics_s"] = round(time.perf_counter() - t0, 1)
    checked = episodes[:args.render_check]
    renders = [score_renders(ep, work / "physics" / f"render_{k}", source) for k, ep in enumerate(checked)]
    posed = render_same_states(simenv, source, twin, checked, act, work / "same_states")
    renders_same = [score_renders(ep, render, source) for ep, render in zip(checked, posed)]
    planned = {}
    if args.planned:
        t0 = time.perf_counter()
        planned = plan_and_execute(simenv, source, twin, args.planned, work / "planned")
        stages["planned_s"] = round(time.perf_counter() - t0, 1)

    result = {
        "benchmark": "augment_cobot", "sample": args.sample, "source_seed": args.source_seed,
        **settings,
        "command": "python -m benchmarks augment_cobot " + " ".join(argv if argv is not None else sys.argv[1:]),
        "augment": {k: report.get(k) for k in ("requested", "drawn", "valid", "validity_rate", "reasons",
                                                "min_arm_clearance_m", "timing_s", "plan_s_per_sample")},
        "physics": summarise_physics(physics),
        **({"planned": planned["plan"], "physics_planned": summarise_physics(planned["physics"])} if planned else {}),
        "renders_vs_simulator": summarise_renders(renders),
        "renders_vs_simulator_same_states": summarise_renders(renders_same), "stages_s": stages,
        "wall_s": round(time.perf_counter() - started, 1), "work": str(work),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    print(json.dumps({k: result.get(k) for k in ("augment", "physics", "physics_planned", "renders_vs_simulator",
                                                 "renders_vs_simulator_same_states")},
                     indent=1, default=float))
    return 0


def training_settings(twin_dir: Path, asked: dict[str, float | str | None], iters: int) -> dict[str, float | bool]:
    """The training settings (``lambda_mask``, ``lambda_pose``, ``lambda_smooth``,
    ``pose_rate_final``, ``light_response``, ``fixed_camera_share``) the twin in ``twin_dir`` was
    reconstructed with; a twin of ``--work`` made with other settings than ``asked`` (None: the
    command's default for three cameras, two of them on the arms, trained ``iters`` iterations) is
    refused. Twins from before ``metrics.json`` recorded a setting were made with the defaults of
    then: mask 1, pose 1, no smoothness loss, a constant pose rate, no light response, every
    camera's frames alike."""
    from manisplat.reconstruct.config import (SHARE_ALIKE, TrainConfig, resolve_fixed_camera_share, resolve_lambda_mask,
                                              resolve_lambda_smooth, resolve_light_response)

    metrics = json.loads((twin_dir / "metrics.json").read_text())
    made = {"lambda_mask": metrics.get("lambda_mask", 1.0), "lambda_pose": metrics.get("lambda_pose", 1.0),
            "lambda_smooth": metrics.get("lambda_smooth", 0.0), "pose_rate_final": metrics.get("pose_rate_final", 1.0),
            "light_response": metrics.get("light_response", False),
            "fixed_camera_share": metrics.get("fixed_camera_share")}
    wanted = {"lambda_mask": resolve_lambda_mask(asked["lambda_mask"], masks_drawn=True),
              "lambda_pose": TrainConfig.lambda_pose if asked["lambda_pose"] is None else asked["lambda_pose"],
              "lambda_smooth": resolve_lambda_smooth(asked["lambda_smooth"], riding=True),
              "pose_rate_final": (TrainConfig.pose_rate_final if asked["pose_rate_final"] is None
                                  else asked["pose_rate_final"]),
              "light_response": resolve_light_response(asked.get("light_response") or "auto", riding=True),
              "fixed_camera_share": resolve_fixed_camera_share(asked["fixed_camera_share"] or "auto", riding=True,
                                                               iters=iters)}
    differ = [f"--{k.replace('_', '-')} {shown_value(made[k], SHARE_ALIKE)}, not {shown_value(wanted[k], SHARE_ALIKE)}"
              for k in made if made[k] != wanted[k]]
    if differ:
        raise RuntimeError(f"{twin_dir} was reconstructed with {'; '.join(differ)}: use another --work")
    return made


def _prompts(episode: Path, source: Path) -> dict[str, tuple[float, float]]:
    """The prompts :func:`add_ground_truth` returned when it prepared ``episode`` (recomputed)."""
    objects = json.loads((source / "episode_0.objects.json").read_text())["objects"]
    camera = json.loads((episode / "episode.json").read_text())["cameras"]["cam_high"]
    K, T_cam_world = np.asarray(camera["K"]), np.linalg.inv(np.asarray(camera["T_mount_cam"]))
    prompts = {}
    for name, o in objects.items():
        if o["role"] == "manipulated":
            u, v, w = K @ (T_cam_world[:3, :3] @ np.asarray(o["T_start"])[:3, 3] + T_cam_world[:3, 3])
            prompts[name] = (u / w, v / w)
    return prompts


def new_objects(source: Path, twin: Twin, new: dict[str, np.ndarray]) -> dict:
    """The simulator's objects.json for an augmented demonstration whose objects' world poses are
    ``new`` (name -> [T, 4, 4]): each manipulated object's source start and end (the simulator's
    frames) moved by the world transforms that took the twin's object from its source start to the
    new start, and from its source end to the new end."""
    spec = json.loads((source / "episode_0.objects.json").read_text())
    objects = {}
    for name, o in spec["objects"].items():
        if o["role"] != "manipulated":
            continue
        src = twin.object_poses[name]
        moved_start = new[name][0] @ np.linalg.inv(src[0])
        moved_end = new[name][-1] @ np.linalg.inv(src[-1])
        objects[name] = {"T_start": (moved_start @ np.asarray(o["T_start"])).tolist(),
                         "T_end": (moved_end @ np.asarray(o["T_end"])).tolist()}
    return {"task": spec["task"], "objects": objects}


def execute_all(simenv: Path, source: Path, twin: Twin, episodes: list[Path], act: Path, out: Path,
                render_check: int) -> list[dict]:
    """execute_bimanual.py on every exported demonstration, two at a time; its JSON per demonstration."""
    def jobs() -> Iterator[SimJob]:
        for k, ep in enumerate(episodes):
            spec = out / f"episode_{k}.objects.json"
            spec.write_text(json.dumps(new_objects(source, twin, dict(np.load(ep / "object_poses.npz")))))
            render = ("--render", str(out / f"render_{k}")) if k < render_check else ()
            yield SimJob("execute_bimanual.py", (str(act / f"episode_{k}.hdf5"), "--objects", str(spec), *render),
                         out / f"episode_{k}.json")

    out.mkdir(parents=True, exist_ok=True)
    run_sim_jobs(simenv, jobs(), ok_codes=(0, 2))
    return [json.loads((out / f"episode_{k}.json").read_text()) | {"episode": ep.name} for k, ep in enumerate(episodes)]


def render_same_states(simenv: Path, source: Path, twin: Twin, episodes: list[Path], act: Path, out: Path) -> list[Path]:
    """The simulator's images of each demonstration's own states, posed without physics
    (``benchmarks/sim_render_bimanual_states.py``): its exported joints (``/observations/qpos``,
    what the twin drew) and each manipulated object's drawn poses in the simulator's frame (moved
    from the source's start as the twin's object was moved from its own). The folders, one per
    demonstration."""
    spec = json.loads((source / "episode_0.objects.json").read_text())
    jobs, renders = [], []
    out.mkdir(parents=True, exist_ok=True)
    for k, ep in enumerate(episodes):
        drawn = np.load(ep / "object_poses.npz")
        with h5py.File(act / f"episode_{k}.hdf5", "r") as f:
            states = {"q": np.asarray(f["observations/qpos"], np.float64)}
        for name, o in spec["objects"].items():
            if o["role"] == "manipulated":
                to_simulator = np.linalg.inv(twin.object_poses[name][0]) @ np.asarray(o["T_start"])
                states[f"T_world_{name}"] = drawn[name] @ to_simulator
        np.savez(out / f"states_{k}.npz", **states)
        renders.append(out / f"render_{k}")
        jobs.append(SimJob(str(BENCH_DIR / "sim_render_bimanual_states.py"),
                           (str(out / f"states_{k}.npz"), "--calib", str(source / "episode_0.calib.json"),
                            "--task", spec["task"], "--render", str(renders[-1])), out / f"render_{k}.json"))
    run_sim_jobs(simenv, jobs)
    return renders


def summarise_physics(physics: list[dict]) -> dict:
    """Counts of execute_bimanual.py's results: success, contacts, largest end errors, the failures."""
    return {"executed": len(physics), "success": sum(r["success"] for r in physics),
            "success_clean": sum(r["success_clean"] for r in physics),
            "arm_arm_contact_steps": sum(r["collisions"]["arm_arm"] for r in physics),
            "demonstrations_with_arm_arm_contact": sum(r["collisions"]["arm_arm"] > 0 for r in physics),
            "final_pos_err_cm_max": {name: max(r["objects"][name]["final_pos_err_cm"] for r in physics)
                                     for name in physics[0]["objects"]} if physics else {},
            "failures": [{"episode": r["episode"], **{k: r[k] for k in ("success", "collisions", "first_collision")},
                          "objects": r["objects"]} for r in physics if not r["success_clean"]]}


def generated_source(simenv: Path, sample: Path, seed: int, out: Path) -> Path:
    """``gen_bimanual.py --task T --seed S`` into ``out`` (once), T the shared sample's task."""
    if not (out / "episode_0.hdf5").exists():
        task = json.loads((sample / "episode_0.objects.json").read_text())["task"]
        subprocess.run([str(simenv), "gen_bimanual.py", "--task", task, "--seed", str(seed), "--out", str(out)],
                       cwd=sim_tools(), check=False, stdout=subprocess.DEVNULL,
                       env={**os.environ, "MUJOCO_GL": "osmesa"})
        if not (out / "episode_0.hdf5").exists():
            raise RuntimeError(f"gen_bimanual.py --task {task} --seed {seed} wrote no episode")
    return out


def plan_and_execute(simenv: Path, source: Path, twin: Twin, n: int, out: Path, seed: int = 1) -> dict:
    """``n`` demonstrations planned as manisplat-augment plans them (its default ranges, samples
    ``seed * 1000003 + k``; not rendered), their commands written as the ACT export writes them
    (``/action``: each arm's ``a1..a6, a_gripper``) and executed by execute_bimanual.py."""
    from manisplat.augment.bimanual import BimanualPlanner
    from manisplat.augment.trajectory import AugmentConfig, Rejected

    planner, config = BimanualPlanner(twin), AugmentConfig(seed=seed)
    valid: list[BimanualTrajectory] = []
    reasons: dict[str, int] = {}
    drawn = 0
    while len(valid) < n and drawn < 3 * n:
        rng = np.random.default_rng(seed * 1_000_003 + drawn)
        drawn += 1
        try:
            valid.append(planner.run(planner.sample_targets(rng), config))
        except Rejected as exc:
            reasons[exc.reason] = reasons.get(exc.reason, 0) + 1
    def jobs() -> Iterator[SimJob]:
        for k, traj in enumerate(valid):
            name = f"planned_{k:04d}"
            with h5py.File(out / f"{name}.hdf5", "w") as f:
                f.create_dataset("action", data=np.concatenate(
                    [np.column_stack([traj.arms[a].action_q, traj.arms[a].action_gripper]) for a in twin.arm_names], 1))
            (out / f"{name}.objects.json").write_text(json.dumps(new_objects(source, twin, traj.object_poses)))
            yield SimJob("execute_bimanual.py", (str(out / f"{name}.hdf5"), "--objects", str(out / f"{name}.objects.json"),
                                                 "--fps", str(twin.fps)), out / f"{name}.json")

    out.mkdir(parents=True, exist_ok=True)
    run_sim_jobs(simenv, jobs(), ok_codes=(0, 2))
    physics = [json.loads((out / f"planned_{k:04d}.json").read_text()) | {"episode": f"planned_{k:04d}"}
               for k in range(len(valid))]
    return {"plan": {"requested": n, "drawn": drawn, "valid": len(valid), "reasons": reasons, "seed": seed,
                     "waited_s": [traj.validation.get("handover", {}).get("waited_s") for traj in valid][:5]},
            "physics": physics}


def score_renders(episode: Path, render: Path, source: Path) -> dict:
    """PSNR (dB) per camera and region of the twin's images of a new demonstration against the
    simulator's renders of its executed states (the simulator's masks say which pixels are robot
    and which are a manipulated object)."""
    from manisplat.episode import Episode

    gt = np.load(source / "episode_0.gt.npz")
    names = gt["label_names"].tolist()
    objects = [k for k, o in json.loads((source / "episode_0.objects.json").read_text())["objects"].items()
               if o["role"] == "manipulated"]
    robot_values = [v for v, n in enumerate(names) if n.split("/")[0] in ("left", "right")]
    object_values = [v for v, n in enumerate(names) if n in {f"object/{o}" for o in objects}]
    ep = Episode.open(episode)
    scores = {}
    for camera in CAMERAS:
        sums = {"full": [0.0, 0], "robot": [0.0, 0], "object": [0.0, 0]}
        for i in range(len(ep)):
            ours = ep.rgb(i, camera).astype(np.float64) / 255
            theirs = cv2.cvtColor(cv2.imread(str(render / camera / "rgb" / f"{i:06d}.png")), cv2.COLOR_BGR2RGB) / 255.0
            labels = cv2.imread(str(render / camera / "masks" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
            error = ((ours - theirs) ** 2).sum(-1)
            for region, where in (("full", np.ones(labels.shape, bool)), ("robot", np.isin(labels, robot_values)),
                                  ("object", np.isin(labels, object_values))):
                sums[region][0] += float(error[where].sum())
                sums[region][1] += int(where.sum()) * 3
        scores[camera] = {region: (round(10 * np.log10(1 / (s / n)), 2) if n else None) for region, (s, n) in sums.items()}
    return scores


def summarise_renders(renders: list[dict]) -> dict:
    """Per camera and region: the mean PSNR over the checked demonstrations."""
    if not renders:
        return {}
    return {camera: {region: round(float(np.mean([r[camera][region] for r in renders if r[camera][region] is not None])), 2)
                     for region in renders[0][camera]} for camera in renders[0]} | {"demonstrations": len(renders)}


if __name__ == "__main__":
    sys.exit(main())
