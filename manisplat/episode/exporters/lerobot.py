"""Export episodes as a LeRobot v3.0 dataset (what ``lerobot >= 0.4`` loads and trains on).

Layout written (``shared/reference/augmentation.md`` section 5.1; checked against a dataset written by
``lerobot`` 0.4.4's own ``LeRobotDataset.create/add_frame/save_episode/finalize``)::

    meta/info.json                       codebase_version "v3.0", robot_type "piper", fps (int), features, ...
    meta/stats.json                      per feature min/max/mean/std/count/q01/q10/q50/q90/q99 over the dataset
    meta/tasks.parquet                   index: task string, column task_index
    meta/episodes/chunk-000/file-000.parquet   one row per episode: length, tasks, data and video file
                                         indices, dataset_from/to_index, from/to_timestamp, stats/<feature>/<stat>
    meta/augmentation.json               ManiSplat's provenance side file (LeRobot ignores it)
    data/chunk-CCC/file-FFF.parquet      one row per frame: observation.state, action (7 x float32 per arm,
                                         each arm's [q1..q6 rad, gripper m] in the episode's arm order, named
                                         q1..gripper in version 1, left.q1..left.gripper, right.q1.. in
                                         version 2), [depth.<camera> (H, W) uint16 mm per camera with depth],
                                         timestamp (float32, frame_index / fps), frame_index, episode_index,
                                         index, task_index (int64)
    videos/observation.images.<camera>/chunk-CCC/file-FFF.mp4   per camera (cam_high, cam_left_wrist, ...
                                         for a Cobot Magic episode), the RGB frames, yuv420p, one per data row

Many episodes share a file; a new file starts when the next episode would push the current one past
LeRobot's limits (100 MB of data, 200 MB of video per camera; 1000 files per chunk). Each video file is one
continuous stream with frame ``n`` at ``pts = n / fps`` exactly, so an episode's
``from_timestamp`` is its first frame's position in the file and every query timestamp
``from_timestamp + frame_index / fps`` hits a frame exactly (LeRobot's tolerance is 1e-4 s).

Depth, when exported, is a uint16 (H, W) column in millimetres (0 = no depth) named ``depth.<camera>``:
lossless, read back by LeRobot's loader as an integer tensor, and outside ``observation.*`` so that
LeRobot's policies do not take it for robot state. Its stats are scalars over all pixels.

The dataset is written into a hidden folder beside ``out_dir`` and renamed into place when complete,
so an interrupted export never leaves a folder that looks like a dataset.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from tqdm import tqdm

from manisplat.episode.exporters.lerobot_files import CHUNKS_SIZE, DATA_PATH, VIDEO_PATH, DataSeries, VideoSeries
from manisplat.episode.exporters.lerobot_stats import (DepthStats, ImageStats, aggregate_stats, as_lists,
                                                       stats_sample_indices, vector_stats)
from manisplat.episode.exporters.sources import (ExportDestinationError, ExportSource, check_depth, depth_cameras,
                                                 export_cameras, export_frames, open_sources, state_and_action,
                                                 state_names)
from manisplat.episode.exporters.staging import replace_folder, staging_folder
from manisplat.episode.format import EpisodeFormatError
from manisplat.episode.fsio import atomic_write_bytes, fsync_path
from manisplat.episode.meta import CameraInfo
from manisplat.episode.reader import Episode

log = logging.getLogger(__name__)

CODEBASE_VERSION = "v3.0"
ROBOT_TYPE = "piper"
DATA_FILE_SIZE_MB = 100
VIDEO_FILE_SIZE_MB = 200
EPISODES_PATH = "meta/episodes/chunk-000/file-000.parquet"
PROVENANCE_PATH = "meta/augmentation.json"
PROVENANCE_FORMAT = "manisplat-lerobot-export"
VIDEO_CODECS = ("libsvtav1", "h264", "hevc")
"""Encoders LeRobot's own writer offers in software; libsvtav1 (AV1) is its default."""
DEFAULT_CRF = 30
DEFAULT_GOP = 2
"""LeRobot's defaults: CRF 30, a keyframe every 2 frames (cheap random access when training)."""
DEPTH_MM_PER_M = 1000.0
ROWS_PER_BATCH = 64
"""Data rows buffered before they are written as a parquet row group (bounds memory with depth)."""


