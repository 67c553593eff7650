"""Small version 2 episodes (two arms, three cameras) for the episode tests, written file by file
without the writer (so that the reader is tested on its own) or with it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from manisplat.episode.tables import format_row

W, H = 32, 24
FPS = 20.0
ARMS = ("left", "right")
CAMERAS = ("cam_high", "cam_left_wrist", "cam_right_wrist")
DEPTH_CAMERA = "cam_high"
DEPTH_SCALE = 0.001
T_WORLD_BASE = {"left": [[1.0, 0, 0, 0], [0, 1.0, 0, 0.3], [0, 0, 1.0, 0], [0, 0, 0, 1.0]],
                "right": [[1.0, 0, 0, 0], [0, 1.0, 0, -0.3], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]}
T_HIGH = [[0.0, -1.0, 0.0, -0.25], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.75], [0.0, 0.0, 0.0, 1.0]]
T_WRIST = [[-1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.075], [0.0, 0.0, -1.0, 0.05], [0.0, 0.0, 0.0, 1.0]]


def camera_dict(name: str) -> dict[str, Any]:
    """The ``cameras.<name>`` object: ``cam_high`` on the world, the wrist cameras on their arm's link6."""
    f = 30.0 if name == "cam_high" else 25.0
    mount = "world" if name == "cam_high" else f"{name.split('_')[1]}/link6"
    return {"width": W, "height": H, "K": [[f, 0.0, 15.5], [0.0, f, 11.5], [0.0, 0.0, 1.0]], "dist": [],
            "mount": mount, "T_mount_cam": T_HIGH if name == "cam_high" else T_WRIST}


def meta_dict(frames: int, *, arms: tuple[str, ...] = ARMS, cameras: tuple[str, ...] = CAMERAS,
              complete: bool = True) -> dict[str, Any]:
    """A version 2 ``episode.json``."""
    return {"format": "manisplat-episode", "version": 2, "complete": complete, "source": "simulation",
            "created": "2026-11-26T12:00:00Z",
            "arms": {a: {"model": "agilex_piper", "joint_names": [f"joint{i}" for i in range(1, 7)],
                         "description": "builtin:agilex_piper", "T_world_base": T_WORLD_BASE.get(a, np.eye(4).tolist())}
                     for a in arms},
            "cameras": {c: camera_dict(c) for c in cameras},
            "fps": FPS, "frame_count": frames, "depth_scale": DEPTH_SCALE, "labels": {}, "objects": [],
            "task": "handover"}


def frame_values(i: int, arms: tuple[str, ...] = ARMS) -> dict[str, float]:
    """Every ``frames.csv`` value of frame ``i`` by column (full float64 precision)."""
    rng = np.random.default_rng(i)
    row: dict[str, float] = {"index": i, "t": i / FPS}
    for a in arms:
        row.update({f"{a}.q{j}": float(v) for j, v in enumerate(rng.uniform(-2, 2, 6), start=1)})
        row[f"{a}.gripper"] = float(rng.uniform(0, 0.07))
    for a in arms:
        row.update({f"{a}.a{j}": float(v) for j, v in enumerate(rng.uniform(-2, 2, 6), start=1)})
        row[f"{a}.a_gripper"] = float(rng.uniform(0, 0.07))
    row["seq"] = float(1000 + i)
    return row


def images(i: int, camera: str) -> dict[str, np.ndarray]:
    """The rgb (and for ``cam_high`` the uint16 depth) of frame ``i`` from ``camera``."""
    rng = np.random.default_rng([i, CAMERAS.index(camera) if camera in CAMERAS else 9])
    out = {"rgb": rng.integers(0, 256, (H, W, 3), dtype=np.uint8)}
    if camera == DEPTH_CAMERA:
        out["depth"] = rng.integers(1, 3000, (H, W), dtype=np.uint16)
    return out


