"""Import one episode of a multi-arm LeRobot v3.0 dataset (a Cobot Magic / ALOHA-style 14-D state and
several ``observation.images.<camera>`` videos) as a version 2 episode: every arm and every camera.

The dataset holds no calibration and does not say its units. The Cobot Magic calibration sidecar
(``*.calib.json``, :func:`~manisplat.episode.importers.cobot_magic.load_calibration`) gives per
camera K, mount and ``T_mount_cam``, per arm ``T_world_base``, its robot description and its
columns of the state (default: left 0..6, right 7..13); the user declares the joint and gripper
units (:mod:`manisplat.episode.importers.units`).

Values are widened from the stored float32 exactly; with ``rad,m`` and a gripper scale of 1 the
episode's joints are those floats bit for bit; other units are multiplied in float64 (degrees:
``value * pi / 180``, millimetres: ``value * 0.001``).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Iterator

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from manisplat.episode.exporters.lerobot import depth_key, image_key
from manisplat.episode.format import EpisodeFormatError
from manisplat.episode.importers.cobot_magic import CobotCalibration, check_cameras, load_calibration
from manisplat.episode.importers.lerobot import (DEPTH_SCALE_MM, EFFORT_KEY, SOURCE, _depth_frames, _episode_row,
                                                 _load_info, _video_frames, has_effort, stored_colour_keys)
from manisplat.episode.importers.units import Units, describe_ranges, require_units, unit_problems
from manisplat.episode.infos import CameraInfo
from manisplat.episode.reader import Episode
from manisplat.episode.writer_v2 import EpisodeWriterV2

log = logging.getLogger(__name__)


def _video_cameras(root: Path, info: dict, cal: CobotCalibration) -> list[str]:
    """The dataset's video cameras (``observation.images.<name>`` -> ``name``); each must be in the calibration."""
    videos = [k.removeprefix(image_key("")) for k, f in info["features"].items()
              if f.get("dtype") == "video" and k.startswith(image_key(""))]
    if not videos:
        images = [k for k, f in info["features"].items() if f.get("dtype") == "image"]
        hint = f"; image-type cameras ({', '.join(images)}) are not supported" if images else ""
        raise EpisodeFormatError(f"{root}: no observation.images.<camera> video features{hint}")
    check_cameras(cal, videos, f"the dataset {root.name}")
    return videos


