"""Where an episode keeps each arm's columns and joint stream and each camera's images, for both
format versions: the one place that knows version 1's ``q1``, ``joints.csv`` and ``rgb/`` and
version 2's ``left.q1``, ``joints_left.csv`` and ``rgb/cam_high/``.

The reader, the writers, ``validate``, ``recover`` and ``info`` go through a :class:`Layout`, so
that every arm and camera is covered the same way and a version 1 episode is the one-arm,
one-camera case.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Iterable

from manisplat.episode.format import (ACTION_COLUMNS, JOINTS_FILE, STATE_COLUMNS, V1_ARM, VERSION, VERSION_2,
                                      arm_column, camera_time_column, joints_file)

if TYPE_CHECKING:  # images.py imports OpenCV; this module stays light for meta.py
    from manisplat.episode.images import ImageKind


@dataclass(frozen=True)
class ArmColumns:
    """The ``frames.csv`` columns and joint stream of one arm.

    Attributes:
        name: the arm (``"arm"`` in version 1).
        prefix: ``""`` in version 1, ``"<name>."`` in version 2: every column of the arm starts with it.
        joints_file: ``joints.csv`` (version 1) or ``joints_<name>.csv``.
    """

    name: str
    prefix: str
    joints_file: str

    @property
    def state(self) -> tuple[str, ...]:
        """The 7 required columns: ``q1..q6, gripper`` with the prefix."""
        return tuple(self.prefix + c for c in STATE_COLUMNS)

    @property
    def actions(self) -> tuple[str, ...]:
        """The 7 optional action columns: ``a1..a6, a_gripper`` with the prefix."""
        return tuple(self.prefix + c for c in ACTION_COLUMNS)

    def owns(self, column: str) -> bool:
        """Whether ``column`` belongs to this arm (version 2: it starts with ``<name>.``)."""
        return bool(self.prefix) and column.startswith(self.prefix)


@dataclass(frozen=True)
class CameraFiles:
    """Where one camera's images and frame times are.

    Attributes:
        name: the camera.
        subfolder: ``""`` in version 1 (``rgb/``), the camera's name in version 2 (``rgb/<name>/``).
        time_column: the optional ``frames.csv`` column with its own frame times (version 2), or None.
    """

    name: str
    subfolder: str
    time_column: str | None

    def folder(self, kind: ImageKind | str) -> str:
        """The folder of ``kind``'s images (an :class:`ImageKind` or its folder name ``"rgb"``),
        relative to the episode: ``rgb`` or ``rgb/cam_high``."""
        top = kind if isinstance(kind, str) else kind.folder
        return f"{top}/{self.subfolder}" if self.subfolder else top


@dataclass(frozen=True)
class Layout:
    """Every arm's columns and every camera's files of one episode.

    Attributes:
        version: the format version.
        arms: in ``episode.json`` order (version 1: one, named ``"arm"``).
        cameras: in ``episode.json`` order.
    """

    version: int
    arms: tuple[ArmColumns, ...]
    cameras: tuple[CameraFiles, ...]

    @property
    def frame_columns(self) -> tuple[str, ...]:
        """The required leading columns of ``frames.csv``: ``index, t``, then each arm's state."""
        return ("index", "t", *(c for arm in self.arms for c in arm.state))

    def arm(self, name: str) -> ArmColumns:
        for arm in self.arms:
            if arm.name == name:
                return arm
        raise KeyError(name)

    def camera(self, name: str) -> CameraFiles:
        for camera in self.cameras:
            if camera.name == name:
                return camera
        raise KeyError(name)

    def image_folders(self, kinds: Iterable[ImageKind]) -> list[tuple[CameraFiles, ImageKind, str]]:
        """``(camera, kind, folder)`` for every camera and each of ``kinds``."""
        return [(cam, kind, cam.folder(kind)) for cam in self.cameras for kind in kinds]


def v1_layout(camera: str = "camera") -> Layout:
    """The layout of a version 1 episode (``camera``: its camera's name)."""
    return Layout(VERSION, (ArmColumns(V1_ARM, "", JOINTS_FILE),), (CameraFiles(camera, "", None),))


def v2_layout(arms: Iterable[str], cameras: Iterable[str]) -> Layout:
    """The layout of a version 2 episode with these arm and camera names."""
    return Layout(VERSION_2, tuple(ArmColumns(a, arm_column(a, ""), joints_file(a)) for a in arms),
                  tuple(CameraFiles(c, c, camera_time_column(c)) for c in cameras))


def layout_of_raw(raw: Any) -> Layout | None:
    """The layout a parsed ``episode.json`` declares, as far as it can be told (None when it is
    not an object)."""
    if not isinstance(raw, dict):
        return None
    if is_v2_raw(raw):  # what of arms and cameras is usable (the rest is reported by meta_problems)
        arms, cameras = raw.get("arms"), raw.get("cameras")
        return v2_layout(list(arms) if isinstance(arms, dict) else [], list(cameras) if isinstance(cameras, dict) else [])
    camera = raw.get("camera")
    name = camera.get("name") if isinstance(camera, dict) else None
    return v1_layout(name if isinstance(name, str) else "camera")


def is_v2_raw(raw: dict[str, Any]) -> bool:
    """Whether a parsed ``episode.json`` is laid out as version 2: it has ``arms`` or ``cameras``,
    or says version 2 without a version 1 ``robot`` or ``camera``."""
    return ("arms" in raw or "cameras" in raw
            or (raw.get("version") == VERSION_2 and "robot" not in raw and "camera" not in raw))
