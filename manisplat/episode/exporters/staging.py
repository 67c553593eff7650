"""Exports are written into a hidden folder beside their destination and moved into place only when
complete, so a failed or killed export never leaves a partial dataset under the user's name."""

from __future__ import annotations

import logging
import os
import shutil
import uuid
from pathlib import Path

from manisplat.episode.fsio import fsync_path

log = logging.getLogger(__name__)


def staging_folder(out_dir: Path) -> Path:
    """A new hidden folder ``.OUT.partial-XXXXXXXX`` beside ``out_dir`` (created); warns about ones a
    killed export left behind (they never look like the dataset, but take space)."""
    stale = sorted(out_dir.parent.glob(f".{out_dir.name}.partial-*"))
    if stale:
        log.warning("left by an earlier export that was killed, safe to delete: %s", ", ".join(map(str, stale)))
    staging = out_dir.parent / f".{out_dir.name}.partial-{uuid.uuid4().hex[:8]}"
    staging.mkdir(parents=True)
    return staging


def replace_folder(staging: Path, out_dir: Path) -> None:
    """Rename the finished ``staging`` to ``out_dir``; an earlier folder there goes only after that."""
    old = None
    if out_dir.is_dir() and any(out_dir.iterdir()):
        old = out_dir.parent / f".{out_dir.name}.replaced-{uuid.uuid4().hex[:8]}"
        os.replace(out_dir, old)
    elif out_dir.is_dir():
        out_dir.rmdir()
    os.replace(staging, out_dir)
    fsync_path(out_dir.parent)
    if old is not None:
        shutil.rmtree(old)


def merge_files(staging: Path, out_dir: Path, last: str) -> None:
    """Move every file of the finished ``staging`` into the existing ``out_dir`` (``last`` at the end,
    so that it marks the moment all the others are there), then remove ``staging``."""
    names = sorted(p.name for p in staging.iterdir() if p.name != last) + [last]
    for name in names:
        os.replace(staging / name, out_dir / name)
    fsync_path(out_dir)
    staging.rmdir()
