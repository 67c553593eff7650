"""Episodes (``shared/EPISODE.md``, format version 1): read, write crash-safely, validate,
recover after a crash, and import from other formats.

    >>> from manisplat.episode import Episode, validate
    >>> ep = Episode.open("data/pick")           # metadata and tables now, images when asked
    >>> ep.frames.q.shape, ep.rgb(0).shape       # (T, 6) radians, (H, W, 3) uint8 RGB
    >>> print(validate("data/pick"))             # every problem, with file and row

The command line is ``manisplat-episode`` (:mod:`manisplat.episode.cli`).
"""

from manisplat.episode.format import (ACTION_COLUMNS, FORMAT, FRAME_COLUMNS, JOINT_COLUMNS, VERSION,
                                      DamagedEpisodeError, EpisodeFormatError)
from manisplat.episode.importers.act_hdf5 import import_act_hdf5
from manisplat.episode.meta import CameraInfo, EpisodeMeta, RobotInfo, load_meta, save_meta
from manisplat.episode.reader import Episode, Frame, FrameTable, JointTable, read_episode
from manisplat.episode.recover import RecoveryReport, recover
from manisplat.episode.validate import Problem, ValidationReport, validate
from manisplat.episode.writer import EpisodeWriter

__all__ = [
    "ACTION_COLUMNS", "FORMAT", "FRAME_COLUMNS", "JOINT_COLUMNS", "VERSION",
    "CameraInfo", "DamagedEpisodeError", "Episode", "EpisodeFormatError", "EpisodeMeta", "EpisodeWriter",
    "Frame", "FrameTable", "JointTable", "Problem", "RecoveryReport", "RobotInfo", "ValidationReport",
    "import_act_hdf5", "load_meta", "read_episode", "recover", "save_meta", "validate",
]
