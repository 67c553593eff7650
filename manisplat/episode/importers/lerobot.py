"""Import one episode of a LeRobot v3.0 dataset (``meta/info.json`` ``codebase_version "v3.0"``).

What is read (``shared/reference/augmentation.md`` section 5.1): the episode's row in
``meta/episodes/*/*.parquet`` (its data and video files, ``from_timestamp``, task), its rows of
``data/chunk-*/file-*.parquet`` (``observation.state``, ``action``, ``observation.effort`` and
``depth.<camera>`` when present, ``frame_index``), and its frames of the camera's video, decoded with
PyAV and matched to rows by timestamp (``from_timestamp + frame_index / fps``, within LeRobot's 1e-4 s tolerance). Rows
and frames stream one at a time into the episode writer. The video's pixel format says how its
colour was kept (``yuv420p``: one colour sample per 2 x 2 pixels); PNG frames keep no trace of it,
so the camera's ``chroma_subsampling`` in ``episode.json`` records it.
"""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path
from typing import Any, Iterator

import av
import numpy as np
import pyarrow.dataset as pads
import pyarrow.parquet as pq

from manisplat.episode.exporters.lerobot import depth_key, image_key
from manisplat.episode.format import ACTION_COLUMNS, GRIPPER_EFFORT_COLUMN, EpisodeFormatError
from manisplat.episode.chroma import video_chroma
from manisplat.episode.images import CHROMA_KEYS, chroma_keys
from manisplat.episode.importers.act_hdf5 import ARM_COLUMNS
from manisplat.episode.importers.units import Units, unit_problems
from manisplat.episode.meta import CameraInfo, RobotInfo
from manisplat.episode.reader import Episode
from manisplat.episode.writer import EpisodeWriter

log = logging.getLogger(__name__)

SOURCE = "import:lerobot"
TOLERANCE_S = 1e-4
"""LeRobot's default ``tolerance_s`` between a query timestamp and a decoded frame."""
DEPTH_SCALE_MM = 0.001
SUPPORTED_VERSION = "v3.0"
EFFORT_KEY = "observation.effort"
"""The motors' efforts (ALOHA / Cobot Magic datasets), laid out like ``observation.state``."""


def _load_info(root: Path) -> dict[str, Any]:
    path = root / "meta" / "info.json"
    if not path.is_file():
        raise EpisodeFormatError(f"{root}: no meta/info.json; not a LeRobot dataset")
    try:
        info = json.loads(path.read_text())
    except ValueError as exc:
        raise EpisodeFormatError(f"{path}: not valid JSON: {exc}") from exc
    version = info.get("codebase_version")
    if version != SUPPORTED_VERSION:
        raise EpisodeFormatError(f"{path}: codebase_version {version!r}; only {SUPPORTED_VERSION} is read (convert "
                                 "older datasets with lerobot's convert_dataset_v21_to_v30 script)")
    for key in ("fps", "features", "data_path", "video_path"):
        if key not in info:
            raise EpisodeFormatError(f"{path}: no {key!r}")
    return info


def _episode_row(root: Path, episode: int) -> dict[str, Any]:
    files = sorted((root / "meta" / "episodes").glob("*/*.parquet"))
    if not files:
        raise EpisodeFormatError(f"{root}: no meta/episodes/chunk-*/file-*.parquet")
    table = pads.dataset([str(f) for f in files], format="parquet")
    columns = [c for c in table.schema.names if not c.startswith("stats/")]
    rows = table.to_table(columns=columns, filter=pads.field("episode_index") == episode).to_pylist()
    if not rows:
        indices = table.to_table(columns=["episode_index"]).column(0).to_pylist()
        span = f"{min(indices)}..{max(indices)}" if indices else "none"
        raise EpisodeFormatError(f"{root}: no episode {episode} (episodes {span})")
    return rows[0]


def _camera_key(info: dict[str, Any], camera: str) -> str:
    videos = [k for k, f in info["features"].items() if f.get("dtype") == "video"]
    for key in (camera, image_key(camera)):
        if key in videos:
            return key
    images = [k for k, f in info["features"].items() if f.get("dtype") == "image"]
    hint = f"; image-type cameras ({', '.join(images)}) are not supported" if images else ""
    raise EpisodeFormatError(f"no video camera {camera!r} in the dataset; it has: {', '.join(videos) or 'none'}{hint}")


def has_effort(root: Path, info: dict[str, Any]) -> bool:
    """Whether the dataset has an ``observation.effort`` to import (its gripper columns: the episode's
    ``gripper_effort``, which dates releases); one not laid out like ``observation.state`` is refused."""
    feature = info["features"].get(EFFORT_KEY)
    if feature is None:
        return False
    shape, state = list(feature.get("shape", [])), list(info["features"]["observation.state"]["shape"])
    if shape != state:
        raise EpisodeFormatError(f"{root}: {EFFORT_KEY} has shape {shape}; expected observation.state's {state} "
                                 "(which of its columns are the grippers' cannot be told)")
    return True