def image_key(camera: str) -> str:
    """LeRobot feature name of a camera's images."""
    return f"observation.images.{camera}"


def depth_key(camera: str) -> str:
    """Feature name of a camera's depth (outside ``observation.*``: not policy state)."""
    return f"depth.{camera}"


@dataclass(frozen=True)
class LeRobotExportResult:
    """What an export wrote.

    Attributes:
        path: the dataset folder.
        episodes: number of episodes.
        frames: number of frames (data rows, video frames per camera).
        cameras: the cameras exported, in order.
        augmented: how many of the episodes are augmented.
        data_files, video_files: files written per kind.
    """

    path: Path
    episodes: int
    frames: int
    augmented: int
    data_files: int
    video_files: int
    cameras: tuple[str, ...] = ()


# ----------------------------------------------------------------------------------------------- layout


def _features(cameras: Sequence[CameraInfo], depth: Sequence[str], names: list[str], codec: str, fps: int,
              dtype: str) -> dict:
    """``info.json`` ``features``, in LeRobot's order (user features first, then the defaults): state
    and action named ``names``, a video per camera, a depth column per camera in ``depth``."""
    codec_name = av.codec.Codec(codec, "w").canonical_name  # "av1", "h264", "hevc"
    vector = {"dtype": dtype, "shape": [len(names)], "names": list(names)}
    features: dict[str, Any] = {"observation.state": dict(vector), "action": dict(vector)}
    for cam in cameras:
        features[image_key(cam.name)] = {
            "dtype": "video", "shape": [cam.height, cam.width, 3], "names": ["height", "width", "channels"],
            "info": {"video.height": cam.height, "video.width": cam.width, "video.codec": codec_name,
                     "video.pix_fmt": "yuv420p", "video.is_depth_map": False, "video.fps": fps,
                     "video.channels": 3, "has_audio": False}}
    for cam in cameras:
        if cam.name in depth:
            features[depth_key(cam.name)] = {"dtype": "uint16", "shape": [cam.height, cam.width],
                                             "names": ["height", "width"]}
    for name, kind in (("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64"),
                       ("index", "int64"), ("task_index", "int64")):
        features[name] = {"dtype": kind, "shape": [1], "names": None}
    return features


def _schema(features: dict) -> pa.Schema:
    """The data files' Arrow schema, with the ``huggingface`` metadata LeRobot's writer stores."""
    fields, hf = [], {}
    for name, ft in features.items():
        if ft["dtype"] == "video":
            continue
        value = pa.from_numpy_dtype(np.dtype(ft["dtype"]))
        if ft["shape"] == [1]:
            fields.append(pa.field(name, value))
            hf[name] = {"dtype": ft["dtype"], "_type": "Value"}
        elif len(ft["shape"]) == 1:
            fields.append(pa.field(name, pa.list_(value, ft["shape"][0])))
            hf[name] = {"feature": {"dtype": ft["dtype"], "_type": "Value"}, "length": ft["shape"][0], "_type": "List"}
        else:
            fields.append(pa.field(name, pa.list_(pa.list_(value))))
            hf[name] = {"shape": list(ft["shape"]), "dtype": ft["dtype"], "_type": "Array2D"}
    return pa.schema(fields, metadata={b"huggingface": json.dumps({"info": {"features": hf}}).encode()})


