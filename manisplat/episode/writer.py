"""Write an episode crash-safely, frame by frame: :class:`WriterBase` (what every writer shares) and
:class:`EpisodeWriter` (format version 1; version 2 is :mod:`manisplat.episode.writer_v2`).

Order of writes: ``episode.json`` with ``complete: false`` first (atomically), then for each frame
its image files (temporary name + rename, so an image is whole or absent), then its
``frames.csv`` row (one ``write`` + flush). A killed writer therefore leaves at most a torn last
row, a temporary image and images without a row, which ``recover`` clears away. Files and
folders are fsynced every ``fsync_every`` rows and at ``close``, which rewrites ``episode.json``
with ``complete: true`` and the ``frame_count``.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Mapping, Sequence

import numpy as np

from manisplat.episode.format import (FRAME_COLUMNS, FRAMES_FILE, JOINT_COLUMNS, JOINTS_FILE, META_FILE,
                                      image_name)
from manisplat.episode.fsio import atomic_write_bytes, fsync_path
from manisplat.episode.images import DEPTH, MASK, RGB, depth_to_raw, encode_image
from manisplat.episode.meta import CameraInfo, EpisodeMeta, RobotInfo, save_meta
from manisplat.episode.tables import format_row

log = logging.getLogger(__name__)

IMAGE_FORMATS = {"png": ".png", "jpg": ".jpg"}


def _finite(name: str, value: Any) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number; got {value!r}") from None
    if not math.isfinite(x):
        raise ValueError(f"{name} must be finite; got {x}")
    return x


def _joint_vector(name: str, q: Any) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (6,):
        raise ValueError(f"{name} must hold 6 joint angles (radians); got shape {q.shape}")
    if not np.isfinite(q).all():
        raise ValueError(f"{name} must be finite; got {q.tolist()}")
    return q


def _extra_values(name: str, extra: Mapping[str, Any] | None, columns: tuple[str, ...]) -> list[float]:
    extra = dict(extra or {})
    missing = [c for c in columns if c not in extra]
    unknown = [c for c in extra if c not in columns]
    if missing or unknown:
        raise ValueError(f"{name}: extra must give exactly the declared columns {list(columns)}; "
                         f"missing {missing}, undeclared {unknown}")
    return [_finite(f"{name}: extra[{c!r}]", extra[c]) for c in columns]


def _check_columns(name: str, columns: Sequence[str], required: tuple[str, ...]) -> tuple[str, ...]:
    columns = tuple(columns)
    bad = [c for c in columns if c in required or not c or any(ch in c for ch in ", \t\r\n")]
    if bad or len(set(columns)) != len(columns):
        raise ValueError(f"{name} must be distinct names without commas or spaces, other than "
                         f"{list(required)}; got {list(columns)}")
    return columns


def check_destination(path: Path, overwrite: bool) -> bool:
    """Whether a new episode may go to ``path``: True when an episode there is to be replaced,
    False when ``path`` is free (missing or an empty folder).

    Raises:
        FileExistsError: ``path`` is a file, a non-empty folder that holds no episode (always
            refused), or an episode and not ``overwrite``.
    """
    if not path.exists():
        return False
    if not path.is_dir():
        raise FileExistsError(f"{path}: exists and is not a folder")
    if not any(path.iterdir()):
        return False
    if not (path / META_FILE).exists():
        raise FileExistsError(f"{path}: folder is not empty and holds no episode; refusing to write into it")
    if not overwrite:
        raise FileExistsError(f"{path}: an episode already exists here; replace it with --overwrite")
    return True


def _prepare_folder(path: Path, overwrite: bool) -> None:
    if check_destination(path, overwrite):
        shutil.rmtree(path)
    path.mkdir(parents=True, exist_ok=True)


class WriterBase:
    """What every episode writer shares: the folder, ``episode.json`` written first with
    ``complete: false`` and last with ``complete: true``, CSV tables appended row by row and
    flushed, image files written through a temporary name, fsync every ``fsync_every`` rows and
    at ``close``. Subclasses add the rows (:class:`EpisodeWriter` version 1,
    :class:`~manisplat.episode.writer_v2.EpisodeWriterV2` version 2)."""

    def __init__(self, path: str | Path, meta: EpisodeMeta, frame_columns: tuple[str, ...], *,
                 fsync_every: int, overwrite: bool) -> None:
        if fsync_every < 0:
            raise ValueError(f"fsync_every must be >= 0; got {fsync_every}")
        self.meta = meta
        self.path = Path(path)
        self._fsync_every = fsync_every
        _prepare_folder(self.path, overwrite)
        (self.path / RGB.folder).mkdir()
        save_meta(self.path / META_FILE, self.meta)
        self._frames = self._open_table(FRAMES_FILE, frame_columns)
        self._tables: dict[str, IO[str]] = {}  # joint streams by file name
        self._frame_count = 0
        self._joint_count = 0
        self._unsynced: list[Path] = []
        self._rows_since_sync = 0
        self._closed = False

    def _open_table(self, name: str, columns: tuple[str, ...]) -> IO[str]:
        f = open(self.path / name, "x", encoding="utf-8", newline="")
        f.write(",".join(columns) + "\n")
        f.flush()
        os.fsync(f.fileno())
        fsync_path(self.path)
        return f

    def __enter__(self) -> WriterBase:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is None:
            self.close()
        else:
            self._close_files()
            log.warning("%s: writer stopped by %s; the episode stays incomplete "
                        "(run `manisplat-episode recover %s`)", self.path, exc_type.__name__, self.path)

    @property
    def frame_count(self) -> int:
        """Frames written so far."""
        return self._frame_count

    @property
    def closed(self) -> bool:
        return self._closed

    def _check_open(self, name: str) -> None:
        if self._closed:
            raise ValueError(f"{name}: the writer of {self.path} is closed")

    def _write_bytes(self, folder: str, name: str, data: bytes) -> None:
        """Write one image file of ``folder`` (relative to the episode, created when missing) atomically."""
        path = self.path / folder / name
        if not path.parent.is_dir():
            path.parent.mkdir(parents=True)
            fsync_path(path.parent.parent)
            if path.parent.parent != self.path:
                fsync_path(self.path)
        atomic_write_bytes(path, data, fsync=False)  # synced in batches
        self._unsynced.append(path)

    def _write_frame_row(self, values: Sequence[float | int]) -> None:
        self._frames.write(format_row(values))
        self._frames.flush()
        self._frame_count += 1
        self._row_written()

    def _write_joint_row(self, file: str, columns: tuple[str, ...], values: Sequence[float]) -> None:
        """Append a row to the joint stream ``file`` (created with ``columns`` by its first row)."""
        if file not in self._tables:
            self._tables[file] = self._open_table(file, columns)
        self._tables[file].write(format_row(values))
        self._tables[file].flush()
        self._joint_count += 1
        self._row_written()

    def _row_written(self) -> None:
        self._rows_since_sync += 1
        if self._fsync_every and self._rows_since_sync >= self._fsync_every:
            self.sync()

    def sync(self) -> None:
        """Flush and fsync everything written so far (images, their folders, the CSV files)."""
        self._check_open("sync")
        for path in self._unsynced:
            fsync_path(path)
        for folder in {p.parent for p in self._unsynced}:
            fsync_path(folder)
        self._unsynced.clear()
        for f in (self._frames, *self._tables.values()):
            f.flush()
            os.fsync(f.fileno())
        self._rows_since_sync = 0

    def _close_files(self) -> None:
        if self._closed:
            return
        self.sync()
        for f in (self._frames, *self._tables.values()):
            f.close()
        self._closed = True

    def close(self) -> None:
        """Sync and close the files, then mark the episode complete with its ``frame_count``."""
        if self._closed:
            return
        self._close_files()
        self.meta.complete = True
        self.meta.frame_count = self._frame_count
        save_meta(self.path / META_FILE, self.meta)
        if not self._frame_count:
            log.warning("%s: closed without a frame; an episode needs at least one, so it is not valid", self.path)
        log.info("%s: wrote %d frames, %d joint samples", self.path, self._frame_count, self._joint_count)


class EpisodeWriter(WriterBase):
    """Writes one episode folder (``docs/episode-format.md``); use it as a context manager.

    Args:
        path: episode folder to create. An existing episode there is refused unless
            ``overwrite`` (then it is deleted); a non-empty folder that is no episode is always refused.
        camera: the camera; every rgb/depth/mask must have its size.
        robot: the arm (joint names, how to read the angles).
        fps: declared camera rate in Hz.
        source: ``episode.json`` ``source`` (``"recorder"``, ``"simulation"``, ``"import:..."``).
        depth_scale: metres per depth unit; required to write depth.
        labels: mask value -> name.
        objects: names of the manipulated objects.
        image_format: ``"png"`` (lossless) or ``"jpg"`` for rgb; depth and masks are always PNG.
        extra_frame_columns: names of optional ``frames.csv`` columns (``seq``, ``a1``..``a_gripper``);
            every ``add_frame`` must give exactly these in ``extra``.
        joint_columns: names of optional ``joints.csv`` columns, likewise for ``add_joint_sample``.
        extra_meta: further top-level ``episode.json`` keys (e.g. ``{"task": "pick the box"}``).
        fsync_every: fsync written images and rows every this many rows (0: only at ``close``).
            A killed process loses at most the frame being written whatever this is; after a
            power loss the rows since the last fsync may be lost (``recover`` drops them).

    If the ``with`` block raises, the files are closed and ``complete`` stays false.
    """

    def __init__(self, path: str | Path, camera: CameraInfo, robot: RobotInfo, fps: float, *,
                 source: str = "recorder", depth_scale: float | None = None,
                 labels: Mapping[int, str] | None = None, objects: Sequence[str] | None = None,
                 image_format: str = "png", extra_frame_columns: Sequence[str] = (),
                 joint_columns: Sequence[str] = (), extra_meta: Mapping[str, Any] | None = None,
                 fsync_every: int = 30, overwrite: bool = False) -> None:
        if image_format not in IMAGE_FORMATS:
            raise ValueError(f"image_format must be one of {sorted(IMAGE_FORMATS)}; got {image_format!r}")
        # file suffix per image folder: rgb as asked, depth and masks in their one (lossless) format
        self._suffixes = {RGB.folder: IMAGE_FORMATS[image_format], DEPTH.folder: DEPTH.suffixes[0],
                          MASK.folder: MASK.suffixes[0]}
        self._frame_columns = _check_columns("extra_frame_columns", extra_frame_columns, FRAME_COLUMNS)
        self._joint_columns = _check_columns("joint_columns", joint_columns, JOINT_COLUMNS)
        meta = EpisodeMeta(complete=False, source=source, robot=robot, camera=camera, fps=fps,
                           depth_scale=depth_scale, labels=dict(labels or {}), objects=list(objects or []),
                           extra=dict(extra_meta or {}))
        super().__init__(path, meta, FRAME_COLUMNS + self._frame_columns, fsync_every=fsync_every,
                         overwrite=overwrite)
        self._last_t: float | None = None
        self._last_joint_t: float | None = None
        self._layers: tuple[bool, bool] | None = None  # (depth, mask), fixed by frame 0

    def _check_image(self, name: str, image: Any, channels: int, dtypes: tuple[type, ...]) -> np.ndarray:
        image = np.asarray(image)
        cam = self.meta.camera
        shape = (cam.height, cam.width) + ((channels,) if channels > 1 else ())
        if image.shape != shape or not any(image.dtype == d for d in dtypes):
            want = " or ".join(np.dtype(d).name for d in dtypes)
            raise ValueError(f"add_frame: {name} must be {shape} {want} for camera {cam.name!r} "
                             f"({cam.width}x{cam.height}); got {image.shape} {image.dtype}")
        return image

    def _depth_raw(self, depth: Any) -> np.ndarray:
        depth = self._check_image("depth", depth, 1, (np.float32, np.float64, np.uint16))
        if self.meta.depth_scale is None:
            raise ValueError("add_frame: depth given but the writer has no depth_scale (metres per unit)")
        return depth if depth.dtype == np.uint16 else depth_to_raw(depth, self.meta.depth_scale)

    def encode_frame(self, rgb: np.ndarray, depth: np.ndarray | None = None,
                     mask: np.ndarray | None = None) -> dict[str, bytes]:
        """Check and encode one frame's images (arguments as in :meth:`add_frame`), keyed by
        folder, for ``add_frame(..., encoded=...)``. It touches no file and no counter, so other
        threads may encode frames in parallel while one thread adds them in order."""
        suffix = self._suffixes
        encoded = {RGB.folder: encode_image(suffix[RGB.folder], self._check_image("rgb", rgb, 3, (np.uint8,)),
                                            rgb=True)}
        if depth is not None:
            encoded[DEPTH.folder] = encode_image(suffix[DEPTH.folder], self._depth_raw(depth), rgb=False)
        if mask is not None:
            encoded[MASK.folder] = encode_image(suffix[MASK.folder], self._check_image("mask", mask, 1, (np.uint8,)),
                                                rgb=False)
        return encoded

    def add_frame(self, t: float, q: Any, gripper: float, rgb: np.ndarray, depth: np.ndarray | None = None,
                  mask: np.ndarray | None = None, extra: Mapping[str, float] | None = None, *,
                  encoded: Mapping[str, bytes] | None = None) -> int:
        """Write one frame: its images first, then its ``frames.csv`` row. Returns its index.

        Args:
            t: seconds on the episode clock, strictly after the previous frame's.
            q: (6,) joint angles in radians.
            gripper: finger-pad gap in metres.
            rgb: (H, W, 3) uint8 RGB.
            depth: (H, W) float metres (non-finite or <= 0: invalid, stored 0) or uint16 raw units.
            mask: (H, W) uint8 labels.
            extra: values of the declared ``extra_frame_columns``.
            encoded: what :meth:`encode_frame` returned for these ``rgb``, ``depth`` and
                ``mask`` (written as given, not encoded again), or None.

        Every frame must carry the same kinds of image (depth, mask) as frame 0.
        """
        self._check_open("add_frame")
        t = _finite("add_frame: t", t)
        if self._last_t is not None and not t > self._last_t:
            raise ValueError(f"add_frame: t={t!r} must be after the previous frame's t={self._last_t!r}")
        q = _joint_vector("add_frame: q", q)
        gripper = _finite("add_frame: gripper", gripper)
        extras = _extra_values("add_frame", extra, self._frame_columns)
        layers = (depth is not None, mask is not None)
        if self._layers is not None and layers != self._layers:
            raise ValueError(f"add_frame: frame 0 had (depth, mask) = {self._layers}, this frame has {layers}; "
                             "every frame must carry the same images")
        if encoded is None:
            encoded = self.encode_frame(rgb, depth, mask)
        expected = {RGB.folder} | ({DEPTH.folder} if layers[0] else set()) | ({MASK.folder} if layers[1] else set())
        if set(encoded) != expected:
            raise ValueError(f"add_frame: encoded images {sorted(encoded)} do not match the frame's {sorted(expected)}")

        index = self._frame_count
        for folder, suffix in self._suffixes.items():
            if folder in encoded:
                self._write_bytes(folder, image_name(index, suffix), encoded[folder])
        self._write_frame_row([index, t, *q, gripper, *extras])
        self._layers = layers
        self._last_t = t
        return index

    def add_joint_sample(self, t: float, q: Any, gripper: float, extra: Mapping[str, float] | None = None) -> None:
        """Append one arm feedback sample to ``joints.csv`` (created by the first call).

        Args:
            t: seconds on the episode clock (the clock of ``add_frame``), strictly increasing.
            q: (6,) joint angles in radians.
            gripper: finger-pad gap in metres.
            extra: values of the declared ``joint_columns``.
        """
        self._check_open("add_joint_sample")
        t = _finite("add_joint_sample: t", t)
        if self._last_joint_t is not None and not t > self._last_joint_t:
            raise ValueError(f"add_joint_sample: t={t!r} must be after the previous sample's t={self._last_joint_t!r}")
        q = _joint_vector("add_joint_sample: q", q)
        gripper = _finite("add_joint_sample: gripper", gripper)
        extras = _extra_values("add_joint_sample", extra, self._joint_columns)
        self._write_joint_row(JOINTS_FILE, JOINT_COLUMNS + self._joint_columns, [t, *q, gripper, *extras])
        self._last_joint_t = t
