"""What a recording gives back: the live :class:`Status` of an episode, its
:class:`EpisodeResult`, and the end of an episode (:func:`close_episode`, :func:`remove_empty`)."""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from manisplat.episode import validate
from manisplat.recorder.stats import EpisodeStats, RigStats
from manisplat.recorder.writer import EpisodeSink, StorageError

log = logging.getLogger(__name__)


@dataclass
class EpisodeResult:
    """The outcome of :meth:`~.rig.RigRecorder.record_episode`.

    Attributes:
        path: the episode folder.
        stats: :class:`~.stats.EpisodeStats` for a version 1 episode, :class:`~.stats.RigStats`
            for named arms and cameras.
        error: why the episode could not be completed (None when complete).
        valid: whether ``validate`` (quick) found no error (False when incomplete).
        removed: the folder was removed because no frame had been written (``error`` says so).
    """

    path: Path
    stats: EpisodeStats | RigStats
    error: str | None = None
    valid: bool = False
    removed: bool = False


@dataclass
class Status:
    """A snapshot for the live status line.

    Attributes: ``elapsed_s``; ``fps`` (frames written in the last second); ``can_fps`` (CAN
    frames received per s); ``frames``; ``lost`` (camera + queue drops); ``sync_gap_ms`` (of the
    last frame); ``flagged``; ``queue`` (frames waiting for the writer); ``camera_silent_s``;
    ``arm`` (arm health state).
    """

    elapsed_s: float
    fps: float
    can_fps: float
    frames: int
    lost: int
    sync_gap_ms: float
    flagged: int
    queue: int
    camera_silent_s: float
    arm: str


def close_episode(path: Path, sink: EpisodeSink, stats: RigStats, extra: dict[str, Any], error: str | None,
                  created: bool) -> EpisodeResult:
    """Finish the episode ``sink`` writes (``extra`` into ``episode.json``, ``complete: true``
    last), then validate it; an episode without a frame in a folder this run ``created`` is removed.
    ``stats`` gets the frames written; ``error``: why the episode ended early, or None."""
    try:
        sink.finish(extra)
    except StorageError as exc:
        error = str(exc)
    stats.count_frames(sink.frames_written)
    result = EpisodeResult(path, stats, error)
    if not stats.frames and created:
        return remove_empty(result)
    if sink.complete:
        report = validate(path, decode_images=False)
        result.valid = report.ok
        if not report.ok:
            result.error = (result.error + "; " if result.error else "") + f"validation failed:\n{report}"
    return result


def remove_empty(result: EpisodeResult) -> EpisodeResult:
    """Remove the folder of an episode in which no frame was written (the joint samples and CAN
    frames before a first frame are no episode), saying so in ``result.error``; a folder that
    cannot be removed stays."""
    try:
        shutil.rmtree(result.path)
    except OSError as exc:
        note = f"no frame was recorded; the episode folder could not be removed: {exc}"
    else:
        result.removed = True
        note = f"no frame was recorded: removed the episode folder {result.path}"
    result.error = f"{result.error.rstrip('.')}; {note}" if result.error else note
    log.error("%s", note)
    return result
