"""manisplat-calibrate on MuJoCo episodes (shared/tools/sim gen_calib.py / gen_pick_place.py).

Reads every episode folder under ``$MANISPLAT_CALIB_DATA`` (generated outside the repository,
see the README's Calibration section for the commands). Calibration episodes (with
``board.json``): ``solve_episode`` against ``gt.npz`` ``T_base_cam`` and ``T_link6_board``, next
to the best OpenCV closed form on the same views; a single-axis episode must raise
``DegenerateMotionError``. Moving episodes (no ``board.json``; ``gt.npz`` ``t_recorded``):
``estimate_latency`` against the true offset ``t_recorded - t``.

Rows: episode, kind, result columns (deg, mm, ms).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from benchmarks._harness import BenchContext, MissingBenchmarkData
from manisplat.calib.board import load_board
from manisplat.calib.episode_solve import solve_episode
from manisplat.calib.errors import CalibrationError, DegenerateMotionError
from manisplat.calib.handeye import opencv_closed_forms
from manisplat.calib.latency import estimate_latency
from manisplat.calib.poses import pose_difference
from manisplat.episode import Episode
from manisplat.robot import load_robot

THREADED = False


def _calib_row(path: Path) -> dict:
    spec = load_board(path / "board.json")
    gt = np.load(path / "gt.npz")
    t0 = time.perf_counter()
    try:
        s = solve_episode(path, spec)
    except DegenerateMotionError as exc:
        return {"episode": path.name, "kind": "solve", "result": f"DegenerateMotionError: {str(exc)[:70]}..."}
    secs = time.perf_counter() - t0
    rot, trans = pose_difference(s.result.T_mount_cam, gt["T_base_cam"])
    ep = Episode.open(path)
    robot = load_robot(ep.meta.robot.description, base_dir=path, load_meshes=False)
    A = robot.link_pose(ep.frames.q[[v.index for v in s.views]], "link6").numpy()
    best = None
    for name, res in opencv_closed_forms("base", A, np.stack([v.T_cam_board for v in s.views])).items():
        if not isinstance(res, str):
            e = pose_difference(res[1], gt["T_base_cam"])
            if best is None or e[1] < best[1][1]:
                best = (name, e)
    info = json.loads(str(gt["info"])) if "info" in gt.files else {}
    args = info.get("args", {})
    return {"episode": path.name, "kind": "solve", "views": len(s.views),
            "record_noise": bool(args.get("record_noise", False)), "blur_sigma": args.get("blur_sigma", 0.0),
            "rms_px": s.result.residual_stats()["rms_px"], "rot_err_deg": rot, "trans_err_mm": trans,
            "sigma_deg": s.result.uncertainty()["T_mount_cam_rot_std_deg"],
            "sigma_mm": s.result.uncertainty()["T_mount_cam_trans_std_mm"],
            "best_opencv": None if best is None else best[0],
            "opencv_rot_deg": None if best is None else best[1][0],
            "opencv_trans_mm": None if best is None else best[1][1], "seconds": secs}


def _latency_row(path: Path) -> dict:
    gt = np.load(path / "gt.npz")
    true = float(np.median(gt["t_recorded"] - gt["t"]))
    t0 = time.perf_counter()
    try:
        est = estimate_latency(path)
    except CalibrationError as exc:
        return {"episode": path.name, "kind": "latency", "result": str(exc)[:80]}
    return {"episode": path.name, "kind": "latency", "latency_ms": true * 1000, "estimate_ms": est.latency_s * 1000,
            "error_ms": (est.latency_s - true) * 1000, "sigma_ms": est.std_s * 1000,
            "correlation": est.correlation, "signal": est.signal, "seconds": time.perf_counter() - t0}


def run(ctx: BenchContext) -> list[dict]:
    root = os.environ.get("MANISPLAT_CALIB_DATA")
    if not root or not Path(root).is_dir():
        raise MissingBenchmarkData("set MANISPLAT_CALIB_DATA to a folder of gen_calib / gen_pick_place episodes")
    rows = []
    for path in sorted(p for p in Path(root).iterdir() if (p / "episode.json").is_file() and (p / "gt.npz").is_file()):
        if not Episode.open(path).meta.complete:
            continue
        rows.append(_calib_row(path) if (path / "board.json").is_file() else _latency_row(path))
    return rows
