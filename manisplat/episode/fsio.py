"""Crash-safe file primitives: atomic replace through a temporary file, and fsync of files and folders."""

from __future__ import annotations

import os
from pathlib import Path

TMP_SUFFIX = ".tmp"
"""Suffix of the temporary file an atomic write goes through; one left behind is a crash artefact."""


def temp_path(path: Path) -> Path:
    """The temporary name used while ``path`` is being written (same folder, so ``os.replace`` is atomic)."""
    return path.with_name(path.name + TMP_SUFFIX)


def fsync_path(path: Path) -> None:
    """Flush a file's or a folder's data and metadata to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes, *, fsync: bool = True) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the whole new one, never a part.

    The bytes go to ``temp_path(path)`` first and are renamed over ``path``. With ``fsync`` the
    data and the rename are on disk when this returns (survives power loss); without it they
    survive a killed process but may be lost with the page cache.
    """
    tmp = temp_path(path)
    with open(tmp, "wb") as f:
        f.write(data)
        if fsync:
            f.flush()
            os.fsync(f.fileno())
    os.replace(tmp, path)
    if fsync:
        fsync_path(path.parent)
