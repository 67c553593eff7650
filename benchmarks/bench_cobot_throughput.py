"""Import and export throughput of a three-camera 640x480 Cobot Magic episode (frames/s, 1 and 2 cores).

The episode is a real render: ``shared/tools/sim/gen_bimanual.py`` at 640x480, made once with the
simulation venv (about 10 minutes on 2 busy cores)::

    cd ../shared/tools/sim && MUJOCO_GL=osmesa SIMENV/bin/python gen_bimanual.py --task handover --seed 0 \\
        --compress --width 640 --height 480 --out /tmp/cobot640

and given as ``$MANISPLAT_COBOT_640`` (the folder with ``episode_0.hdf5`` and ``episode_0.calib.json``):
175 frames, each three JPEG-compressed 640x480 images and three uint16 depth images.

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

from benchmarks._harness import BenchContext, MissingBenchmarkData

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


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    folder = os.environ.get("MANISPLAT_COBOT_640")
    if not folder or not (Path(folder) / "episode_0.hdf5").is_file():
        raise MissingBenchmarkData("set MANISPLAT_COBOT_640 to a folder with a 640x480 gen_bimanual.py episode_0.hdf5 "
                                   "and episode_0.calib.json (the command is in this benchmark's docstring)")
    import h5py

    src = Path(folder)
    with h5py.File(src / "episode_0.hdf5", "r") as f:
        cameras = list(f["observations/images"])
        shape = f["observations/images_depth"][cameras[0]].shape
    if len(cameras) != 3 or shape[1:] != (480, 640):
        raise MissingBenchmarkData(f"{src / 'episode_0.hdf5'}: cameras {cameras}, depth {shape}; expected three "
                                   "640x480 cameras")
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        episode = tmp / "episode"
        _run("import", src, episode, "0,1")  # the export's input, made once
        for cores in ("0", "0,1"):
            for op, what in OPERATIONS.items():
                load = os.getloadavg()[0]
                result = _run(op, src if op == "import" else episode, tmp / f"{op}_{len(rows)}", cores)
                rows.append({"operation": what, "cores": len(cores.split(",")), "frames": result["frames"],
                             "seconds": result["seconds"], "frames_per_s": result["frames"] / result["seconds"],
                             "images_per_s": 3 * result["frames"] / result["seconds"], "load_avg_1min": load})
    ctx.notes.append(f"{src.name}: 3 cameras ({', '.join(cameras)}) at 640x480 with depth; frames/s counts rows "
                     "of three images; the load average shows how busy the shared cores were")
    return rows
