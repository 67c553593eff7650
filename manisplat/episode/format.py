"""Names and constants of the episode format, version 1 (``docs/episode-format.md``), and its errors."""

from __future__ import annotations

FORMAT = "manisplat-episode"
VERSION = 1

META_FILE = "episode.json"
FRAMES_FILE = "frames.csv"
JOINTS_FILE = "joints.csv"
GT_FILE = "gt.npz"
RGB_DIR = "rgb"
DEPTH_DIR = "depth"
MASKS_DIR = "masks"
RECOVERED_DIR = ".recovered"

Q_COLUMNS = ("q1", "q2", "q3", "q4", "q5", "q6")
FRAME_COLUMNS = ("index", "t", *Q_COLUMNS, "gripper")
"""Required leading columns of ``frames.csv``; optional extra columns may follow."""
JOINT_COLUMNS = ("t", *Q_COLUMNS, "gripper")
"""Required leading columns of ``joints.csv``; optional extra columns may follow."""
ACTION_COLUMNS = ("a1", "a2", "a3", "a4", "a5", "a6", "a_gripper")
"""Optional ``frames.csv`` columns holding the commanded (leader-arm) action at ``t``."""

IMAGE_SUFFIXES = (".png", ".jpg")
"""RGB images may be PNG or JPEG; depth and masks must be PNG (lossless)."""
INDEX_DIGITS = 6

DIST_LENGTHS = (0, 4, 5, 8, 12, 14)
"""Numbers of distortion coefficients OpenCV accepts (an empty list means none)."""

GRIPPER_RANGE_M = (0.0, 0.1)
"""Plausible finger-pad gap in metres; values outside get a warning from ``validate``."""


class EpisodeFormatError(ValueError):
    """An episode (or a file being imported) does not follow the format; the message names the
    file and the field or row."""


class DamagedEpisodeError(EpisodeFormatError):
    """``recover`` found damage that is not a crash artefact (a broken frame followed by good
    ones); it names the frames and leaves the episode untouched."""


def image_name(index: int, suffix: str = ".png") -> str:
    """File name of frame ``index`` in ``rgb/``, ``depth/`` or ``masks/``: ``000007.png``."""
    return f"{index:0{INDEX_DIGITS}d}{suffix}"