def _vectors(root: Path, info: dict, table: pa.Table,
             cal: CobotCalibration) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(T, D) float64 ``observation.state``, ``action`` and ``observation.effort`` as stored (None where the
    table does not hold them)."""
    shape = list(info["features"]["observation.state"]["shape"])
    used = [c for joints, gripper in cal.columns.values() for c in (*joints, gripper)]
    if len(shape) != 1 or max(used) >= shape[0]:
        names = info["features"]["observation.state"].get("names")
        raise EpisodeFormatError(f"{root}: observation.state has shape {shape} (names {names}); the arms of "
                                 f"{cal.path} ({', '.join(cal.arms)}) need the columns {sorted(used)}")
    state = np.asarray(table.column("observation.state").to_pylist(), dtype=np.float64)
    action, effort = (np.asarray(table.column(key).to_pylist(), dtype=np.float64) if key in table.column_names
                      else None for key in ("action", EFFORT_KEY))
    return state, action, effort


def import_lerobot_arms(dataset_dir: str | Path, out_dir: str | Path, calib: str | Path | CobotCalibration, *,
                        episode: int, units: Units | None, gripper_scale: float = 1.0, image_format: str = "png",
                        overwrite: bool = False) -> Episode:
    """Convert episode ``episode`` of a multi-arm LeRobot v3.0 dataset into a version 2 episode folder.

    Frame ``i`` gets ``t = frame_index / fps``; each arm of the calibration its ``q1..q6`` (rad) and
    ``gripper`` (m) from its columns of ``observation.state`` in the declared ``units`` (and its
    actions from ``action`` when the dataset has one of the same shape, and its gripper's effort,
    ``<arm>.gripper_effort``, from ``observation.effort`` when present); every
    ``observation.images.<camera>`` its frames decoded from the video (matched to rows by timestamp)
    and its depth from ``depth.<camera>`` (uint16 mm) when present.

    Args:
        dataset_dir: the dataset folder (``meta/``, ``data/``, ``videos/``).
        out_dir: episode folder to create.
        calib: the calibration sidecar (``*.calib.json``) or what :func:`load_calibration` read.
        episode: ``episode_index`` to import.
        units: the stored joint and gripper units; None raises :class:`EpisodeFormatError` with the
            stored value ranges (the dataset cannot tell them).
        gripper_scale: further factor from the gripper value (in metres) to the finger-pad gap.
        image_format: ``"png"`` or ``"jpg"`` for the rgb files.
        overwrite: replace an existing episode at ``out_dir``.

    Returns:
        the new episode, opened for reading.
    """
    root, out_dir = Path(dataset_dir), Path(out_dir)
    info = _load_info(root)
    if "observation.state" not in info["features"]:
        raise EpisodeFormatError(f"{root}: no observation.state feature; it has: {', '.join(info['features'])}")
    cal = calib if isinstance(calib, CobotCalibration) else load_calibration(calib)
    fps = int(info["fps"])
    cameras = _video_cameras(root, info, cal)
    row = _episode_row(root, episode)
    data_path = root / info["data_path"].format(chunk_index=row["data/chunk_index"], file_index=row["data/file_index"])
    if not data_path.is_file():
        raise EpisodeFormatError(f"{root}: episode {episode} points at {data_path.relative_to(root)}, which is missing")
    same_shape = info["features"].get("action", {}).get("shape") == info["features"]["observation.state"]["shape"]
    wanted = ["frame_index", "observation.state"] + (["action"] if same_shape else []) + \
        ([EFFORT_KEY] if has_effort(root, info) else [])
    table = pq.read_table(data_path, columns=wanted, filters=[("episode_index", "=", episode)])
    length = int(row["length"])
    if table.num_rows != length or not np.array_equal(np.asarray(table.column("frame_index")), np.arange(length)):
        raise EpisodeFormatError(f"{data_path}: episode {episode} has {table.num_rows} rows with frame_index "
                                 f"not 0..{length - 1} in order (meta/episodes says length {length})")
    state, action, effort = _vectors(root, info, table, cal)
    effort_columns = cal.gripper_effort_columns if effort is not None else []
    per_arm = {a: state[:, [*j, g]] for a, (j, g) in cal.columns.items()}
    units = require_units(units, [describe_ranges(v, a) for a, v in per_arm.items()], str(root))
    problems = [p for a, v in per_arm.items() for p in unit_problems(v, units, f"arm {a}")]
    if problems:
        raise EpisodeFormatError(f"{root}: observation.state is not in the declared units {units}: "
                                 + "; ".join(problems))
    scale = units.scale() * np.array([1.0] * 6 + [gripper_scale])
    infos = []
    videos: dict[str, Iterator[np.ndarray]] = {}
    for name in cameras:
        key = image_key(name)
        path = root / info["video_path"].format(video_key=key, chunk_index=row[f"videos/{key}/chunk_index"],
                                                file_index=row[f"videos/{key}/file_index"])
        if not path.is_file():
            raise EpisodeFormatError(f"{root}: episode {episode} points at {path.relative_to(root)}, which is missing")
        height, width = info["features"][key]["shape"][:2]
        if cal.sizes.get(name, (width, height)) != (width, height):
            raise EpisodeFormatError(f"{root}: {key} is {width}x{height} but {cal.path} says "
                                     f"{cal.sizes[name][0]}x{cal.sizes[name][1]}")
        infos.append(CameraInfo.from_v2_dict(name, {**cal.cameras[name], "width": width, "height": height,
                                                    **stored_colour_keys(path, image_format)}, list(cal.arms)))
        videos[name] = _video_frames(path, float(row[f"videos/{key}/from_timestamp"]), length, fps)
    depths = {name: _depth_frames(data_path, depth_key(name), episode, length) for name in cameras
              if depth_key(name) in info["features"]}
    tasks = row.get("tasks") or []
    source_info = {"dataset": str(root.resolve()), "episode_index": episode, "calibration": cal.path.name,
                   "arms": {a: {"state_columns": j, "gripper_column": g} for a, (j, g) in cal.columns.items()},
                   "cameras": cameras, "units": str(units), "robot_type": info.get("robot_type"),
                   "codebase_version": info["codebase_version"], "gripper_scale": gripper_scale}
    extra_meta = {"import": source_info, **({"task": tasks[0]} if tasks else {})}
    with EpisodeWriterV2(out_dir, list(cal.arms.values()), infos, float(fps), source=SOURCE,
                         depth_scale=DEPTH_SCALE_MM if depths else None, image_format=image_format,
                         actions=action is not None, extra_frame_columns=effort_columns, extra_meta=extra_meta,
                         overwrite=overwrite) as writer:
        for i in range(length):
            arms = {a: state[i, [*j, g]] * scale for a, (j, g) in cal.columns.items()}
            acts = None if action is None else {a: action[i, [*j, g]] * scale for a, (j, g) in cal.columns.items()}
            grip = None if effort is None else cal.gripper_efforts(effort[i])  # as recorded: its size dates releases
            try:
                writer.add_frame(i / fps, arms, {n: next(v) for n, v in videos.items()},
                                 depth={n: next(d) for n, d in depths.items()}, actions=acts, extra=grip)
            except ValueError as exc:
                raise EpisodeFormatError(f"{root}: episode {episode} frame {i}: {exc}") from exc
    log.info("%s: imported episode %d (%d frames, arms %s, cameras %s) into %s", root, episode, length,
             ", ".join(cal.arms), ", ".join(cameras), out_dir)
    return Episode.open(out_dir)
