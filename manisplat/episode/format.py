"""Names and constants of the episode format, versions 1 and 2 (``docs/episode-format.md``), and its errors."""

from __future__ import annotations

FORMAT = "manisplat-episode"
VERSION = 1
"""The one-arm, one-camera version (``robot`` and ``camera`` in ``episode.json``)."""
VERSION_2 = 2
"""Named arms and cameras (``arms`` and ``cameras`` in ``episode.json``)."""
VERSIONS = (VERSION, VERSION_2)
"""The versions this code reads and writes."""

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
GRIPPER_EFFORT_COLUMN = "gripper_effort"
"""Optional ``frames.csv`` column (``<arm>.gripper_effort`` in version 2): the gripper motor's effort
at ``t`` as the arm reports it (PiPER: N*m; only its size against the grip's hold is read)."""

V1_ARM = "arm"
"""The name the reader gives the one arm of a version 1 episode (``ep.arms``, ``ep.arm_frames``)."""
WORLD_MOUNT = "world"
"""Version 2 ``mount`` of a camera fixed in the world frame (else ``"<arm>/<link>"``)."""
NAME_PATTERN = r"[A-Za-z0-9_-]{1,64}"
"""Arm and camera names of version 2: they become column prefixes and folder names."""
STATE_COLUMNS = (*Q_COLUMNS, "gripper")
"""An arm's joint state; version 2 prefixes each with ``<arm>.``."""

IMAGE_SUFFIXES = (".png", ".jpg")
"""RGB images may be PNG or JPEG; depth and masks must be PNG (lossless)."""
INDEX_DIGITS = 6

DIST_LENGTHS = (0, 4, 5, 8, 12, 14)
"""Numbers of distortion coefficients OpenCV accepts (an empty list means none)."""
CHROMA_SUBSAMPLING = {"4:4:4": (1, 1), "4:2:2": (2, 1), "4:2:0": (2, 2), "4:4:0": (1, 2), "4:1:1": (4, 1)}
"""A camera's ``chroma_subsampling`` schemes (J:a:b) -> the pixels (horizontal, vertical) one colour
sample covers."""

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


def arm_column(arm: str, column: str) -> str:
    """Version 2 ``frames.csv`` column ``column`` of ``arm``: ``left.q1``, ``left.a_gripper``."""
    return f"{arm}.{column}"


def joints_file(arm: str) -> str:
    """Version 2 joint stream of ``arm``: ``joints_left.csv``."""
    return f"joints_{arm}.csv"


def camera_time_column(camera: str) -> str:
    """Optional version 2 ``frames.csv`` column with ``camera``'s own frame time: ``cam_high.t``."""
    return f"{camera}.t"
