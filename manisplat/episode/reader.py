"""Read an episode of either format version: metadata and tables at once, images lazily, one frame at a time."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from manisplat.episode.format import (ACTION_COLUMNS, FRAMES_FILE, GT_FILE, JOINT_COLUMNS, META_FILE,
                                      EpisodeFormatError)
from manisplat.episode.groundtruth import read_gt
from manisplat.episode.images import (DEPTH, MASK, RGB, ImageKind, StoredChroma, find_image,
                                     has_images, jpeg_chroma_subsampling, load_image, raw_to_depth)
from manisplat.episode.layout import CameraFiles, Layout
from manisplat.episode.meta import ArmInfo, CameraInfo, EpisodeMeta, load_meta
from manisplat.episode.tables import CsvScan, scan_csv

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameTable:
    """``frames.csv`` as arrays over the T frames, as one arm sees it (:meth:`Episode.arm_frames`).

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
    """An episode folder opened for reading (``docs/episode-format.md``, versions 1 and 2).

    ``Episode.open(path)`` reads ``episode.json`` and ``frames.csv`` and checks that frame
    indices run 0..T-1; images are decoded only when asked for (``rgb(i)``, ``frame(i)``,
    iteration), so an episode never has to fit in memory. ``joints()`` and ``gt()`` load their
    files on first use. Run ``validate`` for a full check of every file.

    Every episode has named arms and cameras (``arms``, ``cameras``; ``meta.version`` says which
    version it is): ``arm_frames(name)``, ``joints(name)`` and ``rgb(i, camera)`` read any of them.
    The one-arm view (``camera``, ``frames``, ``meta.robot``, ``rgb(i)`` without a camera,
    ``frame(i)``, iteration) reads a version 1 episode and a version 2 one with one arm and one
    camera; on an episode with several it raises :class:`EpisodeFormatError` naming them.
    """

    def __init__(self, path: Path, meta: EpisodeMeta, columns: tuple[str, ...], values: np.ndarray) -> None:
        self.path = Path(path)
        self.meta = meta
        self.layout: Layout = meta.layout
        self._columns = columns
        self._values = values
        self._arm_frames: dict[str, FrameTable] = {}
        self._joints: dict[str, JointTable] = {}
        self._has_images: dict[str, bool] = {}

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
        columns, values = _read_table(path / FRAMES_FILE, meta.layout.frame_columns, ("index",), not meta.complete)
        index = values[:, 0].astype(np.int64)
        expected = np.arange(len(index))
        if not np.array_equal(index, expected):
            row = int(np.flatnonzero(index != expected)[0])
            raise EpisodeFormatError(f"{path / FRAMES_FILE}: line {row + 2}: index {index[row]}, expected {row} "
                                     "(frames must be numbered 0..T-1; run `manisplat-episode validate`)")
        return cls(path, meta, columns, values)

    @property
    def columns(self) -> tuple[str, ...]:
        """The header of ``frames.csv``."""
        return self._columns

    @property
    def arms(self) -> dict[str, ArmInfo]:
        """Arm name -> :class:`ArmInfo`, in file order (a version 1 episode has one, ``"arm"``)."""
        return self.meta.arms

    @property
    def cameras(self) -> dict[str, CameraInfo]:
        """Camera name -> :class:`CameraInfo` as stored (version 2 mounts ``world`` or ``<arm>/<link>``)."""
        return self.meta.cameras

    @property
    def camera(self) -> CameraInfo:
        """The one camera, in version 1 terms (see :attr:`EpisodeMeta.camera`)."""
        return self.meta.camera

    @property
    def frames(self) -> FrameTable:
        """The one arm's :meth:`arm_frames` (version 1's ``frames.csv`` as it reads)."""
        return self.arm_frames(self.meta.robot.name)

    def arm_frames(self, arm: str) -> FrameTable:
        """``frames.csv`` as seen by ``arm``: its ``q`` (T, 6) rad and ``gripper`` (T,) m, and as
        ``extra`` its own further columns without the ``<arm>.`` prefix (``a1``..``a_gripper``,
        so that ``actions`` works) and the columns no arm owns (``seq``, ``<camera>.t``, ...)."""
        if arm not in self._arm_frames:
            try:
                columns = self.layout.arm(arm)
            except KeyError:
                raise KeyError(f"{self.path}: no arm {arm!r}; arms: {', '.join(self.arms)}") from None
            at = {c: k for k, c in enumerate(self._columns)}
            values = self._values
            state = [at[c] for c in columns.state]
            extra: dict[str, np.ndarray] = {}
            for k, c in enumerate(self._columns):
                if c in ("index", "t") or c in columns.state:
                    continue
                if columns.owns(c):
                    extra[c[len(columns.prefix):]] = values[:, k].copy()
                elif not any(other.owns(c) for other in self.layout.arms) and c not in self.layout.frame_columns:
                    extra[c] = values[:, k].copy()
            self._arm_frames[arm] = FrameTable(index=values[:, 0].astype(np.int64), t=values[:, 1].copy(),
                                               q=values[:, state[:6]].copy(), gripper=values[:, state[6]].copy(),
                                               extra=extra)
        return self._arm_frames[arm]

    def camera_times(self, camera: str | None = None) -> np.ndarray:
        """(T,) float64 seconds: ``camera``'s own frame times (its ``<camera>.t`` column) when the
        episode has them, else ``t`` (the cameras were triggered together)."""
        files = self._camera_files(camera)
        if files.time_column is not None and files.time_column in self._columns:
            return self._values[:, self._columns.index(files.time_column)].copy()
        return self._values[:, 1].copy()

    def __len__(self) -> int:
        return len(self._values)

    def __repr__(self) -> str:
        return f"Episode({str(self.path)!r}, frames={len(self)}, complete={self.meta.complete})"

    def _camera_files(self, camera: str | None) -> CameraFiles:
        if camera is None:
            self.meta.refuse_several(arms=False)
            return self.layout.cameras[0]
        try:
            return self.layout.camera(camera)
        except KeyError:
            raise EpisodeFormatError(f"{self.path}: no camera {camera!r}; cameras: {', '.join(self.cameras)}") from None

    def has_images(self, kind: str, camera: str | None = None) -> bool:
        """Whether ``camera``'s ``kind`` folder (``"rgb"``, ``"depth"``, ``"masks"``) holds frame images."""
        folder = self._camera_files(camera).folder(kind)
        if folder not in self._has_images:
            self._has_images[folder] = has_images(self.path / folder)
        return self._has_images[folder]

    @property
    def has_depth(self) -> bool:
        """Whether the one camera has depth images."""
        return self.has_images(DEPTH.folder)

    @property
    def has_masks(self) -> bool:
        """Whether the one camera has mask images."""
        return self.has_images(MASK.folder)

    def _check_index(self, i: int) -> int:
        if not 0 <= i < len(self):
            raise IndexError(f"{self.path}: frame {i} out of range 0..{len(self) - 1}")
        return int(i)

    def _image(self, kind: ImageKind, i: int, camera: str | None) -> np.ndarray:
        files = self._camera_files(camera)
        folder = self.path / files.folder(kind)
        path = find_image(folder, self._check_index(i))
        if path is None:
            raise EpisodeFormatError(f"{folder}: no image for frame {i}")
        info = self.cameras[files.name]
        return load_image(path, kind, info.width, info.height)

    def rgb(self, i: int, camera: str | None = None) -> np.ndarray:
        """(H, W, 3) uint8 RGB image of frame ``i`` from ``camera`` (default: the one camera)."""
        return self._image(RGB, i, camera)

    def chroma_subsampling(self, camera: str | None = None) -> StoredChroma | None:
        """How ``camera``'s (default: the one camera's) images kept their colour when encoded: the
        camera's ``chroma_subsampling`` (and ``chroma_red_blue_swapped``) in episode.json (checked
        with the rest of it), else the header of its first image where that is a JPEG file; None
        where neither says (PNG images of unknown origin).

        Raises:
            EpisodeFormatError: the first image is a ``.jpg`` file but not a JPEG stream.
        """
        files = self._camera_files(camera)
        extra = self.cameras[files.name].extra
        if "chroma_subsampling" in extra:
            return StoredChroma(extra["chroma_subsampling"], extra.get("chroma_red_blue_swapped", False))
        first = find_image(self.path / files.folder(RGB.folder), 0) if len(self) else None
        if first is None or first.suffix != ".jpg":
            return None
        try:
            scheme = jpeg_chroma_subsampling(first.read_bytes())
        except ValueError as exc:
            raise EpisodeFormatError(f"{first}: {exc}") from None
        return None if scheme is None else StoredChroma(scheme)  # image files hold BGR: the colours as encoded

    def depth(self, i: int, camera: str | None = None) -> np.ndarray | None:
        """(H, W) float32 depth of frame ``i`` in metres (0 = invalid) from ``camera`` (default:
        the one camera), or None when that camera has no depth."""
        if not self.has_images(DEPTH.folder, camera):
            return None
        if self.meta.depth_scale is None:
            raise EpisodeFormatError(f"{self.path / META_FILE}: depth images are present but depth_scale is null")
        return raw_to_depth(self._image(DEPTH, i, camera), self.meta.depth_scale)

    def mask(self, i: int, camera: str | None = None) -> np.ndarray | None:
        """(H, W) uint8 label image of frame ``i`` (values in ``meta.labels``) from ``camera``
        (default: the one camera), or None when that camera has no masks."""
        return self._image(MASK, i, camera) if self.has_images(MASK.folder, camera) else None

    def frame(self, i: int) -> Frame:
        """Frame ``i`` of the one arm and camera, with its images decoded."""
        i = self._check_index(i)
        f = self.frames
        return Frame(index=i, t=float(f.t[i]), q=f.q[i].copy(), gripper=float(f.gripper[i]),
                     rgb=self.rgb(i), depth=self.depth(i), mask=self.mask(i),
                     extra={k: float(v[i]) for k, v in f.extra.items()})

    def __iter__(self) -> Iterator[Frame]:
        """Frames of the one arm and camera in order, each decoded when reached."""
        self.meta.refuse_several()
        return (self.frame(i) for i in range(len(self)))

    def joints(self, arm: str | None = None) -> JointTable | None:
        """The raw joint stream of ``arm`` (default: the one arm): ``joints.csv`` in version 1,
        ``joints_<arm>.csv`` in version 2 (loaded on first call), or None without one."""
        name = self.meta.robot.name if arm is None else arm
        try:
            files = self.layout.arm(name)
        except KeyError:
            raise KeyError(f"{self.path}: no arm {name!r}; arms: {', '.join(self.arms)}") from None
        path = self.path / files.joints_file
        if name not in self._joints and path.is_file():
            columns, values = _read_table(path, JOINT_COLUMNS, (), not self.meta.complete)
            self._joints[name] = JointTable(t=values[:, 0].copy(), q=values[:, 1:7].copy(),
                                            gripper=values[:, 7].copy(),
                                            extra=_columns(columns, values, JOINT_COLUMNS))
        return self._joints.get(name)

    def gt(self) -> dict[str, np.ndarray] | None:
        """The arrays of ``gt.npz`` (simulation ground truth), or None without one; raises
        :class:`EpisodeFormatError` naming the file when it cannot be read."""
        path = self.path / GT_FILE
        return read_gt(path) if path.is_file() else None


def read_episode(path: str | Path) -> Episode:
    """Same as :meth:`Episode.open`."""
    return Episode.open(path)
