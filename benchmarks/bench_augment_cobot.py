"""Issue 33, item 3: augmentation of a two-arm, three-camera Cobot Magic demonstration, checked in
contact physics. The shared sample is imported as a user does (``manisplat-episode import-act
--calib``), reconstructed with every camera (``manisplat-reconstruct --no-masks``, each object
prompted by one pixel in the head camera's first frame), augmented (``manisplat-augment --n N``)
and exported (``manisplat-episode export --format act-hdf5``: 14-D actions, three cameras); every
exported demonstration is then executed by ``shared/tools/sim/execute_bimanual.py`` in the scene
the sample was made in, with each object's new start and intended end: the source's
(``episode_0.objects.json``, read only to score) moved by the same world transforms the
demonstration moved the twin's object by. For the first ``--render-check`` demonstrations the
simulator also renders every camera at the executed states, and the twin's images are scored
against them per region (the simulator's masks).

``MANISPLAT_SIMENV=SIMENV/bin/python python -m benchmarks augment_cobot [--sample cobot_dual_small] [--n 100]
[--iters 1000] [--render-check 10] [--work DIR] [--out FILE]``
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

import cv2
import numpy as np

from benchmarks._harness import BENCH_DIR, MissingBenchmarkData, shared_dir
from benchmarks.bench_reconstruct_cobot import CAMERAS, add_ground_truth, reconstruct
from manisplat.augment.cli import main as augment_main
from manisplat.episode import Episode
from manisplat.episode.cli import main as episode_main
from manisplat.twin import Twin

OWN_OPTIONS = True


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks augment_cobot", description=__doc__.splitlines()[0])
    p.add_argument("--sample", default="cobot_dual_small", help="a shared Cobot Magic sample (default cobot_dual_small)")
    p.add_argument("--n", type=int, default=100, help="demonstrations (default 100)")
    p.add_argument("--iters", type=int, default=1000, help="reconstruction iterations (default 1000)")
    p.add_argument("--render-check", type=int, default=10, help="demonstrations the simulator also renders (default 10)")
    p.add_argument("--work", type=Path, help="stage outputs, reused when present (default a temporary folder)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_augment" / "augment_cobot.json")
    args = p.parse_args(argv)
    simenv = os.environ.get("MANISPLAT_SIMENV")
    if not simenv:
        raise MissingBenchmarkData("set MANISPLAT_SIMENV to the python of a venv with mujoco (shared/tools/sim)")
    source = shared_dir() / "data" / args.sample
    work = (args.work or Path(tempfile.mkdtemp(prefix="augment_cobot_"))).resolve()
    work.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    stages: dict[str, float] = {}

    episode, twin_dir, aug, act = work / "episode", work / "twin", work / "aug", work / "act"
    if not (episode / "episode.json").exists():
        if episode_main(["import-act", str(source / "episode_0.hdf5"), "--calib", str(source / "episode_0.calib.json"),
                         "--out", str(episode)]) != 0:
            raise RuntimeError(f"{args.sample}: import failed")
    prompts = add_ground_truth(episode, source) if not (episode / "gt.npz").exists() else _prompts(episode, source)
    if not (twin_dir / "twin.json").exists():
        t0 = time.perf_counter()
        recon = reconstruct(episode, twin_dir, CAMERAS, prompts, args.iters)
        stages["reconstruct_s"] = round(time.perf_counter() - t0, 1)
        print(json.dumps({k: recon[k] for k in ("wall_s", "ms_per_iter", "pose_anchored")}, default=float), flush=True)
    if not (aug / "augment_report.json").exists():
        t0 = time.perf_counter()
        augment_main([str(twin_dir), "--n", str(args.n), "--out", str(aug), "--workers", "2", "--seed", "0", "-q",
                      "--overwrite"])
        stages["augment_s"] = round(time.perf_counter() - t0, 1)
    report = json.loads((aug / "augment_report.json").read_text())
    episodes = sorted(aug.glob("episode_*"))
    if not (act / "augmentation.json").exists():
        if episode_main(["export", *map(str, episodes), "--format", "act-hdf5", "--compress", "--out", str(act),
                         "--overwrite"]) != 0:
            raise RuntimeError("export failed")
    t0 = time.perf_counter()
    physics = execute_all(Path(simenv), source, Twin.load(twin_dir), episodes, act, work / "physics", args.render_check)
    stages["physics_s"] = round(time.perf_counter() - t0, 1)
    renders = [score_renders(ep, work / "physics" / f"render_{k}", source) for k, ep in enumerate(episodes[:args.render_check])]

    result = {
        "benchmark": "augment_cobot", "sample": args.sample,
        "command": "python -m benchmarks augment_cobot " + " ".join(argv if argv is not None else sys.argv[1:]),
        "augment": {k: report.get(k) for k in ("requested", "drawn", "valid", "validity_rate", "reasons",
                                                "min_arm_clearance_m", "timing_s", "plan_s_per_sample")},
        "physics": {"executed": len(physics), "success": sum(r["success"] for r in physics),
                    "success_clean": sum(r["success_clean"] for r in physics),
                    "arm_arm_contact_steps": sum(r["collisions"]["arm_arm"] for r in physics),
                    "demonstrations_with_arm_arm_contact": sum(r["collisions"]["arm_arm"] > 0 for r in physics),
                    "final_pos_err_cm_max": {name: max(r["objects"][name]["final_pos_err_cm"] for r in physics)
                                             for name in physics[0]["objects"]} if physics else {},
                    "failures": [{"episode": r["episode"], **{k: r[k] for k in ("success", "collisions",
                                                                                 "first_collision")},
                                  "objects": r["objects"]} for r in physics if not r["success_clean"]]},
        "renders_vs_simulator": summarise_renders(renders), "stages_s": stages,
        "wall_s": round(time.perf_counter() - started, 1), "work": str(work),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    print(json.dumps({k: result[k] for k in ("augment", "physics", "renders_vs_simulator")}, indent=1, default=float))
    return 0


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


def new_objects(source: Path, twin: Twin, episode: Path) -> dict:
    """The simulator's objects.json for an augmented demonstration: each manipulated object's
    source start and end (the simulator's frames) moved by the world transforms that took the
    twin's object from its source start to the new start, and from its source end to the new end."""
    spec = json.loads((source / "episode_0.objects.json").read_text())
    new = np.load(episode / "object_poses.npz")
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
    tools = source.parent.parent / "tools" / "sim"
    out.mkdir(parents=True, exist_ok=True)
    running: list[tuple[Path, subprocess.Popen]] = []
    results = []
    jobs = list(enumerate(episodes))
    while jobs or running:
        while jobs and len(running) < 2:
            k, ep = jobs.pop(0)
            report = out / f"episode_{k}.json"
            if report.exists():
                continue
            spec = out / f"episode_{k}.objects.json"
            spec.write_text(json.dumps(new_objects(source, twin, ep)))
            command = [str(simenv), "execute_bimanual.py", str(act / f"episode_{k}.hdf5"), "--objects", str(spec),
                       "--json", str(report.with_suffix(".part"))]
            if k < render_check:
                command += ["--render", str(out / f"render_{k}")]
            running.append((report, subprocess.Popen(command, cwd=tools, stdout=subprocess.DEVNULL,
                                                     env={**os.environ, "MUJOCO_GL": "osmesa"})))
        if running:
            report, proc = running.pop(0)
            proc.wait()  # exit 2: the task's self-checks failed, which the JSON says
            report.with_suffix(".part").rename(report)
    for k, ep in enumerate(episodes):
        results.append(json.loads((out / f"episode_{k}.json").read_text()) | {"episode": ep.name})
    return results


def score_renders(episode: Path, render: Path, source: Path) -> dict:
    """PSNR (dB) per camera and region of the twin's images of a new demonstration against the
    simulator's renders of its executed states (the simulator's masks say which pixels are robot
    and which are a manipulated object)."""
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
