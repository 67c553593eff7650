"""Episodes (``docs/episode-format.md``, format versions 1 and 2): read, write crash-safely, validate,
recover after a crash, and import from other formats.

    >>> from manisplat.episode import Episode, validate
    >>> ep = Episode.open("data/pick")           # metadata and tables now, images when asked
    >>> ep.frames.q.shape, ep.rgb(0).shape       # (T, 6) radians, (H, W, 3) uint8 RGB
    >>> print(validate("data/pick"))             # every problem, with file and row
    >>> ep.meta.version, list(ep.arms), list(ep.cameras)   # 2, ['left', 'right'], ['cam_high', ...]
    >>> ep.arm_frames("left").q, ep.rgb(0, "cam_high")      # any arm, any camera

The command line is ``manisplat-episode`` (:mod:`manisplat.episode.cli`). Names are imported
from their submodules on first use (PEP 562), so that ``import manisplat.episode`` (and the
command line's ``--help``) stays free of OpenCV, h5py and torch.
"""

from __future__ import annotations

from manisplat._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "format": ("ACTION_COLUMNS", "FORMAT", "FRAME_COLUMNS", "JOINT_COLUMNS", "VERSION", "VERSION_2", "VERSIONS",
               "DamagedEpisodeError", "EpisodeFormatError"),
    "importers.act_hdf5": ("import_act_hdf5",),
    "importers.cobot_magic": ("import_cobot_magic",),
    "importers.lerobot": ("import_lerobot",),
    "meta": ("ArmInfo", "CameraInfo", "EpisodeMeta", "RobotInfo", "load_meta", "save_meta"),
    "reader": ("Episode", "Frame", "FrameTable", "JointTable", "read_episode"),
    "recovery": ("RecoveryReport", "recover"),
    "validation": ("Problem", "ValidationReport", "validate"),
    "writer": ("EpisodeWriter",),
    "writer_v2": ("EpisodeWriterV2",),
})