def _arm_columns(info: dict[str, Any], key: str, arm: str) -> slice:
    shape = list(info["features"][key]["shape"])
    width = {"single": 7}.get(arm, 14)
    if shape != [width]:
        expected = ("[7] for --arm single" if arm == "single"
                    else "[14] [left 6 joints, left gripper, right 6, right gripper] for --arm left/right")
        raise EpisodeFormatError(f"feature {key!r} has shape {shape}; expected {expected}")
    return ARM_COLUMNS[arm]


def _video_frames(path: Path, start_s: float, count: int, fps: int) -> Iterator[np.ndarray]:
    """(H, W, 3) uint8 RGB frames ``0..count-1`` of an episode starting at ``start_s`` in ``path``."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        if start_s > 0:
            container.seek(int(start_s / stream.time_base), stream=stream, backward=True, any_frame=False)
        expected = 0
        for frame in container.decode(stream):
            if frame.pts is None:
                continue
            offset = float(frame.pts * frame.time_base) - start_s
            index = round(offset * fps)
            if index < expected:
                continue  # frames of the previous episode, decoded from the keyframe before the seek point
            if abs(offset - index / fps) > TOLERANCE_S or index != expected:
                raise EpisodeFormatError(f"{path}: frame {expected} of the episode should be at "
                                         f"{start_s + expected / fps:.6f} s; the video has one at "
                                         f"{start_s + offset:.6f} s (LeRobot's tolerance is {TOLERANCE_S} s)")
            yield frame.to_ndarray(format="rgb24")
            expected += 1
            if expected == count:
                return
    raise EpisodeFormatError(f"{path}: the video ends after {expected} of the episode's {count} frames")


def stored_colour_keys(video: Path, image_format: str) -> dict[str, Any]:
    """The camera's ``chroma_subsampling`` keys for frames decoded from ``video`` and stored as
    ``image_format`` files: the video's (:func:`~manisplat.episode.chroma.video_chroma`) for PNG,
    none for JPEG files, whose header says how they were kept."""
    return {} if image_format == "jpg" else chroma_keys(video_chroma(video))


def _depth_frames(path: Path, key: str, episode: int, count: int) -> Iterator[np.ndarray]:
    """(H, W) uint16 depth of the episode's rows in ``path``, in order, read a row group at a time."""
    served = 0
    for batch in pq.ParquetFile(path).iter_batches(batch_size=64, columns=["episode_index", key]):
        mine = np.asarray(batch.column(0)) == episode
        if not mine.any():
            continue
        column = batch.column(1).filter(mine)
        for value in column.to_pylist():
            yield np.asarray(value, dtype=np.uint16)
            served += 1
    if served != count:
        raise EpisodeFormatError(f"{path}: {served} {key} rows for episode {episode}; expected {count}")