def write_by_hand(path: Path, frames: int = 5, *, arms: tuple[str, ...] = ARMS,
                  cameras: tuple[str, ...] = CAMERAS) -> Path:
    """A complete version 2 episode written file by file (no writer)."""
    path.mkdir(parents=True)
    (path / "episode.json").write_text(json.dumps(meta_dict(frames, arms=arms, cameras=cameras), indent=1))
    columns = list(frame_values(0, arms))
    lines = [",".join(columns) + "\n"]
    for i in range(frames):
        values = frame_values(i, arms)
        lines.append(format_row([int(values[c]) if c == "index" else values[c] for c in columns]))
        for cam in cameras:
            for kind, image in images(i, cam).items():
                folder = path / kind / cam
                folder.mkdir(parents=True, exist_ok=True)
                data = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if kind == "rgb" else image
                cv2.imwrite(str(folder / f"{i:06d}.png"), data)
    (path / "frames.csv").write_text("".join(lines))
    return path


def infos(arms: tuple[str, ...] = ARMS, cameras: tuple[str, ...] = CAMERAS,
          description: str = "builtin:agilex_piper") -> tuple[list[Any], list[Any]]:
    """``(arms, cameras)`` as :class:`ArmInfo` and :class:`CameraInfo` lists for the writer."""
    from manisplat.episode import ArmInfo, CameraInfo

    arm_infos = [ArmInfo(name=a, description=description, T_world_base=T_WORLD_BASE.get(a, np.eye(4))) for a in arms]
    cam_infos = [CameraInfo(name=c, **{k: v for k, v in camera_dict(c).items()}) for c in cameras]
    return arm_infos, cam_infos


def joint_sample(arm: str, k: int) -> dict[str, Any]:
    """A joint sample of ``arm`` (at 4x the frame rate)."""
    rng = np.random.default_rng([k, ARMS.index(arm) if arm in ARMS else 9])
    return {"t": k / (4 * FPS), "q": rng.uniform(-2, 2, 6), "gripper": float(rng.uniform(0, 0.07))}


def open_writer_v2(path: Path, *, arms: tuple[str, ...] = ARMS, cameras: tuple[str, ...] = CAMERAS,
                   **kwargs: Any) -> Any:
    from manisplat.episode.writer_v2 import EpisodeWriterV2

    arm_infos, cam_infos = infos(arms, cameras, kwargs.pop("description", "builtin:agilex_piper"))
    options = dict(source="simulation", depth_scale=DEPTH_SCALE, actions=True, extra_frame_columns=("seq",),
                   camera_times=("cam_left_wrist",) if "cam_left_wrist" in cameras else (),
                   extra_meta={"task": "handover"})
    options.update(kwargs)
    return EpisodeWriterV2(path, arm_infos, cam_infos, FPS, **options)


def add_frame_v2(writer: Any, i: int, arms: tuple[str, ...] = ARMS, cameras: tuple[str, ...] = CAMERAS) -> None:
    """Frame ``i`` of :func:`frame_values` and :func:`images`, with the joint samples before it."""
    values = frame_values(i, arms)
    shots = {c: images(i, c) for c in cameras}
    writer.add_frame(values["t"], {a: [values[f"{a}.q{j}"] for j in range(1, 7)] + [values[f"{a}.gripper"]]
                                   for a in arms},
                     {c: s["rgb"] for c, s in shots.items()},
                     depth={c: s["depth"] for c, s in shots.items() if "depth" in s},
                     actions={a: [values[f"{a}.a{j}"] for j in range(1, 7)] + [values[f"{a}.a_gripper"]]
                              for a in arms},
                     camera_t={"cam_left_wrist": values["t"] + 0.004} if "cam_left_wrist" in cameras else None,
                     extra={"seq": values["seq"]})
    for arm in arms:
        for k in range(4 * i, 4 * i + 4):
            writer.add_joint_sample(arm, **joint_sample(arm, k))


def write_v2(path: Path, frames: int = 6, **kwargs: Any) -> Path:
    """A complete version 2 episode (two arms, three cameras, depth on ``cam_high``) by the writer."""
    with open_writer_v2(path, **kwargs) as writer:
        for i in range(frames):
            add_frame_v2(writer, i, kwargs.get("arms", ARMS), kwargs.get("cameras", CAMERAS))
    return path
