"""manisplat-augment end to end on shared/data/sim_pick_place_small: validity, physics, replay, renders.

1. The twin: ``$MANISPLAT_BENCH_RECON`` (a manisplat-reconstruct output of the episode) or a
   reconstruction made here (``--iters 1000``, about 4-5 minutes on 2 cores).
2. ``manisplat-augment --n 100 --workers 2 --seed 0`` (object +-8 cm, +-8 cm, +-45 deg; place
   +-5 cm, +-5 cm, +-45 deg): validity rate with reasons, skill-relative TCP error, time split.
3. Every written episode: ``validate`` and the replay checks of ``manisplat-replay`` at speed 1.
4. Physics (``$MANISPLAT_SIMENV``: the python of a venv with mujoco 4.0.0, see
   shared/tools/sim/README.md; skipped without; ``$MUJOCO_GL``, default osmesa, picks its
   OpenGL): ``execute_episode.py`` on every demonstration:
   success (grasped, carried, left within 1.5 cm / 10 deg of ``T_end``, upright) and collisions.
5. Visual fidelity on the first 5 demonstrations: our renders against the simulator's renders of
   the same new demonstrations (``--render``): PSNR / SSIM on the full image and over the
   simulator's robot and object masks, beside the reconstruction's own held-out figures.

``--quick``: 10 demonstrations, fidelity on 2.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks._harness import BenchContext, MissingBenchmarkData
from benchmarks._simulator import sim_env
from manisplat.twin import Twin

THREADED = False
FIDELITY_DEMOS = 5


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    from manisplat.augment.cli import main as augment
    from manisplat.reconstruct.cli import main as reconstruct

    episode = ctx.require_shared("data", "sim_pick_place_small")
    work = Path(tempfile.mkdtemp(prefix="bench_augment_shared_"))
    recon = Path(os.environ["MANISPLAT_BENCH_RECON"]) if os.environ.get("MANISPLAT_BENCH_RECON") else None
    if recon is None:
        recon = work / "recon"
        assert reconstruct([str(episode), "--out", str(recon), "--iters", "1000", "-q"]) == 0
    n = 10 if ctx.quick else 100
    out = work / "aug"
    augment([str(recon), "--n", str(n), "--out", str(out), "--workers", "2", "--seed", "0", "-q"])
    report = json.loads((out / "augment_report.json").read_text())
    episodes = sorted(p for p in out.iterdir() if p.name.startswith("episode_"))
    row: dict[str, Any] = {
        "row": "augment", "requested": report["requested"], "drawn": report["drawn"], "valid": report["valid"],
        "validity_rate": report["validity_rate"], "reasons": report["reasons"],
        "skill_err_mm_max": report["skill_error_max"]["mm"], "skill_err_deg_max": report["skill_error_max"]["deg"],
        "plan_s": report["timing_s"]["plan"], "render_write_s": report["timing_s"]["render_and_write"],
        "frames": int(sum(_frames(p) for p in episodes)),
    }
    row["render_frames_per_s"] = row["frames"] / max(row["render_write_s"], 1e-9)
    row.update(_checks(episodes))
    recon_metrics = json.loads((recon / "metrics.json").read_text())
    rows = [row, {"row": "reconstruction (object pose, both definitions; pseudo ground truth alone)",
                  **{k: recon_metrics.get(k) for k in ("pose", "pose_anchored", "pose_pseudo")}}]
    simenv = os.environ.get("MANISPLAT_SIMENV")
    if simenv:
        rows[0].update(_physics(Path(simenv), episodes, episode, ctx))
        rows += _fidelity(Path(simenv), episodes[: 2 if ctx.quick else FIDELITY_DEMOS], episode, recon, ctx, work)
    else:
        ctx.notes.append("physics and visual fidelity skipped: set MANISPLAT_SIMENV to a mujoco venv's python")
    ctx.notes.append(f"outputs kept in {work}")
    return rows


def _frames(path: Path) -> int:
    return sum(1 for _ in open(path / "frames.csv")) - 1


def _checks(episodes: list[Path]) -> dict[str, Any]:
    """validate + the replay checks at speed 1 on every episode."""
    from manisplat.drivers.piper.convention import convention_for
    from manisplat.drivers.piper.trajectory import ReplayLimits, check_trajectory, trajectory_from_episode
    from manisplat.episode import Episode, validate
    from manisplat.robot import builtin_piper

    robot, limits = builtin_piper(with_geometry=False), ReplayLimits()
    valid = replayable = 0
    for path in episodes:
        valid += validate(path, decode_images=False).ok
        ep = Episode.open(path)
        traj = trajectory_from_episode(ep, convention_for(ep.meta.robot.description, ep.path), 1.0)
        replayable += check_trajectory(traj, robot, limits) == []
    return {"episodes_valid": valid, "replay_checks_pass": replayable}


def _execute(simenv: Path, episode: Path, parent: Path, ctx: BenchContext, render: Path | None = None) -> dict:
    tools = ctx.shared / "tools" / "sim"
    cmd = [str(simenv), "execute_episode.py", str(episode), "--parent", str(parent)]
    if render is not None:
        cmd += ["--render", str(render)]
    proc = subprocess.run(cmd, cwd=tools, capture_output=True, text=True, env=sim_env())
    if proc.returncode != 0:
        raise MissingBenchmarkData(f"execute_episode.py failed on {episode}: {proc.stderr[-500:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _physics(simenv: Path, episodes: list[Path], parent: Path, ctx: BenchContext,
             source: Twin | None = None, work: Path | None = None) -> dict[str, Any]:
    """Each new demonstration executed in ``parent``'s scene; with ``source`` (the twin, its source
    demonstration the active one) its objects' poses first put in the simulator's object frame
    (:func:`in_simulator_frame`, copies under ``work``)."""
    if source is not None:
        episodes = [in_simulator_frame(p, source, parent, work / p.name) for p in episodes]
    results = [_execute(simenv, p, parent, ctx) for p in episodes]
    pos = np.array([r["final_pos_err_cm"] for r in results])
    rot = np.array([r["final_rot_err_deg"] for r in results])
    failures = {r["episode"]: {k: r[k] for k in ("final_pos_err_cm", "final_rot_err_deg", "upright", "lift_cm",
                                                 "collisions")} for r in results if not r["success_clean"]}
    return {"physics_success": sum(r["success"] for r in results), "physics_success_clean":
            sum(r["success_clean"] for r in results), "physics_n": len(results),
            "physics_success_rate": sum(r["success_clean"] for r in results) / max(len(results), 1),
            "final_pos_err_cm_median": float(np.median(pos)), "final_pos_err_cm_max": float(pos.max()),
            "final_rot_err_deg_median": float(np.median(rot)), "failures": failures}


def in_simulator_frame(episode: Path, source: Twin, parent: Path, out: Path) -> Path:
    """A copy of what ``execute_episode.py`` reads of a new demonstration (``frames.csv``,
    ``episode.json``, ``augmentation.json``) with each object's start and end in the simulator's
    object frame: moved by the same rigid motion the demonstration moved the twin's object by from
    where the twin's source demonstration (``source``, the twin with it active) starts it (``T_sim = T_new T_twin_source^-1 G_source``, ``G_source`` the
    ground truth at the source's first frame, read here only to set the simulator up). The twin's
    object frame keeps the base's axes at the object's first-frame centroid; the simulator's turns
    with the object and sits at its geometric centre: without this, a source object turned by 20
    deg is promised 20 deg off. The per-frame poses the twin drew (``object_poses.npz``, where the
    demonstration has it) are mapped the same way, for ``sim_render_states.py``."""
    from manisplat.augment.frames import from_centre_frame
    from manisplat.augment.writer import OBJECT_POSES_FILE
    from manisplat.reconstruct.data import load_ground_truth

    gt = load_ground_truth(parent)
    out.mkdir(parents=True, exist_ok=True)
    for name in ("frames.csv", "episode.json"):
        shutil.copy(episode / name, out / name)
    augmentation = json.loads((episode / "augmentation.json").read_text())
    to_simulator = {name: np.linalg.inv(source.object_poses[name][0]) @ gt[f"T_base_{name}"][0]
                    for name in augmentation["objects"]}  # the twin's object frame -> the simulator's
    for name, poses in augmentation["objects"].items():
        mapped = from_centre_frame(source, name, np.asarray(list(poses.values()))) @ to_simulator[name]
        augmentation["objects"][name] = {k: T.tolist() for k, T in zip(poses, mapped)}
    (out / "augmentation.json").write_text(json.dumps(augmentation))
    if (episode / OBJECT_POSES_FILE).exists():
        with np.load(episode / OBJECT_POSES_FILE) as drawn:
            np.savez(out / OBJECT_POSES_FILE, **{name: drawn[name] @ to_simulator[name] for name in drawn.files})
    return out


def render_scores(path: Path, sim: Path) -> dict[str, float]:
    """PSNR / SSIM (``psnr_full``, ``psnr_robot``, ``psnr_object``, ``ssim_*``; means over frames) of
    the demonstration ``path``'s images against the simulator's renders of it in ``sim``
    (``execute_episode.py --render``: ``rgb/``, ``masks/``), regions from the simulator's masks."""
    import cv2

    from manisplat.episode import Episode
    from manisplat.reconstruct.metrics import psnr, ssim

    ours = Episode.open(path)
    labels = ours.meta.labels
    robot_values = [v for v, name in labels.items() if name.startswith("robot/")]
    object_values = [v for v, name in labels.items() if name.startswith("object/") and name[7:] in ours.meta.objects]
    scores: dict[str, list[float]] = {}
    sim_rgb = sorted((sim / "rgb").iterdir())
    sim_masks = sorted((sim / "masks").iterdir())
    for i in range(len(ours)):
        pred = torch.from_numpy(ours.rgb(i)).float() / 255
        target = torch.from_numpy(cv2.cvtColor(cv2.imread(str(sim_rgb[i])), cv2.COLOR_BGR2RGB)).float() / 255
        mask = cv2.imread(str(sim_masks[i]), cv2.IMREAD_UNCHANGED)
        regions = {"full": None, "robot": torch.from_numpy(np.isin(mask, robot_values)),
                   "object": torch.from_numpy(np.isin(mask, object_values))}
        for key, region in regions.items():
            scores.setdefault(f"psnr_{key}", []).append(psnr(pred, target, region))
            scores.setdefault(f"ssim_{key}", []).append(ssim(pred, target, region))
    return {"frames": len(ours), **{k: float(np.nanmean(v)) for k, v in scores.items()}}


def _fidelity(simenv: Path, episodes: list[Path], parent: Path, recon: Path, ctx: BenchContext,
              work: Path) -> list[dict[str, Any]]:
    held_out = json.loads((recon / "metrics.json").read_text())
    rows = [{"row": "reconstruction held-out (source demonstration)", **{f"psnr_{k}": v for k, v in
                                                                        held_out["psnr"].items()},
             **{f"ssim_{k}": v for k, v in held_out["ssim"].items()}}]
    for path in episodes:
        sim = work / "sim_render" / path.name
        _execute(simenv, path, parent, ctx, render=sim)
        scores = render_scores(path, sim)
        rows.append({"row": f"new demonstration {path.name} vs the simulator's render", "frames": scores.pop("frames"),
                     **scores})
    return rows
