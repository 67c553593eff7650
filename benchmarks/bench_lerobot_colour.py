"""How a LeRobot video keeps an episode's colour, and whether the reconstruction's model of it fits:
``shared/data/sim_pick_place_small`` exported as a LeRobot v3.0 dataset (``yuv420p``, each codec at
its default quality), imported back (``import-lerobot``: the frames stored as PNG, the camera's
``chroma_subsampling`` read from the video's pixel format), and every imported frame scored against
the simulator's original (PSNR, 8-bit): as drawn, and with the original's colour subsampled as
:mod:`manisplat.reconstruct.chroma` models what the importer records. What the model leaves is the
codec's own loss.

``python -m benchmarks lerobot_colour [--codecs libsvtav1,h264] [--out FILE]``
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._harness import BENCH_DIR, shared_dir

OWN_OPTIONS = True


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks lerobot_colour", description=__doc__.splitlines()[0])
    p.add_argument("--codecs", default="libsvtav1,h264", help="export codecs (default: libsvtav1,h264)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_export" / "lerobot_colour.json")
    args = p.parse_args(argv)
    options = sys.argv[1:] if argv is None else argv
    import torch  # after the arguments: --help stays quick

    from benchmarks._harness import MissingBenchmarkData
    from manisplat.episode import Episode
    from manisplat.episode.exporters.lerobot import VIDEO_CODECS, export_lerobot
    from manisplat.episode.images import describe_chroma
    from manisplat.episode.importers.lerobot import import_lerobot
    from manisplat.reconstruct.chroma import subsample_chroma, subsampled
    from manisplat.reconstruct.metrics import psnr

    if unknown := [c for c in args.codecs.split(",") if c not in VIDEO_CODECS]:
        p.error(f"--codecs: {', '.join(unknown)} not among {', '.join(VIDEO_CODECS)}")
    source = shared_dir() / "data" / "sim_pick_place_small"
    if not source.is_dir():
        raise MissingBenchmarkData(f"{source} not found (set MANISPLAT_SHARED to the shared folder)")
    original = Episode.open(source)
    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for codec in args.codecs.split(","):
            dataset = Path(tmp) / codec
            export_lerobot([source], dataset, task="pick", codec=codec, depth=False)
            back = import_lerobot(dataset, Path(tmp) / f"{codec}_back", episode=0, camera=original.camera.name,
                                  K=original.camera)
            recorded = back.chroma_subsampling()
            stored = subsampled(recorded)
            drawn, modelled = [], []
            for i in range(len(original)):
                image, imported = (torch.from_numpy(x).double() for x in (original.rgb(i), back.rgb(i)))
                drawn.append(psnr(image / 255, imported / 255))
                if stored is not None:
                    as_stored = subsample_chroma(image, stored).clamp(0, 255).round()  # 8-bit, as stored
                    modelled.append(psnr(as_stored / 255, imported / 255))
            row = {"codec": codec, "frames": len(original), "colour_recorded": describe_chroma(recorded),
                   "psnr_as_drawn_db": float(np.mean(drawn)),
                   "psnr_colour_modelled_db": float(np.mean(modelled)) if modelled else None}
            rows.append(row)
            print(json.dumps(row), flush=True)
    result = {"benchmark": "lerobot_colour", "command": " ".join(["python -m benchmarks lerobot_colour", *options]),
              "episode": str(source.name), "rows": rows, "wall_s": round(time.perf_counter() - t0, 1)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    return 0
