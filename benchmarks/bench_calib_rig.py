"""Two-arm rig calibration (manisplat-calibrate solve-rig) against exact ground truth.

Part ``synthetic``: per trial, a new Cobot Magic-like rig episode rendered by the project
(``manisplat.calib.synth_rig``: two built-in PiPERs 0.6 m apart turned 3 deg towards each other, a
640x480 head camera (f 1000 px) 0.75 m up behind them, a 480x360 camera (f 360 px) on each link6,
a 7x5 ChArUco board still on the table; blur 0.6 px, grey-level noise 1.5; 12 frames, each arm
at a new random pose in which its wrist camera sees the board) solved by ``solve_rig`` in the
default world (the midpoint of the bases). Errors of each arm's ``T_world_base`` (the same for both:
the world is their midpoint), of the right base seen from the left one, of each wrist camera's
``T_link6_cam`` and of the head camera's ``T_world_cam``: median and max over the trials.

Part ``convention`` (needs ``shared/data/cobot_*_small``): the world ``solve-rig`` chooses by
default (``bases``), built from the simulator's true arm bases (``*.gt.npz``), against the world
frame of the Cobot Magic calibration sidecar: the difference should be zero.

Rows: part, quantity, trials, rot_med_deg, rot_max_deg, trans_med_mm, trans_max_mm, seconds.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._harness import BenchContext
from manisplat.calib.board import BoardSpec
from manisplat.calib.poses import inv_T, pose_difference
from manisplat.calib.rig import world_in_board
from manisplat.calib.synth_rig import ARMS, HEAD, WRIST, write_rig_episode

THREADED = False
FRAMES = 12


def _trial(spec: BoardSpec, seed: int) -> tuple[dict[str, tuple[float, float]], float]:
    from manisplat.calib.rig import solve_rig

    with tempfile.TemporaryDirectory() as tmp:
        truth = write_rig_episode(Path(tmp) / "ep", spec, FRAMES, np.random.default_rng(seed))
        start = time.perf_counter()
        solved = solve_rig(Path(tmp) / "ep", spec)
        seconds = time.perf_counter() - start
    errors = {f"T_world_base {arm}": pose_difference(solved.T_world_base[arm], truth.T_world_base[arm]) for arm in ARMS}
    errors.update({f"T_link6_cam {WRIST[arm]}": pose_difference(solved.cameras[WRIST[arm]].T_mount_cam,
                                                                truth.T_link6_cam[arm]) for arm in ARMS})
    left, right = solved.T_world_base["left"], solved.T_world_base["right"]
    errors["right base in the left base"] = pose_difference(
        inv_T(left) @ right, inv_T(truth.T_world_base["left"]) @ truth.T_world_base["right"])
    errors[f"T_world_cam {HEAD}"] = pose_difference(solved.cameras[HEAD].T_mount_cam, truth.T_world_head)
    return errors, seconds


def _convention_rows(ctx: BenchContext) -> list[dict]:
    rows = []
    for sample in ("cobot_handover_small", "cobot_dual_small"):
        path = ctx.shared / "data" / sample / "episode_0.gt.npz"
        if not path.is_file():
            ctx.notes.append(f"{path} not found: part convention skipped for {sample}")
            continue
        with np.load(path) as gt:
            bases = {arm: gt[f"T_world_base_{arm}"] for arm in ARMS}
        rot, mm = pose_difference(world_in_board("bases", bases, {}), np.eye(4))
        rows.append({"part": "convention", "quantity": f"{sample}: bases world vs the sidecar's world", "trials": 1,
                     "rot_med_deg": rot, "rot_max_deg": rot, "trans_med_mm": mm, "trans_max_mm": mm})
    return rows


def run(ctx: BenchContext) -> list[dict]:
    spec = BoardSpec()
    trials = 2 if ctx.quick else 10
    per: dict[str, list[tuple[float, float]]] = {}
    seconds = []
    for seed in range(trials):
        errors, secs = _trial(spec, 100 + seed)
        seconds.append(secs)
        for name, e in errors.items():
            per.setdefault(name, []).append(e)
    rows = []
    for name, values in per.items():
        rot, mm = np.array(values).T
        rows.append({"part": "synthetic", "quantity": name, "trials": trials,
                     "rot_med_deg": float(np.median(rot)), "rot_max_deg": float(rot.max()),
                     "trans_med_mm": float(np.median(mm)), "trans_max_mm": float(mm.max()),
                     "seconds": float(np.median(seconds))})
    return rows + _convention_rows(ctx)
