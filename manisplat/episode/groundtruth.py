"""``gt.npz``, the ground truth of a simulated episode: which of its arrays hold one row per frame
(``docs/episode-format.md``), reading it with errors that name the file, and writing it atomically."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from manisplat.episode.format import EpisodeFormatError
from manisplat.episode.fsio import atomic_write_bytes

PER_EPISODE = ("K", "T_cam_base", "link_names")
"""Arrays that describe the whole episode, never cut per frame (however long they are)."""
PER_FRAME = ("t", "q", "gripper", "phase", "T_base_tcp", "T_base_links")
"""Arrays that always hold one row per frame, as do ``T_base_<object>`` / ``T_world_<object>`` for
every listed object."""


def read_gt(path: Path) -> dict[str, np.ndarray]:
    """Every array of a ``gt.npz`` file; raises :class:`EpisodeFormatError` naming the file when
    it is not a readable NumPy archive (pickled object arrays are refused)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return {name: data[name] for name in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise EpisodeFormatError(f"{path}: cannot read: {exc}") from None


def per_frame_names(arrays: Mapping[str, np.ndarray], objects: Sequence[str]) -> list[str]:
    """Names of the arrays of ``arrays`` that hold one row per frame.

    Those are :data:`PER_FRAME`, ``T_base_<object>`` (``T_world_<object>`` in an episode with
    several arms) for each name in ``objects``, and any other
    array whose first dimension is as long as ``t`` (``t_recorded``, actions, contacts), except
    the :data:`PER_EPISODE` ones and 0-d arrays.
    """
    named = {*PER_FRAME, *(f"T_{frame}_{o}" for o in objects for frame in ("base", "world"))}
    t = arrays.get("t")
    frames = len(t) if t is not None and t.ndim >= 1 else None
    return [name for name, a in arrays.items() if name not in PER_EPISODE
            and (name in named or (a.ndim >= 1 and a.shape[0] == frames))]


def frame_count_problems(arrays: Mapping[str, np.ndarray], objects: Sequence[str], frames: int) -> list[str]:
    """One message per per-frame array whose length is not ``frames`` (the rows of ``frames.csv``)."""
    return [f"array {name!r} has shape {arrays[name].shape}: it must hold one row per frame, "
            f"{frames} like frames.csv" for name in per_frame_names(arrays, objects)
            if arrays[name].ndim == 0 or arrays[name].shape[0] != frames]


def is_compressed(path: Path) -> bool:
    """Whether the archive at ``path`` was written by ``np.savez_compressed`` (deflated members)."""
    with zipfile.ZipFile(path) as archive:
        return any(info.compress_type != zipfile.ZIP_STORED for info in archive.infolist())


def write_gt(path: Path, arrays: Mapping[str, np.ndarray], *, compressed: bool) -> None:
    """Write ``arrays`` to ``path`` atomically and durably (temporary file, fsync, rename)."""
    buffer = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buffer, **arrays)
    atomic_write_bytes(Path(path), buffer.getvalue())
