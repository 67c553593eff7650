"""A new demonstration rendered from the twin and written as an episode (``source:
augmentation``) with its ``augmentation.json``: format version 1 for a twin of one arm and one
camera, version 2 for several arms (every arm's joints and commands, every camera rendered: a
wrist camera from its link at the new joints).

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

from manisplat.augment.bimanual import BimanualTrajectory
from manisplat.augment.frames import to_centre_frame
from manisplat.augment.trajectory import NewTrajectory
from manisplat.episode import ACTION_COLUMNS, ArmInfo, CameraInfo, EpisodeWriter, RobotInfo
from manisplat.episode.format import WORLD_MOUNT
from manisplat.episode.writer_v2 import EpisodeWriterV2
from manisplat.episode.fsio import atomic_write_bytes
from manisplat.twin import Twin

DEPTH_SCALE = 1e-4  # m per uint16 unit: 0.1 mm steps up to 6.5 m
AUGMENTATION_JSON = "augmentation.json"
OBJECT_POSES_FILE = "object_poses.npz"
"""Per frame ``T_base_obj`` of each object, name -> [T, 4, 4] float64, in the twin's object frames
(what the twin rendered; ``manisplat-view`` animates the objects with it)."""


def write_demonstration(twin: Twin, traj: NewTrajectory | BimanualTrajectory, path: Path, *, seed: int,
                        image_format: str = "png", on_frame: Callable[[], None] | None = None) -> Path:
    """Render every frame of ``traj`` from the twin (RGB, depth, label masks of every camera) and
    write the episode at ``path`` (which must not exist). ``on_frame`` is called after each frame
    (progress)."""
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path} exists; augmented episodes are never overwritten")
    partial = path.with_name(f".partial-{path.name}")
    if partial.exists():
        shutil.rmtree(partial)  # debris of an interrupted run: never a finished episode
    extra_meta = {"parent": twin.episode}
    if twin.task:
        extra_meta["task"] = twin.task
    if isinstance(traj, BimanualTrajectory):
        _write_arms(twin, traj, partial, image_format, extra_meta, on_frame)
        record = arms_record(twin, traj, seed)
    else:
        _write_one_arm(twin, traj, partial, image_format, extra_meta, on_frame)
        record = augmentation_record(twin, traj, seed)
    _write_json(partial / AUGMENTATION_JSON, record)
    with open(partial / OBJECT_POSES_FILE, "wb") as f:
        np.savez(f, **{name: np.asarray(poses, np.float64) for name, poses in traj.object_poses.items()})
    os.replace(partial, path)
    return path


def _write_one_arm(twin: Twin, traj: NewTrajectory, partial: Path, image_format: str, extra_meta: dict,
                   on_frame: Callable[[], None] | None) -> None:
    camera = CameraInfo(name=twin.camera_name, width=twin.width, height=twin.height, K=twin.K, mount="base",
                        T_mount_cam=twin.T_base_cam)
    robot = RobotInfo(model=twin.robot_info["model"], joint_names=list(twin.robot_info["joint_names"]),
                      description=twin.robot_description)
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


def _write_arms(twin: Twin, traj: BimanualTrajectory, partial: Path, image_format: str, extra_meta: dict,
                on_frame: Callable[[], None] | None) -> None:
    """A version 2 episode: every arm at its base, every camera of the twin (fixed, or riding on
    its link as it was recorded), each frame rendered by every camera at the new joints."""
    arms = [ArmInfo(name=a.name, model=a.model, joint_names=list(a.joint_names), description=a.description,
                    T_world_base=a.T_world_base) for a in twin.arms]
    cameras = [CameraInfo(name=c.name, width=c.width, height=c.height, K=c.K,
                          mount=WORLD_MOUNT if c.fixed else c.mount, T_mount_cam=c.T_mount_cam)
               for c in twin.cameras.values()]
    with EpisodeWriterV2(partial, arms, cameras, twin.fps, source="augmentation", depth_scale=DEPTH_SCALE,
                         labels=twin.labels, objects=twin.objects, image_format=image_format, actions=True,
                         extra_meta=extra_meta) as writer:
        for i, t in enumerate(traj.t):
            q, gripper = twin.joint_state(traj.joint_state(i))
            poses = {k: v[i] for k, v in traj.object_poses.items()}
            views = {name: twin.render(q, gripper, poses, camera=name) for name in twin.cameras}
            writer.add_frame(float(t), {name: [*arm.q[i], arm.gripper[i]] for name, arm in traj.arms.items()},
                             {name: v.rgb for name, v in views.items()},
                             depth={name: v.depth for name, v in views.items()},
                             masks={name: v.labels for name, v in views.items()},
                             actions={name: [*arm.action_q[i], arm.action_gripper[i]] for name, arm in traj.arms.items()})
            if on_frame is not None:
                on_frame()


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


def arms_record(twin: Twin, traj: BimanualTrajectory, seed: int) -> dict[str, Any]:
    """``augmentation.json`` of a demonstration of several arms: per arm its objects (start and end
    in the world frame, centre frame), segments, validation and planner record; the arm-pair check."""
    return {
        "parent": twin.episode, "seed": int(seed), "frame": "world",
        "objects": {name: {"T_start": to_centre_frame(twin, name, poses[0]).tolist(),
                           "T_end": to_centre_frame(twin, name, poses[-1]).tolist()}
                    for name, poses in traj.object_poses.items()},
        "object_frame": "centre of the object's bounding box, axes of its reconstructed frame",
        "arms": {name: {"segments": arm.segments, "planner": arm.planner} for name, arm in traj.arms.items()},
        "validation": traj.validation,
    }


def _write_json(path: Path, content: dict) -> None:
    atomic_write_bytes(path, (json.dumps(content, indent=1, default=_jsonable) + "\n").encode())


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
