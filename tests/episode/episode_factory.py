"""Small deterministic episodes for the episode tests (also imported by the crash-test child process)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import h5py
import numpy as np

from manisplat.episode import ACTION_COLUMNS, CameraInfo, EpisodeWriter, RobotInfo

W, H = 32, 24
FPS = 10.0
DEPTH_SCALE = 1e-4
LABELS = {0: "background", 1: "robot/link1", 2: "object/box"}
EXTRA_COLUMNS = ("seq", *ACTION_COLUMNS)
JOINT_EXTRA = ("effort1",)
ACT_FRAMES = 6


def camera() -> CameraInfo:
    K = np.array([[30.0, 0.0, 15.5], [0.0, 31.0, 11.5], [0.0, 0.0, 1.0]])
    return CameraInfo(name="test", width=W, height=H, K=K, dist=np.zeros(5), mount="base", T_mount_cam=np.eye(4))


def frame_data(i: int, *, depth: bool = True, masks: bool = True) -> dict[str, Any]:
    """The arguments of ``add_frame`` for frame ``i`` (values with full float64 precision)."""
    rng = np.random.default_rng(i)
    data: dict[str, Any] = {
        "t": i / FPS + 1e-3 * rng.random(),
        "q": rng.uniform(-2.0, 2.0, 6),
        "gripper": rng.uniform(0.0, 0.08),
        "rgb": rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
        "extra": {"seq": float(100 + i), **dict(zip(ACTION_COLUMNS, rng.uniform(-1.0, 1.0, 7).tolist()))},
    }
    if depth:
        d = rng.uniform(0.3, 2.0, (H, W))
        d[0, 0] = np.nan  # invalid pixel, stored as 0
        data["depth"] = d
    if masks:
        data["mask"] = rng.integers(0, 3, (H, W), dtype=np.uint8)
    return data


def joint_data(k: int) -> dict[str, Any]:
    """The arguments of ``add_joint_sample`` for sample ``k`` (at 4x the frame rate)."""
    rng = np.random.default_rng(1000 + k)
    return {"t": k / (4 * FPS), "q": rng.uniform(-2.0, 2.0, 6), "gripper": rng.uniform(0.0, 0.08),
            "extra": {"effort1": rng.normal()}}


def open_writer(path: Path, **kwargs: Any) -> EpisodeWriter:
    options = dict(depth_scale=DEPTH_SCALE, labels=LABELS, objects=["box"], extra_frame_columns=EXTRA_COLUMNS,
                   joint_columns=JOINT_EXTRA, extra_meta={"task": "test"})
    options.update(kwargs)
    return EpisodeWriter(path, camera(), RobotInfo(), FPS, **options)


def write_episode(path: Path, frames: int = 8, *, depth: bool = True, masks: bool = True, joints: bool = True,
                  **kwargs: Any) -> Path:
    """Write a complete episode of ``frames`` frames (32x24) at ``path``."""
    with open_writer(path, **kwargs) as writer:
        for i in range(frames):
            writer.add_frame(**frame_data(i, depth=depth, masks=masks))
            if joints:
                for k in range(4 * i, 4 * i + 4):
                    writer.add_joint_sample(**joint_data(k))
    return path


def mark_incomplete(path: Path) -> None:
    """Set ``complete: false`` in the episode's ``episode.json``, as a crashed writer leaves it."""
    meta = json.loads((path / "episode.json").read_text())
    (path / "episode.json").write_text(json.dumps({**meta, "complete": False}))


def jpeg_rows(images: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], np.ndarray]:
    """ALOHA-style compressed images: camera -> (T, H, W, 3) uint8 to camera -> (T, L) uint8 JPEG
    bytes zero-padded to the longest, camera -> the (T, H, W, 3) images those bytes decode to, and
    the (cameras, T) byte counts (``compress_len``), cameras in ``images``' order."""
    encoded = {c: [cv2.imencode(".jpg", im)[1] for im in frames] for c, frames in images.items()}
    width = max(len(b) for rows in encoded.values() for b in rows)
    rows, decoded = {}, {}
    for c, jpegs in encoded.items():
        rows[c] = np.zeros((len(jpegs), width), np.uint8)
        for i, b in enumerate(jpegs):
            rows[c][i, :len(b)] = b
        decoded[c] = np.stack([cv2.imdecode(b, cv2.IMREAD_COLOR) for b in jpegs])
    return rows, decoded, np.array([[len(b) for b in jpegs] for jpegs in encoded.values()])


def write_act(path: Path, *, arms: int = 2, compress: bool = False, depth: bool = True,
              cameras: tuple[str, ...] = ("cam_high", "cam_left_wrist")) -> dict[str, Any]:
    """An ACT / Cobot Magic HDF5 file of ``ACT_FRAMES`` 32x24 frames; returns what it holds
    (``qpos``, ``action``, ``effort``, ``depth`` and ``images[cam]``, the arrays a reader gets back)."""
    T, rng, cols = ACT_FRAMES, np.random.default_rng(0), 7 * arms
    data = {"qpos": rng.uniform(-1, 1, (T, cols)), "action": rng.uniform(-1, 1, (T, cols)),
            "effort": rng.uniform(-1, 1, (T, cols)),
            "images": {c: rng.integers(0, 256, (T, H, W, 3), dtype=np.uint8) for c in cameras},
            "depth": rng.integers(1, 3000, (T, H, W), dtype=np.uint16)}
    with h5py.File(path, "w") as f:
        f.attrs["sim"] = False
        f.attrs["compress"] = compress
        obs = f.create_group("observations")
        obs["qpos"] = data["qpos"]
        obs["qvel"] = np.zeros((T, cols))
        obs["effort"] = data["effort"]
        f["action"] = data["action"]
        images = obs.create_group("images")
        if compress:  # ALOHA style: JPEG bytes padded to the longest, plus compress_len
            rows, data["images"], lengths = jpeg_rows(data["images"])
            for c in cameras:
                images[c] = rows[c]
            f["compress_len"] = lengths
        else:
            for c in cameras:
                images.create_dataset(c, data=data["images"][c], chunks=(1, H, W, 3))
        if depth:
            obs.create_group("images_depth")["cam_high"] = data["depth"]
    return data
