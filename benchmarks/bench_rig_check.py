"""Issue 33: a Cobot Magic rig's calibration checked against its robots. Each shared sample
(``cobot_dual_small``, ``cobot_handover_small``) is imported as the user does, and for each seed
its calibration is put off as a hand calibration would be: the head camera, the right arm's base
and both wrist cameras' ``T_link6_cam``, each by 0.3 deg about a random axis and 3 mm along
another. The check runs as ``manisplat-reconstruct --no-masks`` runs it
(:func:`manisplat.reconstruct.rig_check.check_rig`: the head camera's masks drawn and the objects
prompted, the training frames); each result is scored against the simulator's calibration (read
only here): the error before, after (what is used) and as fitted, the reported 1-sigma, whether
the truth lies within the reported 2-sigma. Beside it, each wrist camera checked against the
robot alone (no static scene), the check before this one.

``python -m benchmarks rig_check [--samples cobot_dual_small,...] [--seeds 1,2,3,4,5] [--out FILE]``
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._harness import BENCH_DIR, shared_dir
from benchmarks.bench_policy_sim import _seeds

OWN_OPTIONS = True
SAMPLES = ("cobot_dual_small", "cobot_handover_small")
HEAD, WRISTS, MOVED_ARM = "cam_high", ("cam_left_wrist", "cam_right_wrist"), "right"
ERROR_DEG, ERROR_MM = 0.3, 3.0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks rig_check", description=__doc__.splitlines()[0])
    p.add_argument("--samples", default=",".join(SAMPLES), help=f"shared samples (default {','.join(SAMPLES)})")
    p.add_argument("--seeds", type=_seeds, default="1,2,3,4,5", help="calibration error seeds (default 1,2,3,4,5)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_calib" / "rig_check.json")
    args = p.parse_args(argv)
    from benchmarks.bench_reconstruct_cobot import imported_sample  # the pipeline: after --help

    shared = shared_dir()
    rows = []
    t0 = time.perf_counter()
    logging.disable(logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        for sample in args.samples.split(","):
            episode, prompts = imported_sample(shared / "data", sample, Path(tmp))
            for seed in args.seeds:
                rows.append({"sample": sample, "seed": seed, **check_once(episode, prompts, seed)})
                print(json.dumps({k: v for k, v in rows[-1].items() if k != "items"}
                                 | {name: item["after"] for name, item in rows[-1]["items"].items()}), flush=True)
    logging.disable(logging.NOTSET)
    result = {"benchmark": "rig_check",
              "command": "python -m benchmarks rig_check " + " ".join(argv if argv is not None else sys.argv[1:]),
              "error": f"{ERROR_DEG} deg about a random axis and {ERROR_MM} mm along another, on each of the head "
                       f"camera, arm {MOVED_ARM}'s base and both wrist cameras",
              "summary": summary(rows), "rows": rows, "wall_s": round(time.perf_counter() - t0, 1)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    print(json.dumps(result["summary"], indent=1))
    return 0


def _error(rng: np.random.Generator) -> np.ndarray:
    """[4, 4] a rotation of ERROR_DEG about a random axis and a translation of ERROR_MM along another."""
    import torch

    from manisplat.geometry import se3_exp

    axis, direction = rng.normal(size=3), rng.normal(size=3)
    twist = np.concatenate([np.zeros(3), axis / np.linalg.norm(axis) * np.radians(ERROR_DEG)])
    E = se3_exp(torch.as_tensor(twist)).numpy()
    E[:3, 3] = direction / np.linalg.norm(direction) * ERROR_MM / 1000
    return E


def check_once(episode: Path, prompts: dict[str, tuple[float, float]], seed: int) -> dict:
    """The calibration put off (seed), checked as the reconstruction checks it, scored."""
    from manisplat.reconstruct.data import load_episode_data
    from manisplat.reconstruct.extrinsic import refine_extrinsic
    from manisplat.reconstruct.masks import ObjectPrompt, complete_masks
    from manisplat.reconstruct.plan import make_plan
    from manisplat.reconstruct.rig_check import check_rig

    meta_path = episode / "episode.json"
    original = meta_path.read_text()
    meta = json.loads(original)
    rng = np.random.default_rng(seed)
    truth = {HEAD: np.asarray(meta["cameras"][HEAD]["T_mount_cam"]),
             "base": np.asarray(meta["arms"][MOVED_ARM]["T_world_base"]),
             **{c: np.asarray(meta["cameras"][c]["T_mount_cam"]) for c in WRISTS}}
    meta["cameras"][HEAD]["T_mount_cam"] = (truth[HEAD] @ _error(rng)).tolist()
    meta["arms"][MOVED_ARM]["T_world_base"] = (truth["base"] @ _error(rng)).tolist()
    for c in WRISTS:
        meta["cameras"][c]["T_mount_cam"] = (truth[c] @ _error(rng)).tolist()
    meta_path.write_text(json.dumps(meta))
    try:
        start = time.perf_counter()
        data = load_episode_data(episode, camera=HEAD, use_masks=False)
        views = {c: load_episode_data(episode, camera=c, use_masks=False, load_meshes=False) for c in WRISTS}
        for view in views.values():
            view.robot = data.robot
        links = [name for name in data.robot.link_names if data.robot.visuals.get(name)]
        complete_masks(data, links, [ObjectPrompt(name, point=point) for name, point in prompts.items()],
                       progress=False)
        frames = make_plan(data).train_frames
        robot_alone = {c: refine_extrinsic(views[c], frames) for c in WRISTS}
        check = check_rig(data, views, frames)
        wall = time.perf_counter() - start
    finally:
        meta_path.write_text(original)
    items = {HEAD: _scored(truth[HEAD], check.camera),
             f"base {MOVED_ARM}": _scored(truth["base"], check.bases.get(MOVED_ARM)),
             **{c: _scored(truth[c], check.riding.get(c)) for c in WRISTS},
             **{f"{c} (robot alone)": _scored(truth[c], robot_alone[c]) for c in WRISTS}}
    return {"wall_s": round(wall, 1), "items": items}


def _scored(T_true: np.ndarray, c) -> dict | None:
    """Errors (deg, mm) against the truth before, after and as fitted; the reported 1-sigma;
    whether the fitted error lies within the reported 2-sigma."""
    from manisplat.reconstruct.extrinsic import pose_difference

    if c is None:
        return None
    before, after, fitted = (pose_difference(T_true, T) for T in (c.T_before, c.T_after, c.T_fitted))
    return {"before": [round(v, 4) for v in before], "after": [round(v, 4) for v in after],
            "fitted": [round(v, 4) for v in fitted],
            "sigma": [round(c.sigma_rotation_deg, 4), round(c.sigma_translation_mm, 4)], "applied": bool(c.applied),
            "covered": bool(fitted[0] <= 2 * c.sigma_rotation_deg and fitted[1] <= 2 * c.sigma_translation_mm),
            "reason": c.reason}


def summary(rows: list[dict]) -> dict:
    """Per item: the error after the check (median / 90th percentile / worst, deg and mm), how many
    were applied, and the coverage of the reported 2-sigma."""
    out = {}
    for name in rows[0]["items"]:
        scored = [r["items"][name] for r in rows if r["items"][name] is not None]
        if not scored:
            out[name] = None
            continue
        after = np.array([s["after"] for s in scored])
        out[name] = {"n": len(scored), "applied": sum(s["applied"] for s in scored),
                     "covered": sum(s["covered"] for s in scored),
                     "after_deg": [round(float(np.percentile(after[:, 0], q)), 4) for q in (50, 90, 100)],
                     "after_mm": [round(float(np.percentile(after[:, 1], q)), 4) for q in (50, 90, 100)]}
    return out


if __name__ == "__main__":
    raise SystemExit(main())
