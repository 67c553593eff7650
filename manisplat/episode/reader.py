"""Read an episode: metadata and tables at once, images lazily, one frame at a time."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Iterator

import numpy as np

from manisplat.episode.format import (ACTION_COLUMNS, FRAME_COLUMNS, FRAMES_FILE, GT_FILE, JOINT_COLUMNS,
                                      JOINTS_FILE, META_FILE, EpisodeFormatError)
from manisplat.episode.groundtruth import read_gt
from manisplat.episode.images import DEPTH, MASK, RGB, ImageKind, find_image, has_images, load_image, raw_to_depth
from manisplat.episode.meta import CameraInfo, EpisodeMeta, load_meta
from manisplat.episode.tables import CsvScan, scan_csv

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameTable:
    """``frames.csv`` as arrays over the T frames.

    Attributes:
        index: (T,) int64 frame numbers, 0..T-1.
        t: (T,) float64 seconds on the episode clock.
        q: (T, 6) float64 joint angles in radians.
        gripper: (T,) float64 finger-pad gap in metres.
        extra: optional column name -> (T,) float64 (``seq``, ``a1``..``a6``, ``a_gripper``, ...).
    """

    index: np.ndarray
    t: np.ndarray
    q: np.ndarray
    gripper: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.t)

    @property
    def actions(self) -> np.ndarray | None:
        """(T, 7) float64 commanded ``a1..a6, a_gripper``, or None when those columns are absent."""
        if not all(c in self.extra for c in ACTION_COLUMNS):
            return None
        return np.stack([self.extra[c] for c in ACTION_COLUMNS], axis=1)


@dataclass(frozen=True)
class JointTable:
    """``joints.csv`` as arrays over the N feedback samples.

    Attributes:
        t: (N,) float64 seconds on the episode clock.
        q: (N, 6) float64 joint angles in radians.
        gripper: (N,) float64 finger-pad gap in metres.
        extra: optional column name -> (N,) float64 (efforts, status, ...).
    """

    t: np.ndarray
    q: np.ndarray
    gripper: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.t)


@dataclass(frozen=True)
class Frame:
    """Everything about one frame.

    Attributes:
        index: frame number.
        t: seconds on the episode clock.
        q: (6,) float64 joint angles in radians.
        gripper: finger-pad gap in metres.
        rgb: (H, W, 3) uint8 RGB.
        depth: (H, W) float32 metres (0 = invalid), or None without depth.
        mask: (H, W) uint8 labels (``meta.labels``), or None without masks.
        extra: optional frames.csv columns of this row.
    """

    index: int
    t: float
    q: np.ndarray
    gripper: float
    rgb: np.ndarray
    depth: np.ndarray | None
    mask: np.ndarray | None
    extra: dict[str, float]


def _read_table(path: Path, required: tuple[str, ...], int_columns: tuple[str, ...],
                incomplete: bool) -> tuple[tuple[str, ...], np.ndarray]:
    """``(columns, values (N, C))`` of a CSV file; raises naming the file and line of the first problem.

    In an ``incomplete`` episode a torn last line (the writer was stopped mid-write) is skipped
    with a warning.
    """
    try:
        scan: CsvScan = scan_csv(path, required, int_columns)
    except FileNotFoundError:
        raise EpisodeFormatError(f"{path}: missing") from None
    if scan.header_problem:
        raise EpisodeFormatError(f"{path}: line 1: {scan.header_problem}")
    rows = scan.rows
    if incomplete and scan.torn_tail:
        log.warning("%s: skipping the torn last line %d of an incomplete episode", path, rows[-1].line)
        rows = rows[:-1]
    for row in rows:
        if row.problem:
            raise EpisodeFormatError(f"{path}: line {row.line}: {row.problem}")
    values = np.array([r.values for r in rows], dtype=np.float64).reshape(len(rows), len(scan.columns))
    return scan.columns, values


def _columns(columns: tuple[str, ...], values: np.ndarray, required: tuple[str, ...]) -> dict[str, np.ndarray]:
    return {c: values[:, i].copy() for i, c in enumerate(columns) if c not in required}


class Episode:
    """An episode folder opened for reading (``docs/episode-format.md``, version 1).

    ``Episode.open(path)`` reads ``episode.json`` and ``frames.csv`` and checks that frame
    indices run 0..T-1; images are decoded only when asked for (``rgb(i)``, ``frame(i)``,
    iteration), so an episode never has to fit in memory. ``joints()`` and ``gt()`` load their
    files on first use. Run ``validate`` for a full check of every file.
    """

    def __init__(self, path: Path, meta: EpisodeMeta, frames: FrameTable) -> None:
        self.path = Path(path)
        self.meta = meta
        self.frames = frames
        self._joints: JointTable | None = None

    @classmethod
    def open(cls, path: str | Path) -> Episode:
        """Open the episode folder ``path``; raises :class:`EpisodeFormatError` naming the file."""
        path = Path(path)
        if not path.is_dir():
            raise EpisodeFormatError(f"{path}: not a folder")
        meta = load_meta(path / META_FILE)
        if not meta.complete:
            log.warning("%s: incomplete episode (writer stopped or crashed); "
                        "run `manisplat-episode recover %s` to make it valid", path, path)
        columns, values = _read_table(path / FRAMES_FILE, FRAME_COLUMNS, ("index",), not meta.complete)
        index = values[:, 0].astype(np.int64)
        expected = np.arange(len(index))
        if not np.array_equal(index, expected):
            row = int(np.flatnonzero(index != expected)[0])
            raise EpisodeFormatError(f"{path / FRAMES_FILE}: line {row + 2}: index {index[row]}, expected {row} "
                                     "(frames must be numbered 0..T-1; run `manisplat-episode validate`)")
        frames = FrameTable(index=index, t=values[:, 1].copy(), q=values[:, 2:8].copy(),
                            gripper=values[:, 8].copy(), extra=_columns(columns, values, FRAME_COLUMNS))
        return cls(path, meta, frames)

    @property
    def camera(self) -> CameraInfo:
        return self.meta.camera

    def __len__(self) -> int:
        return len(self.frames)

    def __repr__(self) -> str:
        return f"Episode({str(self.path)!r}, frames={len(self)}, complete={self.meta.complete})"

    @cached_property
    def has_depth(self) -> bool:
        """Whether ``depth/`` holds frame images."""
        return has_images(self.path / DEPTH.folder)

    @cached_property
    def has_masks(self) -> bool:
        """Whether ``masks/`` holds frame images."""
        return has_images(self.path / MASK.folder)

    def _check_index(self, i: int) -> int:
        if not 0 <= i < len(self):
            raise IndexError(f"{self.path}: frame {i} out of range 0..{len(self) - 1}")
        return int(i)

    def _image(self, kind: ImageKind, i: int) -> np.ndarray:
        folder = self.path / kind.folder
        path = find_image(folder, self._check_index(i))
        if path is None:
            raise EpisodeFormatError(f"{folder}: no image for frame {i}")
        return load_image(path, kind, self.camera.width, self.camera.height)

    def rgb(self, i: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB image of frame ``i``."""
        return self._image(RGB, i)

    def depth(self, i: int) -> np.ndarray | None:
        """(H, W) float32 depth of frame ``i`` in metres (0 = invalid), or None without depth."""
        if not self.has_depth:
            return None
        if self.meta.depth_scale is None:
            raise EpisodeFormatError(f"{self.path / META_FILE}: depth/ is present but depth_scale is null")
        return raw_to_depth(self._image(DEPTH, i), self.meta.depth_scale)

    def mask(self, i: int) -> np.ndarray | None:
        """(H, W) uint8 label image of frame ``i`` (values in ``meta.labels``), or None without masks."""
        return self._image(MASK, i) if self.has_masks else None

    def frame(self, i: int) -> Frame:
        """Frame ``i`` with its images decoded."""
        i = self._check_index(i)
        f = self.frames
        return Frame(index=i, t=float(f.t[i]), q=f.q[i].copy(), gripper=float(f.gripper[i]),
                     rgb=self.rgb(i), depth=self.depth(i), mask=self.mask(i),
                     extra={k: float(v[i]) for k, v in f.extra.items()})

    def __iter__(self) -> Iterator[Frame]:
        """Frames in order, each decoded when reached."""
        return (self.frame(i) for i in range(len(self)))

    def joints(self) -> JointTable | None:
        """The raw joint stream of ``joints.csv`` (loaded on first call), or None without one."""
        path = self.path / JOINTS_FILE
        if self._joints is None and path.is_file():
            columns, values = _read_table(path, JOINT_COLUMNS, (), not self.meta.complete)
            self._joints = JointTable(t=values[:, 0].copy(), q=values[:, 1:7].copy(), gripper=values[:, 7].copy(),
                                      extra=_columns(columns, values, JOINT_COLUMNS))
        return self._joints

    def gt(self) -> dict[str, np.ndarray] | None:
        """The arrays of ``gt.npz`` (simulation ground truth), or None without one; raises
        :class:`EpisodeFormatError` naming the file when it cannot be read."""
        path = self.path / GT_FILE
        return read_gt(path) if path.is_file() else None


def read_episode(path: str | Path) -> Episode:
    """Same as :meth:`Episode.open`."""
    return Episode.open(path)
