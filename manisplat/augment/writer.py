"""A new demonstration rendered from the twin and written as an episode (format v1, ``source:
augmentation``) with its ``augmentation.json``.

The episode is written into a hidden sibling folder and renamed into place only once it is
complete (``episode.json`` closed, ``augmentation.json`` written): an interrupted run leaves no
folder that looks like a finished episode.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any, Callable

import numpy as np

from manisplat.augment.frames import to_centre_frame
from manisplat.augment.trajectory import NewTrajectory
from manisplat.episode import ACTION_COLUMNS, CameraInfo, EpisodeWriter, RobotInfo
from manisplat.episode.fsio import atomic_write_bytes
from manisplat.twin import Twin

DEPTH_SCALE = 1e-4  # m per uint16 unit: 0.1 mm steps up to 6.5 m
AUGMENTATION_JSON = "augmentation.json"
OBJECT_POSES_FILE = "object_poses.npz"
"""Per frame ``T_base_obj`` of each object, name -> [T, 4, 4] float64, in the twin's object frames
(what the twin rendered; ``manisplat-view`` animates the objects with it)."""


def write_demonstration(twin: Twin, traj: NewTrajectory, path: Path, *, seed: int, image_format: str = "png",
                        on_frame: Callable[[], None] | None = None) -> Path:
    """Render every frame of ``traj`` from the twin (RGB, depth, label masks) and write the episode
    at ``path`` (which must not exist). ``on_frame`` is called after each frame (progress)."""
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path} exists; augmented episodes are never overwritten")
    partial = path.with_name(f".partial-{path.name}")
    if partial.exists():
        shutil.rmtree(partial)  # debris of an interrupted run: never a finished episode
    camera = CameraInfo(name=twin.camera_name, width=twin.width, height=twin.height, K=twin.K, mount="base",
                        T_mount_cam=twin.T_base_cam)
    robot = RobotInfo(model=twin.robot_info["model"], joint_names=list(twin.robot_info["joint_names"]),
                      description=twin.robot_description)
    extra_meta = {"parent": twin.episode}
    if twin.task:
        extra_meta["task"] = twin.task
    with EpisodeWriter(partial, camera, robot, twin.fps, source="augmentation", depth_scale=DEPTH_SCALE,
                       labels=twin.labels, objects=twin.objects, image_format=image_format,
                       extra_frame_columns=ACTION_COLUMNS, extra_meta=extra_meta) as writer:
        for i, t in enumerate(traj.t):
            view = twin.render(traj.q[i], float(traj.gripper[i]), {k: v[i] for k, v in traj.object_poses.items()})
            actions = dict(zip(ACTION_COLUMNS, [*traj.action_q[i].tolist(), float(traj.action_gripper[i])]))
            writer.add_frame(float(t), traj.q[i], float(traj.gripper[i]), view.rgb, view.depth, view.labels,
                             extra=actions)
            if on_frame is not None:
                on_frame()
    _write_json(partial / AUGMENTATION_JSON, augmentation_record(twin, traj, seed))
    with open(partial / OBJECT_POSES_FILE, "wb") as f:
        np.savez(f, **{name: np.asarray(poses, np.float64) for name, poses in traj.object_poses.items()})
    os.replace(partial, path)
    return path


def augmentation_record(twin: Twin, traj: NewTrajectory, seed: int) -> dict[str, Any]:
    """The content of ``augmentation.json`` (docs/episode-format.md); object poses in the centre
    frame (:mod:`manisplat.augment.frames`)."""
    return {
        "parent": twin.episode, "seed": int(seed),
        "objects": {name: {k: to_centre_frame(twin, name, v).tolist() for k, v in poses.items()}
                    for name, poses in traj.objects.items()},
        "object_frame": "centre of the object's bounding box, axes of its reconstructed frame",
        "segments": traj.segments, "validation": traj.validation, "planner": traj.planner,
    }


def _write_json(path: Path, content: dict) -> None:
    atomic_write_bytes(path, (json.dumps(content, indent=1, default=_jsonable) + "\n").encode())


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
