"""Two arms, three cameras: the Cobot Magic samples exported to LeRobot (loaded by lerobot's LeRobotDataset) and
to ACT HDF5 (re-imported by import-act --calib bit-exact in joints).

Both ``shared/data`` Cobot Magic samples (``cobot_handover_small``, ``cobot_dual_small``: 175 and
150 frames, 320x240, 20 fps, ``cam_high``, ``cam_left_wrist``, ``cam_right_wrist``, depth for each) are
imported as the user would (``manisplat-episode import-act FILE --calib FILE.calib.json --out EP
--task TASK``) and validated, then:

* exported together as one LeRobot v3.0 dataset (AV1, depth columns), which
  ``benchmarks/lerobot_side.py check`` loads with lerobot's own ``LeRobotDataset`` in the lerobot
  venv (``$MANISPLAT_LEROBOT_PYTHON``, made as ``bench_export_lerobot``'s docstring says): length,
  episodes, a sample's keys and shapes, a DataLoader over every frame, action chunks, every camera's
  images (PSNR against the imported PNGs) and the 14-D state against the HDF5's ``qpos`` in float32;
* read back from that dataset with ``import-lerobot --calib FILE.calib.json --units rad,m``:
  joints against the HDF5's ``qpos`` in float32 (exact);
* exported as ACT HDF5 (``--float64`` and the float32 default) and re-imported with
  ``import-act --calib`` and the sample's own calibration: joints and actions against the HDF5's
  (bit-exact with ``--float64``; float32 rounding otherwise) and every image against the first
  import (raw rows, so lossless).
"""

from __future__ import annotations

import json
import os
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from benchmarks._harness import REPO_DIR, BenchContext, MissingBenchmarkData

THREADED = False
SIDE = REPO_DIR / "benchmarks" / "lerobot_side.py"
SAMPLES = {"cobot_handover_small": "handover", "cobot_dual_small": "dual_pick_place"}
"""Sample folder -> its task (the ``task`` of its ``episode_0.objects.json``)."""


def _cli(*argv: str) -> None:
    from manisplat.episode.cli import main

    status = main(list(argv))
    if status != 0:
        raise RuntimeError(f"manisplat-episode {' '.join(argv)} exited {status}")


def _joints(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(T, 14) joints and actions of an episode, each arm's q1..q6, gripper in its order."""
    from manisplat.episode import Episode

    ep = Episode.open(path)
    tables = [ep.arm_frames(a) for a in ep.arms]
    return (np.concatenate([np.column_stack([t.q, t.gripper]) for t in tables], axis=1),
            np.concatenate([t.actions for t in tables], axis=1))


def _same_images(a: Path, b: Path) -> bool:
    from manisplat.episode import Episode

    first, again = Episode.open(a), Episode.open(b)
    return list(first.cameras) == list(again.cameras) and all(
        np.array_equal(first.rgb(i, c), again.rgb(i, c)) for c in first.cameras for i in range(len(first)))


def _act_round_trip(name: str, episode: Path, h5: Path, tmp: Path) -> list[dict[str, Any]]:
    with h5py.File(h5, "r") as f:
        qpos, action = f["observations/qpos"][()], f["action"][()]
    rows = []
    for option in ("--float64", None):
        out, back = tmp / f"act_{name}_{option}", tmp / f"act_back_{name}_{option}"
        _cli("export", str(episode), "--format", "act-hdf5", "--out", str(out), *([option] if option else []))
        _cli("import-act", str(out / "episode_0.hdf5"), "--calib", str(h5.with_suffix(".calib.json")),
             "--out", str(back))
        joints, actions = _joints(back)
        dtype = np.float64 if option else np.float32
        with h5py.File(out / "episode_0.hdf5", "r") as f:
            keys = sorted(f["observations/images"])
            shape = list(f["observations/qpos"].shape)
        rows.append({"case": f"ACT HDF5 {option or 'float32'} -> import-act --calib: {name}", "qpos_shape": shape,
                     "image_keys": keys,
                     "joints_equal_hdf5_qpos": bool(np.array_equal(joints, qpos.astype(dtype).astype(np.float64))),
                     "actions_equal_hdf5_action": bool(np.array_equal(actions,
                                                                      action.astype(dtype).astype(np.float64))),
                     "joints_max_abs_diff_vs_hdf5_float64": float(np.abs(joints - qpos).max()),
                     "images_equal_first_import": _same_images(episode, back)})
    return rows


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    lerobot_python = os.environ.get("MANISPLAT_LEROBOT_PYTHON")
    if not lerobot_python or not Path(lerobot_python).is_file():
        raise MissingBenchmarkData("set MANISPLAT_LEROBOT_PYTHON to the python of a venv with lerobot==0.4.4")
    from manisplat.episode import Episode, validate

    files = {name: ctx.require_shared("data", name, "episode_0.hdf5") for name in SAMPLES}
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        episodes, expected = [], []
        for name, h5 in files.items():
            episode = tmp / name
            _cli("import-act", str(h5), "--calib", str(h5.with_suffix(".calib.json")), "--out", str(episode),
                 "--task", SAMPLES[name])
            report = validate(episode)
            with h5py.File(h5, "r") as f:
                np.save(tmp / f"{name}_qpos.npy", f["observations/qpos"][()].astype(np.float32))
            episodes.append(str(episode))
            expected.append(str(tmp / f"{name}_qpos.npy"))
            rows.append({"case": f"import-act --calib: {name}", "valid": report.ok, "warnings": len(report.warnings)})
            rows += _act_round_trip(name, episode, h5, tmp)
        dataset = tmp / "lerobot"
        _cli("export", *episodes, "--format", "lerobot", "--out", str(dataset))
        for number, (name, h5) in enumerate(files.items()):  # and back through import-lerobot
            back = tmp / f"lerobot_back_{name}"
            _cli("import-lerobot", str(dataset), "--episode", str(number), "--calib",
                 str(h5.with_suffix(".calib.json")), "--units", "rad,m", "--out", str(back))
            joints, actions = _joints(back)
            qpos = np.load(expected[number]).astype(np.float64)
            rows.append({"case": f"LeRobot -> import-lerobot --calib --units rad,m: {name}",
                         "joints_equal_hdf5_qpos_float32": bool(np.array_equal(joints, qpos)),
                         "cameras": list(Episode.open(back).cameras),
                         "valid": validate(back).ok})
        done = subprocess.run([lerobot_python, str(SIDE), "check", str(dataset), "--episodes", *episodes,
                               "--expected-state", *expected, "--json", str(tmp / "check.json")],
                              capture_output=True, text=True, env={**os.environ, "SVT_LOG": "1"})
        if done.returncode != 0:
            raise RuntimeError(f"lerobot_side.py check failed:\n{done.stderr[-3000:]}")
        result = json.loads((tmp / "check.json").read_text())
        rows.append({"case": "LeRobotDataset loads our export of both samples (state vs the HDF5 qpos in float32)",
                     **{k: result[k] for k in ("ok", "lerobot_len", "expected_frames", "lerobot_num_episodes",
                                               "dataloader_frames", "state_compared_with",
                                               "state_max_abs_diff_vs_float32", "camera_keys", "sample_keys_shapes",
                                               "image_psnr_db_min", "image_psnr_db_mean", "image_psnr_db_by_camera",
                                               "action_chunk_shape", "camera_pair_shape")}})
    ctx.notes.append("LeRobot export: AV1 (libsvtav1, CRF 30, GOP 2), depth columns depth.<camera> uint16 mm; "
                     "PSNR against the PNGs the import wrote (the samples' JPEG frames decoded)")
    return rows
