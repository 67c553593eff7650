"""Dataset export: LeRobot's own loader reads our LeRobot v3.0 export, ACT HDF5 round-trips through
import-act bit-exact, and export throughput (frames/s) beside LeRobot's own writer, 1 and 2 cores.

LeRobot pins another torch, so it lives in its own virtual environment, never ours: make one with
``python3 -m venv /tmp/lrvenv && /tmp/lrvenv/bin/pip install lerobot==0.4.4`` (about 3 minutes,
8 GB) and point ``$MANISPLAT_LEROBOT_PYTHON`` at its ``bin/python``. ``benchmarks/lerobot_side.py``
runs there: ``check`` loads our export with ``LeRobotDataset(..., video_backend="pyav")`` and
iterates a DataLoader over every frame; ``write`` is the peer (``LeRobotDataset.create`` +
``add_frame`` + ``save_episode`` + ``finalize``, AV1 as we write it).

Episodes: the built-in sample (``manisplat-episode sample``, 4 seeds x 96 frames) at 320x240 and
640x480, and ``shared/data/sim_pick_place_small`` (MuJoCo renders, 320x240) for the loader check
when present. Both writers read the same PNG episodes and run pinned to 1 or 2 cores (``taskset``);
each is timed inside its process, from the first read to the last file closed.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks._harness import REPO_DIR, BenchContext, MissingBenchmarkData

THREADED = False
SIDE = REPO_DIR / "benchmarks" / "lerobot_side.py"
TASK = "pick the box and place it on the mat"
OURS = """
import json, sys, time
from manisplat.episode.exporters.lerobot import export_lerobot
out, variant, episodes = sys.argv[1], sys.argv[2], sys.argv[3:]
codec, _, extra = variant.partition("+")
start = time.perf_counter()
result = export_lerobot(episodes, out, task={task!r}, codec=codec, depth=extra == "depth")
seconds = time.perf_counter() - start
print(json.dumps({{"frames": result.frames, "seconds": seconds, "frames_per_s": result.frames / seconds}}))
"""


def _run_json(command: list[str], cores: str | None = None, json_path: Path | None = None) -> dict[str, Any]:
    if cores is not None:
        command = ["taskset", "-c", cores, *command]
    done = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "SVT_LOG": "1"})
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr[-3000:]}")
    if json_path is not None:
        return json.loads(json_path.read_text())
    return json.loads(done.stdout.strip().splitlines()[-1])


def _samples(root: Path, width: int, height: int, count: int, frames: int) -> list[str]:
    from manisplat.episode.synthetic import write_sample_episode

    return [str(write_sample_episode(root / f"sample_{width}x{height}_{seed}", frames=frames, width=width,
                                     height=height, seed=seed)) for seed in range(count)]


def _act_round_trip(episodes: list[str], tmp: Path) -> dict[str, Any]:
    from manisplat.episode import Episode, import_act_hdf5
    from manisplat.episode.exporters import export_act_hdf5

    export_act_hdf5(episodes, tmp / "act", dtype="float64")
    exact = True
    for n, path in enumerate(episodes):
        ep = Episode.open(path)
        back = import_act_hdf5(tmp / "act" / f"episode_{n}.hdf5", tmp / f"act_back_{n}", K=ep.camera, arm="single",
                               camera=ep.camera.name, fps=ep.meta.fps)
        exact &= bool(np.array_equal(back.frames.q, ep.frames.q) and np.array_equal(back.frames.gripper,
                                                                                   ep.frames.gripper)
                      and np.array_equal(back.frames.actions, ep.frames.actions))
    return {"case": "act-hdf5 --float64 -> import-act", "episodes": len(episodes), "joints_bit_exact": exact}


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    lerobot_python = os.environ.get("MANISPLAT_LEROBOT_PYTHON")
    if not lerobot_python or not Path(lerobot_python).is_file():
        raise MissingBenchmarkData("set MANISPLAT_LEROBOT_PYTHON to the python of a venv with lerobot==0.4.4")
    count, frames = (2, 24) if ctx.quick else (4, 96)
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        sets = {"sample 320x240": _samples(tmp, 320, 240, count, frames),
                "sample 640x480": _samples(tmp, 640, 480, count, frames)}
        shared = ctx.shared / "data" / "sim_pick_place_small"
        checks = dict(sets)
        if shared.is_dir():
            checks["sim_pick_place_small (MuJoCo) x2"] = [str(shared), str(shared)]
        for name, episodes in checks.items():  # LeRobot's loader on our export
            out = tmp / f"check_{len(rows)}"
            _run_json([sys.executable, "-c", OURS.format(task=TASK), str(out), "libsvtav1+depth", *episodes])
            result = _run_json([lerobot_python, str(SIDE), "check", str(out), "--episodes", *episodes,
                                "--json", str(tmp / "check.json")], json_path=tmp / "check.json")
            rows.append({"case": f"LeRobotDataset loads our export: {name}", **{
                k: result[k] for k in ("ok", "lerobot_len", "lerobot_num_episodes", "dataloader_frames",
                                       "state_max_abs_diff_vs_float32", "image_psnr_db_min",
                                       "image_psnr_db_mean", "action_chunk_shape")}})
        rows.append(_act_round_trip(sets["sample 320x240"], tmp))
        for name, episodes in sets.items():  # throughput, same episodes, same run
            for cores in ("0", "0,1"):
                n_cores = len(cores.split(","))
                for writer in ("lerobot libsvtav1", "manisplat libsvtav1", "manisplat h264", "manisplat libsvtav1+depth"):
                    out = tmp / f"speed_{len(rows)}"
                    if writer.startswith("manisplat"):
                        result = _run_json([sys.executable, "-c", OURS.format(task=TASK), str(out),
                                            writer.split()[1], *episodes], cores)
                    else:
                        result = _run_json([lerobot_python, str(SIDE), "write", str(out), "--episodes", *episodes,
                                            "--task", TASK, "--json", str(tmp / "write.json")], cores,
                                           json_path=tmp / "write.json")
                    rows.append({"case": f"export {name}", "writer": writer, "cores": n_cores,
                                 "frames": result["frames"], "seconds": result["seconds"],
                                 "frames_per_s": result["frames_per_s"]})
    ctx.notes.append("throughput includes reading the episodes' PNGs; both writers encode AV1 with SVT-AV1 "
                     "(preset 12, CRF 30, GOP 2) through PyAV and write state, action and video; '+depth' adds our "
                     "depth.<camera> column (uint16 mm), which LeRobot's peer does not write")
    return rows
