"""Import and export throughput of a three-camera 640x480 Cobot Magic episode (frames/s, 1 and 2 cores).

The input is ``shared/data/cobot_handover_small`` (``gen_bimanual.py`` renders: 175 frames, three
320x240 cameras, JPEG rows, depth for each camera) made 640x480: every image decoded, resized 2x
(OpenCV bicubic) and JPEG-encoded again at the sample's quality 90 as ALOHA-style rows, the depth
resized 2x (nearest), the joints, actions, attributes and calibration (K scaled 2x) kept. Rendering
the scene at 640x480 directly (``gen_bimanual.py --width 640 --height 480``) took more than 15
minutes on the 2 shared cores. Upscaled renders are smoother than native ones, so the video encoder
and PNG have an easier time than with a real camera's noise.

Each operation runs in its own process pinned to 1 or 2 cores (``taskset``; OpenCV, SVT-AV1 and
HDF5 use the cores they are given) and is timed inside it around the library call:

* ``import-act --calib``: decode every camera's JPEG rows, write PNG images and 16-bit depth PNGs
  for the three cameras, frames.csv (the version 2 writer, as ``manisplat-episode import-act``);
* ``export act-hdf5``: raw (T, 480, 640, 3) datasets per camera, and ``--compress`` (JPEG rows);
* ``export lerobot``: one AV1 video per camera (libsvtav1, CRF 30, GOP 2, as LeRobot), with and
  without the three ``depth.<camera>`` columns.

A frame is one row: three camera images (and three depth images where they are written). The
machine's 1-minute load average before each run is recorded: the 2 cores are shared.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from benchmarks._harness import BenchContext

THREADED = False
RUNNER = """
import json, sys, time
from pathlib import Path
op, src, out = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3])
start = time.perf_counter()
if op == "import":
    from manisplat.episode.importers.cobot_magic import import_cobot_magic
    frames = len(import_cobot_magic(src / "episode_0.hdf5", out, src / "episode_0.calib.json"))
elif op.startswith("act"):
    from manisplat.episode.exporters.act_hdf5 import export_act_hdf5
    frames = sum(e["frames"] for e in export_act_hdf5([src], out, compress=op == "act-compress"))
else:
    from manisplat.episode.exporters.lerobot import export_lerobot
    frames = export_lerobot([src], out, task="handover", depth=op == "lerobot-depth").frames
seconds = time.perf_counter() - start
print(json.dumps({"frames": frames, "seconds": seconds}))
"""
OPERATIONS = {
    "import": "import-act --calib (JPEG rows -> PNG, depth -> 16-bit PNG)",
    "act-raw": "export act-hdf5 (raw uint8 images)",
    "act-compress": "export act-hdf5 --compress (JPEG rows, quality 90)",
    "lerobot": "export lerobot --no-depth (3 AV1 videos)",
    "lerobot-depth": "export lerobot (3 AV1 videos + 3 depth columns)",
}


def _run(op: str, src: Path, out: Path, cores: str) -> dict[str, Any]:
    command = ["taskset", "-c", cores, sys.executable, "-c", RUNNER, op, str(src), str(out)]
    done = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "SVT_LOG": "1"})
    if done.returncode != 0:
        raise RuntimeError(f"{op} on cores {cores} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _upscale(src: Path, out: Path) -> list[str]:
    """Write ``src``'s Cobot Magic episode at twice the size into ``out`` (HDF5 and calibration);
    returns the camera names."""
    import cv2
    import h5py
    import numpy as np

    out.mkdir(parents=True)
    calib = json.loads((src / "episode_0.calib.json").read_text())
    with h5py.File(src / "episode_0.hdf5", "r") as f, h5py.File(out / "episode_0.hdf5", "w") as g:
        for key, value in f.attrs.items():
            g.attrs[key] = value
        for name in ("observations/qpos", "observations/qvel", "action"):
            g[name] = f[name][()]
        cameras = list(f["observations/images"])
        rows, lengths = {}, []
        for cam in cameras:
            jpegs = []
            for row in f[f"observations/images/{cam}"]:
                image = cv2.resize(cv2.imdecode(row, cv2.IMREAD_COLOR), None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC)
                jpegs.append(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])[1])
            rows[cam] = jpegs
            lengths.append([len(b) for b in jpegs])
            depth = f[f"observations/images_depth/{cam}"][()]
            g[f"observations/images_depth/{cam}"] = np.stack(
                [cv2.resize(d, None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST) for d in depth])
        padded = max(max(n) for n in lengths)
        for cam, jpegs in rows.items():
            data = np.zeros((len(jpegs), padded), np.uint8)
            for i, b in enumerate(jpegs):
                data[i, :len(b)] = b
            g.create_dataset(f"observations/images/{cam}", data=data, chunks=(1, padded))
        g["compress_len"] = np.array(lengths, dtype=np.float32)
    for camera in calib["cameras"].values():
        K = np.array(camera["K"]) * [[2.0], [2.0], [1.0]]
        K[:2, 2] += 0.5  # pixel centres: (c + 0.5) * 2 - 0.5
        camera["K"] = K.tolist()
        camera["width"], camera["height"] = 2 * camera["width"], 2 * camera["height"]
    for arm in calib["arms"].values():  # the URDF path is relative to the calibration file
        if "urdf" in arm:
            arm["urdf"] = str((src / arm["urdf"]).resolve())
    (out / "episode_0.calib.json").write_text(json.dumps(calib))
    return cameras


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    sample = ctx.require_shared("data", "cobot_handover_small")
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        src = tmp / "cobot_640x480"
        cameras = _upscale(sample, src)
        episode = tmp / "episode"
        _run("import", src, episode, "0,1")  # the exports' input, made once
        for cores in ("0", "0,1"):
            for op, what in OPERATIONS.items():
                load = os.getloadavg()[0]
                result = _run(op, src if op == "import" else episode, tmp / f"{op}_{len(rows)}", cores)
                rows.append({"operation": what, "cores": len(cores.split(",")), "frames": result["frames"],
                             "seconds": result["seconds"], "frames_per_s": result["frames"] / result["seconds"],
                             "images_per_s": len(cameras) * result["frames"] / result["seconds"],
                             "load_avg_1min": load})
    ctx.notes.append(f"{sample.name} made 640x480 (2x bicubic, JPEG 90 again): {len(cameras)} cameras "
                     f"({', '.join(cameras)}) with depth; frames/s counts rows of {len(cameras)} images; the load "
                     "average shows how busy the shared cores were")
    return rows
