"""manisplat-view on the Cobot Magic samples: where it places every camera and TCP against the simulator's truth.

Each sample (``shared/data/cobot_handover_small``, ``cobot_dual_small``) is imported with
``manisplat-episode import-act --calib`` into a temporary version 2 episode and read by
``load_content``; every camera's ``T_world_cam`` (the wrist cameras through each arm's FK and
``T_world_base``) and every arm's TCP in the world, over every frame, are compared with
``*.gt.npz`` (``T_world_<camera>``, ``T_world_tcp_<arm>``); then ``--video`` writes the three
cameras side by side.

Rows: sample, quantity, frames, max_mm, max_deg (and video_frames_per_s, video_size for the video row).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from benchmarks._harness import BenchContext
from manisplat.calib.poses import pose_difference

THREADED = False
SAMPLES = ("cobot_handover_small", "cobot_dual_small")


def _rows(sample: str, folder: Path, tmp: Path) -> list[dict]:
    from manisplat.episode.cli import main as episode
    from manisplat.view.content import load_content
    from manisplat.view.video import write_video

    out = tmp / sample
    assert episode(["import-act", str(folder / "episode_0.hdf5"), "--calib", str(folder / "episode_0.calib.json"),
                    "--out", str(out)]) == 0
    content = load_content(out)
    demo = content.demos[0]
    rows = []
    with np.load(folder / "episode_0.gt.npz") as gt:
        for name in content.cameras:
            errors = np.array([pose_difference(content.camera_pose(name, demo, i), gt[f"T_world_{name}"][i])
                               for i in range(len(demo))])
            rows.append({"sample": sample, "quantity": f"T_world_cam {name} ({content.cameras[name].mount})",
                         "frames": len(demo), "max_mm": float(errors[:, 1].max()), "max_deg": float(errors[:, 0].max())})
        for arm, path in content.tcp_paths(demo).items():
            mm = 1000 * np.linalg.norm(path - gt[f"T_world_tcp_{arm}"][:, :3, 3], axis=1)
            rows.append({"sample": sample, "quantity": f"TCP {arm}", "frames": len(demo), "max_mm": float(mm.max())})
    video = write_video(content, tmp / f"{sample}.mp4")
    rows.append({"sample": sample, "quantity": "--video (every camera side by side)", "frames": video.frames,
                 "video_frames_per_s": video.frames_per_s, "video_size": f"{video.width}x{video.height}"})
    return rows


def run(ctx: BenchContext) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for sample in SAMPLES[:1] if ctx.quick else SAMPLES:
            rows += _rows(sample, ctx.require_shared("data", sample), Path(tmp))
    return rows