def import_lerobot(dataset_dir: str | Path, out_dir: str | Path, *, episode: int, camera: str, K: Any = None,
                   arm: str = "single", units: Units | None = None, gripper_scale: float = 1.0, dist: Any = (),
                   mount: str = "base",
                   robot_description: str = "builtin:agilex_piper", image_format: str = "png",
                   overwrite: bool = False) -> Episode:
    """Convert episode ``episode`` of a LeRobot v3.0 dataset into an episode folder.

    Frame ``i`` gets ``t = frame_index / fps``, ``q1..q6`` and ``gripper`` from ``observation.state``,
    ``a1..a6, a_gripper`` from ``action`` (when the dataset has one of the same layout),
    ``gripper_effort`` from the gripper's column of ``observation.effort`` (when present), the image
    decoded from the camera's video, and the depth from ``depth.<camera>`` (uint16 millimetres) when
    present. Values are read as stored (float32 -> float64 exactly), so a ManiSplat export comes back
    with the same joints bit for bit.

    Args:
        dataset_dir: the dataset folder (``meta/``, ``data/``, ``videos/``).
        out_dir: episode folder to create.
        episode: ``episode_index`` to import.
        camera: the video feature (``observation.images.cam_high``) or its camera name (``cam_high``).
        K: (3, 3) intrinsics in pixels, required: LeRobot datasets store none; or a :class:`CameraInfo`.
        arm: ``"single"`` for 7-D state/action, ``"left"``/``"right"`` for a 14-D dual-arm layout.
        units: the stored joint and gripper units (default: radians and metres, as ManiSplat exports);
            values that cannot be in them are refused.
        gripper_scale: factor from the dataset's gripper value to the finger-pad gap in metres.
        dist, mount: distortion coefficients and mount (when K is an array).
        robot_description: ``episode.json`` ``robot.description``.
        image_format: ``"png"`` or ``"jpg"`` for the rgb files.
        overwrite: replace an existing episode at ``out_dir``.

    Returns:
        the new episode, opened for reading.
    """
    root, out_dir = Path(dataset_dir), Path(out_dir)
    if K is None:
        raise EpisodeFormatError(f"{root}: LeRobot datasets store no camera intrinsics; pass K (pixels, from your "
                                 "calibration or the camera's factory values), e.g. `manisplat-episode "
                                 "import-lerobot DATASET --K fx,fy,cx,cy ...`")
    if arm not in ARM_COLUMNS:
        raise ValueError(f"arm must be one of {sorted(ARM_COLUMNS)}; got {arm!r}")
    info = _load_info(root)
    fps = int(info["fps"])
    key = _camera_key(info, camera)
    if "observation.state" not in info["features"]:
        raise EpisodeFormatError(f"{root}: no observation.state feature; it has: {', '.join(info['features'])}")
    columns = _arm_columns(info, "observation.state", arm)
    has_action = "action" in info["features"] and list(info["features"]["action"]["shape"]) == \
        list(info["features"]["observation.state"]["shape"])
    effort_read = has_effort(root, info)
    camera_name = key.removeprefix(image_key(""))
    depth_name = depth_key(camera_name)
    has_depth = depth_name in info["features"]
    row = _episode_row(root, episode)
    data_path = root / info["data_path"].format(chunk_index=row["data/chunk_index"], file_index=row["data/file_index"])
    video_path = root / info["video_path"].format(video_key=key, chunk_index=row[f"videos/{key}/chunk_index"],
                                                  file_index=row[f"videos/{key}/file_index"])
    for path in (data_path, video_path):
        if not path.is_file():
            raise EpisodeFormatError(f"{root}: episode {episode} points at {path.relative_to(root)}, which is missing")
    wanted = ["frame_index", "observation.state"] + (["action"] if has_action else []) + \
        ([EFFORT_KEY] if effort_read else [])
    table = pq.read_table(data_path, columns=wanted, filters=[("episode_index", "=", episode)])
    length = int(row["length"])
    frame_index = np.asarray(table.column("frame_index"))
    if table.num_rows != length or not np.array_equal(frame_index, np.arange(length)):
        raise EpisodeFormatError(f"{data_path}: episode {episode} has {table.num_rows} rows with frame_index "
                                 f"not 0..{length - 1} in order (meta/episodes says length {length})")
    scale = (Units("rad", "m") if units is None else units).scale() * np.array([1.0] * 6 + [gripper_scale])
    state = np.asarray(table.column("observation.state").to_pylist(), dtype=np.float64)[:, columns]
    problems = [] if units is None else unit_problems(state, units, f"arm {arm}")
    if problems:
        raise EpisodeFormatError(f"{root}: observation.state is not in the declared units {units}: "
                                 + "; ".join(problems))
    state = state * scale
    action = (np.asarray(table.column("action").to_pylist(), dtype=np.float64)[:, columns] * scale
              if has_action else None)
    effort = (np.asarray(table.column(EFFORT_KEY).to_pylist(), dtype=np.float64)[:, columns][:, 6]
              if effort_read else None)  # as recorded: its size dates the release, not its units
    height, width = info["features"][key]["shape"][:2]
    cam = K if isinstance(K, CameraInfo) else CameraInfo(name=camera_name, width=width, height=height, K=K,
                                                         dist=dist, mount=mount)
    kept = {k: v for k, v in cam.extra.items() if k not in CHROMA_KEYS}  # a given camera's say of other images
    cam = replace(cam, extra={**kept, **stored_colour_keys(video_path, image_format)})
    if (cam.width, cam.height) != (width, height):
        raise EpisodeFormatError(f"{root}: {key} is {width}x{height} but the camera is {cam.width}x{cam.height}")
    tasks = row.get("tasks") or []
    source_info = {"dataset": str(root.resolve()), "episode_index": episode, "camera": key, "arm": arm,
                   "robot_type": info.get("robot_type"), "codebase_version": info["codebase_version"],
                   "gripper_scale": gripper_scale}
    extra_meta = {"import": source_info, **({"task": tasks[0]} if tasks else {})}
    frames = _video_frames(video_path, float(row[f"videos/{key}/from_timestamp"]), length, fps)
    depths = _depth_frames(data_path, depth_name, episode, length) if has_depth else None
    frame_columns = ((*ACTION_COLUMNS,) if action is not None else ()) + ((GRIPPER_EFFORT_COLUMN,) if effort_read
                                                                          else ())
    with EpisodeWriter(out_dir, cam, RobotInfo(description=robot_description), float(fps), source=SOURCE,
                       depth_scale=DEPTH_SCALE_MM if has_depth else None, image_format=image_format,
                       extra_frame_columns=frame_columns, extra_meta=extra_meta, overwrite=overwrite) as writer:
        for i, rgb in enumerate(frames):
            extra = {} if action is None else dict(zip(ACTION_COLUMNS, action[i].tolist()))
            if effort is not None:
                extra[GRIPPER_EFFORT_COLUMN] = float(effort[i])
            depth = None if depths is None else next(depths)
            try:
                writer.add_frame(i / fps, state[i, :6], state[i, 6], rgb, depth=depth, extra=extra or None)
            except ValueError as exc:
                raise EpisodeFormatError(f"{root}: episode {episode} frame {i}: {exc}") from exc
    log.info("%s: imported episode %d (%d frames) into %s", root, episode, length, out_dir)
    return Episode.open(out_dir)
