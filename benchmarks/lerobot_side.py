"""The LeRobot side of ``bench_export_lerobot``: run with the Python of a virtual environment that has
``lerobot`` (0.4.4 checked), never ManiSplat's own (lerobot pins another torch).

    python benchmarks/lerobot_side.py check DATASET_DIR --episodes E0 E1 ... [--expected-state S0.npy ...]
                                      --json OUT.json
        LeRobotDataset(root=DATASET_DIR, video_backend="pyav") loads the export: len, num_episodes,
        a sample's keys and shapes, a DataLoader over every frame (no timestamp-tolerance error),
        ACT-style action chunks through delta_timestamps, and every camera's decoded images against
        the episodes' own PNGs (PSNR) and the state against frames.csv (float32 exact), or against
        the (T, D) float32 arrays of --expected-state (e.g. a Cobot Magic file's qpos), one per episode.
    python benchmarks/lerobot_side.py write OUT_DIR --episodes E0 E1 ... --task TEXT --json OUT.json
        LeRobot's own writer (LeRobotDataset.create + add_frame + save_episode + finalize) on the same
        episodes, timed: the peer for export throughput.

Episodes (format version 1, or 2 with several arms and cameras) are read here with numpy, csv and
PIL only (this environment has no ManiSplat).
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import numpy as np
from PIL import Image


def read_episode(path: Path) -> tuple[dict, np.ndarray, np.ndarray | None, dict[str, list[Path]]]:
    """episode.json, (T, 7 A) state (each arm's q1..q6, gripper), (T, 7 A) actions or None, and
    camera -> rgb file paths; version 1 has one arm and camera (columns q1.., rgb/), version 2
    named ones (columns <arm>.q1.., rgb/<camera>/)."""
    meta = json.loads((path / "episode.json").read_text())
    with open(path / "frames.csv") as f:
        rows = list(csv.DictReader(f))
    prefixes = [f"{arm}." for arm in meta["arms"]] if "arms" in meta else [""]
    folders = ({c: path / "rgb" / c for c in meta["cameras"]} if "cameras" in meta
               else {meta["camera"]["name"]: path / "rgb"})
    state_columns = [p + c for p in prefixes for c in ("q1", "q2", "q3", "q4", "q5", "q6", "gripper")]
    action_columns = [p + c for p in prefixes for c in ("a1", "a2", "a3", "a4", "a5", "a6", "a_gripper")]
    state = np.array([[float(r[c]) for c in state_columns] for r in rows])
    actions = (np.array([[float(r[c]) for c in action_columns] for r in rows])
               if rows and all(c in rows[0] for c in action_columns) else None)
    images = {camera: [next(folder.glob(f"{i:06d}.*")) for i in range(len(rows))]
              for camera, folder in folders.items()}
    return meta, state, actions, images


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(255.0 ** 2 / mse))


def check(args: argparse.Namespace) -> dict:
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    start = time.perf_counter()
    ds = LeRobotDataset("manisplat/export", root=args.dataset, video_backend="pyav")
    load_s = time.perf_counter() - start
    info = json.loads((Path(args.dataset) / "meta" / "info.json").read_text())
    camera_keys = [k for k, f in info["features"].items() if f["dtype"] == "video"]
    camera_key = camera_keys[0]
    sample = ds[0]
    shapes = {k: list(v.shape) if hasattr(v, "shape") else type(v).__name__ for k, v in sample.items()}
    episodes = [read_episode(Path(e)) for e in args.episodes]
    expected = ([np.load(p).astype(np.float32) for p in args.expected_state] if args.expected_state
                else [e[1].astype(np.float32) for e in episodes])
    expected_frames = sum(len(e[1]) for e in episodes)
    start = time.perf_counter()
    loader = torch.utils.data.DataLoader(ds, batch_size=32, shuffle=False, num_workers=0)
    seen, worst_state, psnrs = 0, 0.0, {k: [] for k in camera_keys}
    for batch in loader:
        for j in range(len(batch["index"])):
            ep, frame = int(batch["episode_index"][j]), int(batch["frame_index"][j])
            images = episodes[ep][3]
            worst_state = max(worst_state, float(np.abs(batch["observation.state"][j].numpy()
                                                        - expected[ep][frame]).max()))
            for key in camera_keys:
                decoded = (batch[key][j].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
                own = images[key.removeprefix("observation.images.")][frame]
                psnrs[key].append(psnr(decoded, np.asarray(Image.open(own).convert("RGB"))))
        seen += len(batch["index"])
    iterate_s = time.perf_counter() - start
    fps = info["fps"]
    chunk = LeRobotDataset("manisplat/export", root=args.dataset, video_backend="pyav",
                           delta_timestamps={"action": [k / fps for k in range(10)],
                                             camera_key: [-1 / fps, 0.0]})
    last = chunk[len(chunk) - 1]
    result = {
        "lerobot_len": len(ds), "lerobot_num_episodes": ds.num_episodes, "expected_frames": expected_frames,
        "expected_episodes": len(episodes), "sample_keys_shapes": shapes, "dataloader_frames": seen,
        "state_compared_with": "--expected-state" if args.expected_state else "frames.csv",
        "state_max_abs_diff_vs_float32": worst_state,
        "camera_keys": camera_keys,
        "image_psnr_db_min": min(min(v) for v in psnrs.values()),
        "image_psnr_db_mean": float(np.mean([x for v in psnrs.values() for x in v])),
        "image_psnr_db_by_camera": {k: [min(v), float(np.mean(v))] for k, v in psnrs.items()},
        "action_chunk_shape": list(last["action"].shape), "action_is_pad_last": int(last["action_is_pad"].sum()),
        "camera_pair_shape": list(last[camera_key].shape), "load_s": load_s, "iterate_s": iterate_s,
        "ok": bool(len(ds) == expected_frames == seen and ds.num_episodes == len(episodes) and worst_state == 0.0),
    }
    return result


def write(args: argparse.Namespace) -> dict:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    episodes = [read_episode(Path(e)) for e in args.episodes]
    meta = episodes[0][0]
    width, height, camera = meta["camera"]["width"], meta["camera"]["height"], meta["camera"]["name"]
    names = ["q1", "q2", "q3", "q4", "q5", "q6", "gripper"]
    features = {"observation.state": {"dtype": "float32", "shape": (7,), "names": names},
                "action": {"dtype": "float32", "shape": (7,), "names": names},
                f"observation.images.{camera}": {"dtype": "video", "shape": (height, width, 3),
                                                 "names": ["height", "width", "channels"]}}
    start = time.perf_counter()
    ds = LeRobotDataset.create("manisplat/peer", fps=int(round(meta["fps"])), features=features, root=args.out,
                               robot_type="piper", use_videos=True, vcodec=args.codec)
    frames = 0
    for _, state, actions, images in episodes:
        action = actions if actions is not None else np.concatenate([state[1:], state[-1:]])
        for i, path in enumerate(images[camera]):
            ds.add_frame({"observation.state": state[i].astype(np.float32), "action": action[i].astype(np.float32),
                          f"observation.images.{camera}": np.asarray(Image.open(path).convert("RGB")),
                          "task": args.task})
            frames += 1
        ds.save_episode()
    ds.finalize()
    seconds = time.perf_counter() - start
    return {"frames": frames, "seconds": seconds, "frames_per_s": frames / seconds, "codec": args.codec}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("check")
    p.add_argument("dataset")
    p.add_argument("--episodes", nargs="+", required=True)
    p.add_argument("--expected-state", nargs="+", help="one (T, D) .npy per episode (default: frames.csv)")
    p.add_argument("--json", required=True)
    p = sub.add_parser("write")
    p.add_argument("out")
    p.add_argument("--episodes", nargs="+", required=True)
    p.add_argument("--task", required=True)
    p.add_argument("--codec", default="libsvtav1")
    p.add_argument("--json", required=True)
    args = parser.parse_args()
    result = check(args) if args.command == "check" else write(args)
    Path(args.json).write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