def _depth_column(frames: list[np.ndarray]) -> pa.Array:
    """(N, H, W) uint16 frames as an Arrow list<list<uint16>> column (LeRobot's Array2D storage)."""
    stack = np.stack(frames)
    n, height, width = stack.shape
    rows = pa.ListArray.from_arrays(np.arange(0, n * height + 1, dtype=np.int32) * width, pa.array(stack.ravel()))
    return pa.ListArray.from_arrays(np.arange(0, n + 1, dtype=np.int32) * height, rows)


def _fixed_column(values: np.ndarray, dtype: str) -> pa.Array:
    values = np.ascontiguousarray(values, dtype=dtype)
    return pa.FixedSizeListArray.from_arrays(pa.array(values.ravel()), values.shape[1])


def check_destination(out_dir: str | Path, overwrite: bool) -> None:
    """Refuse an ``out_dir`` that is a file, holds something that is not a LeRobot dataset, or holds a
    dataset without ``overwrite``; raises :class:`ExportDestinationError`."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ExportDestinationError(f"--out {out_dir} exists and is not a folder")
    if not out_dir.is_dir() or not any(out_dir.iterdir()):
        return
    if not (out_dir / "meta" / "info.json").is_file():
        raise ExportDestinationError(f"--out {out_dir} is not empty and holds no LeRobot dataset (no meta/info.json); "
                                     "choose another folder (--overwrite replaces only an earlier dataset)")
    if not overwrite:
        raise ExportDestinationError(f"--out {out_dir} already holds a LeRobot dataset; pass --overwrite to replace "
                                     "it (it is removed only once the new one is complete) or choose another folder")


def _episode_fps(sources: list[ExportSource], fps: int | None) -> int:
    """The dataset's integer fps: ``fps``, or the episodes' common rate when it is a whole number."""
    if fps is not None:
        if fps <= 0:
            raise ValueError(f"fps must be positive; got {fps}")
        return int(fps)
    rates = sorted({s.episode.meta.fps for s in sources})
    if len(rates) > 1:
        listing = ", ".join(f"{s.episode.path.name} {s.episode.meta.fps:g}" for s in sources)
        raise EpisodeFormatError(f"episodes of different fps cannot share one LeRobot dataset without --fps "
                                 f"(each episode is then resampled to it): {listing}")
    rate = rates[0]
    if abs(rate - round(rate)) > 1e-6:
        raise EpisodeFormatError(f"LeRobot datasets have a whole-number fps; the episodes are at {rate:g} fps: pass "
                                 f"--fps {max(1, int(rate))} (frames nearest each 1/fps step are exported)")
    return int(round(rate))


def _task_of(src: ExportSource, task: str | None) -> str:
    if task is not None:
        return task
    own = src.episode.meta.extra.get("task")
    if isinstance(own, str) and own.strip():
        return own
    raise EpisodeFormatError(f"{src.episode.path}: no task description in episode.json; pass --task "
                             "\"pick the box and place it on the mat\" (LeRobot stores one per frame)")


@dataclass
class _Writers:
    """Everything open while a dataset is written."""

    data: DataSeries
    videos: dict[str, VideoSeries]
    episode_rows: list[dict[str, Any]] = field(default_factory=list)
    episode_stats: list[dict[str, dict[str, np.ndarray]]] = field(default_factory=list)
    provenance: list[dict[str, Any]] = field(default_factory=list)
    tasks: dict[str, int] = field(default_factory=dict)
    frames: int = 0

    def close(self) -> None:
        self.data.close()
        for video in self.videos.values():
            video.close()


def _depth_mm(ep: Episode, i: int, camera: str) -> np.ndarray:
    """(H, W) uint16 millimetres of frame ``i`` of ``camera`` (0 = no depth)."""
    mm = np.round(np.nan_to_num(ep.depth(i, camera), nan=0.0, posinf=0.0) * DEPTH_MM_PER_M)
    if mm.max(initial=0) > np.iinfo(np.uint16).max:
        raise EpisodeFormatError(f"{ep.path}: camera {camera} frame {i}: depth beyond 65.535 m does not fit uint16 mm")
    return mm.astype(np.uint16)


def _write_episode(w: _Writers, src: ExportSource, frames: np.ndarray, number: int, task: str, fps: int,
                   depth: Sequence[str], dtype: str, bar: tqdm) -> None:
    """Stream frames ``frames`` of one episode into the data file and each camera's video file (depth
    columns for the cameras in ``depth``); record its row and stats."""
    ep = src.episode
    length = len(frames)
    state, action, recorded = state_and_action(ep, frames)
    action_source = "actions" if recorded else "next_state"
    state, action = state.astype(dtype), action.astype(dtype)
    task_index = w.tasks.setdefault(task, len(w.tasks))
    data_chunk, data_file = w.data.begin_episode(length)
    video_rows = {camera: video.begin_episode(length) for camera, video in w.videos.items()}
    first_index = w.frames
    timestamps = (np.arange(length) / fps).astype(np.float32)
    columns = {"timestamp": timestamps, "frame_index": np.arange(length), "episode_index": np.full(length, number),
               "index": first_index + np.arange(length), "task_index": np.full(length, task_index)}
    sampled = set(stats_sample_indices(length).tolist())
    image_stats = {camera: ImageStats() for camera in w.videos}
    depth_stats = {camera: DepthStats() for camera in depth}
    depth_batch: dict[str, list[np.ndarray]] = {camera: [] for camera in depth}
    start = 0
    for k, i in enumerate(frames):
        for camera, video in w.videos.items():
            rgb = ep.rgb(int(i), camera)
            video.write(rgb)
            if k in sampled:
                image_stats[camera].add(rgb)
        for camera in depth:
            mm = _depth_mm(ep, int(i), camera)
            depth_batch[camera].append(mm)
            if k in sampled:
                depth_stats[camera].add(mm)
        if k + 1 - start == ROWS_PER_BATCH or k + 1 == length:
            rows = slice(start, k + 1)
            arrays = {"observation.state": _fixed_column(state[rows], dtype),
                      "action": _fixed_column(action[rows], dtype)}
            for camera in depth:
                arrays[depth_key(camera)] = _depth_column(depth_batch[camera])
                depth_batch[camera] = []
            arrays.update({name: pa.array(values[rows]) for name, values in columns.items()})
            w.data.write(pa.Table.from_arrays([arrays[f.name] for f in w.data.schema],
                                              schema=w.data.schema))
            start = k + 1
        bar.update(1)
    stats = {"observation.state": vector_stats(state), "action": vector_stats(action),
             **{image_key(camera): s.result() for camera, s in image_stats.items()},
             **{depth_key(camera): s.result() for camera, s in depth_stats.items()}}
    stats.update({name: vector_stats(values) for name, values in columns.items()})
    w.episode_stats.append(stats)
    row: dict[str, Any] = {
        "episode_index": number, "tasks": [task], "length": length,
        "data/chunk_index": data_chunk, "data/file_index": data_file,
        "dataset_from_index": first_index, "dataset_to_index": first_index + length}
    for camera, (video_chunk, video_file, from_ts) in video_rows.items():
        key = image_key(camera)
        row.update({f"videos/{key}/chunk_index": video_chunk, f"videos/{key}/file_index": video_file,
                    f"videos/{key}/from_timestamp": from_ts,
                    f"videos/{key}/to_timestamp": w.videos[camera].end_timestamp()})
    for feature, values in stats.items():
        for name, value in values.items():
            row[f"stats/{feature}/{name}"] = value.tolist()
    row.update({"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0})
    w.episode_rows.append(row)
    w.provenance.append({"episode_index": number, **src.provenance(), "frames": length,
                         "recorded_frames": [int(frames[0]), int(frames[-1])], "action": action_source,
                         "task": task})
    w.frames += length


def _write_metadata(root: Path, w: _Writers, features: dict, fps: int, settings: dict[str, Any]) -> None:
    meta = root / "meta"
    (meta / "episodes" / "chunk-000").mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pylist(w.episode_rows), root / EPISODES_PATH)
    tasks = sorted(w.tasks, key=w.tasks.get)
    pandas_meta = {"index_columns": ["__index_level_0__"], "column_indexes": [
        {"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object",
         "metadata": {"encoding": "UTF-8"}}], "columns": [
        {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64",
         "metadata": None},
        {"name": None, "field_name": "__index_level_0__", "pandas_type": "unicode", "numpy_type": "object",
         "metadata": None}], "creator": {"library": "pyarrow", "version": pa.__version__}, "pandas_version": "2.2.0"}
    table = pa.table({"task_index": pa.array([w.tasks[t] for t in tasks], pa.int64()),
                      "__index_level_0__": pa.array(tasks, pa.string())})
    pq.write_table(table.replace_schema_metadata({b"pandas": json.dumps(pandas_meta).encode()}),
                   meta / "tasks.parquet")
    stats = aggregate_stats(w.episode_stats)
    (meta / "stats.json").write_text(json.dumps(as_lists(stats), indent=4))
    info = {"codebase_version": CODEBASE_VERSION, "robot_type": ROBOT_TYPE, "total_episodes": len(w.episode_rows),
            "total_frames": w.frames, "total_tasks": len(tasks), "chunks_size": CHUNKS_SIZE,
            "data_files_size_in_mb": DATA_FILE_SIZE_MB, "video_files_size_in_mb": VIDEO_FILE_SIZE_MB,
            "fps": fps, "splits": {"train": f"0:{len(w.episode_rows)}"}, "data_path": DATA_PATH,
            "video_path": VIDEO_PATH, "features": features}
    (meta / "info.json").write_text(json.dumps(info, indent=4))
    record = {"format": PROVENANCE_FORMAT, "version": 1, **settings, "episodes": w.provenance}
    atomic_write_bytes(root / PROVENANCE_PATH, (json.dumps(record, indent=2) + "\n").encode(), fsync=False)


def _fsync_tree(root: Path) -> None:
    for folder, _, names in os.walk(root):
        for name in names:
            fsync_path(Path(folder) / name)
        fsync_path(Path(folder))


def export_lerobot(episodes: Sequence[str | Path], out_dir: str | Path, *, task: str | None = None,
                   fps: int | None = None, camera: str | Sequence[str] | None = None, depth: bool | None = None,
                   codec: str = "libsvtav1", crf: int = DEFAULT_CRF, gop: int = DEFAULT_GOP, dtype: str = "float32",
                   overwrite: bool = False, progress: bool = False, data_file_size_mb: float = DATA_FILE_SIZE_MB,
                   video_file_size_mb: float = VIDEO_FILE_SIZE_MB) -> LeRobotExportResult:
    """Write ``episodes`` as one LeRobot v3.0 dataset at ``out_dir``, episode ``n`` being the n-th given.

    Everything is checked before anything is written (complete episodes, the same arms and cameras,
    one image size per camera, every image present, a task and a whole-number fps). Frames stream
    one at a time into each camera's video encoder and in batches of ``ROWS_PER_BATCH`` rows into
    the parquet files, so memory does not grow with the number of episodes. ``observation.state``
    is each arm's recorded q1..q6 and gripper gap, arm after arm in the episode's order; ``action``
    each arm's commanded a1..a6, a_gripper, or without them the next frame's state.

    Args:
        episodes: episode folders.
        out_dir: the dataset folder; must be new, empty, or (with ``overwrite``) an earlier dataset.
        task: task description for every episode (default: each episode.json's ``task``).
        fps: dataset rate in Hz (default: the episodes' rate, which must then be one whole number);
            episodes recorded faster are resampled to the frame nearest each ``1/fps`` step.
        camera: the camera or cameras to export, one ``observation.images.<camera>`` video each,
            which every episode must have (default: every camera of the first episode).
        depth: export depth as ``depth.<camera>`` for each camera with depth images in any episode
            (then every episode must have them); default: when there are any; False: none.
        codec: ``libsvtav1`` (LeRobot's default), ``h264`` or ``hevc``.
        crf: encoder quality (lower is better and larger; LeRobot uses 30).
        gop: keyframe interval in frames (LeRobot uses 2).
        dtype: ``float32`` (what LeRobot's policies expect) or ``float64`` (joints round-trip bit-exact).
        overwrite: replace an earlier LeRobot dataset at ``out_dir`` (once the new one is complete).
        progress: show a tqdm progress bar over all frames.
        data_file_size_mb, video_file_size_mb: file size limits (LeRobot's defaults; smaller in tests).

    Returns:
        what was written.
    """
    if codec not in VIDEO_CODECS:
        raise ValueError(f"codec must be one of {VIDEO_CODECS}; got {codec!r}")
    if dtype not in ("float32", "float64"):
        raise ValueError(f"dtype must be float32 or float64; got {dtype!r}")
    if not 0 <= crf <= 63 or gop < 1:
        raise ValueError(f"crf must be in 0..63 and gop >= 1; got crf={crf}, gop={gop}")
    out_dir = Path(out_dir)
    check_destination(out_dir, overwrite)
    sources = open_sources(episodes, "LeRobot", same_fps=False)
    cameras = export_cameras(sources, camera, "LeRobot")
    names = [c.name for c in cameras]
    with_depth = depth_cameras(sources, names) if depth is None or depth else []
    if depth and not with_depth:
        raise EpisodeFormatError(f"depth asked for, but no episode has depth images from {', '.join(names)}")
    check_depth(sources, with_depth)
    rate = _episode_fps(sources, fps)
    tasks = [_task_of(s, task) for s in sources]
    for cam in cameras:
        if cam.width % 2 or cam.height % 2:
            raise EpisodeFormatError(f"camera {cam.name}: {cam.width}x{cam.height} images: yuv420p video needs an "
                                     "even width and height")
    frames = [export_frames(src.episode, rate) for src in sources]  # raises now, before anything is written
    features = _features(cameras, with_depth, state_names(sources[0].episode), codec, rate, dtype)
    staging = staging_folder(out_dir)
    writers = _Writers(DataSeries(staging, _schema(features), data_file_size_mb * 1024 ** 2),
                       {cam.name: VideoSeries(staging, image_key(cam.name), codec, rate, cam.width, cam.height, crf,
                                              gop, video_file_size_mb * 1024 ** 2) for cam in cameras})
    settings = {"fps": rate, "cameras": names, "codec": codec, "crf": crf, "gop": gop, "depth": bool(with_depth),
                "depth_cameras": with_depth, "dtype": dtype}
    try:
        total = sum(len(f) for f in frames)
        with tqdm(total=total, desc="export lerobot", unit="frame", disable=not progress) as bar:
            for number, (src, chosen, text) in enumerate(zip(sources, frames, tasks)):
                _write_episode(writers, src, chosen, number, text, rate, with_depth, dtype, bar)
        writers.close()
        _write_metadata(staging, writers, features, rate, settings)
        _fsync_tree(staging)
        replace_folder(staging, out_dir)
    except BaseException:
        writers.close()
        shutil.rmtree(staging, ignore_errors=True)
        raise
    augmented = sum(s.augmented for s in sources)
    log.info("exported %d episodes (%d frames, %d augmented) as a LeRobot dataset at %s", len(sources),
             writers.frames, augmented, out_dir)
    return LeRobotExportResult(out_dir, len(sources), writers.frames, augmented, writers.data.files,
                               sum(video.files for video in writers.videos.values()), tuple(names))
