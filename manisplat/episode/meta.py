"""``episode.json``: typed metadata (camera, robot, episode), its rules, and JSON load/save.

Every rule lives in one ``*_problems`` function that returns all the violations of a raw JSON
value as messages naming the field (``camera.K must be 3x3 ...``). ``validate`` reports them
one by one; the dataclasses run the same functions and raise :class:`EpisodeFormatError`.
Unknown keys are kept in ``extra`` dicts and written back unchanged.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from manisplat.episode.format import DIST_LENGTHS, FORMAT, VERSION, EpisodeFormatError
from manisplat.episode.fsio import atomic_write_bytes

RIGID_TOL = 1e-6
"""Tolerance of the rigid-transform checks: max |R^T R - I|, |det R - 1| and the last row."""

_CAMERA_KEYS = ("name", "width", "height", "K", "dist", "mount", "T_mount_cam")
_ROBOT_KEYS = ("model", "joint_names", "description")
_META_KEYS = ("format", "version", "complete", "source", "created", "robot", "camera", "fps",
              "frame_count", "depth_scale", "labels", "objects")
_META_REQUIRED = ("format", "version", "complete", "source", "created", "robot", "camera", "fps",
                  "frame_count")


def utc_now() -> str:
    """The current UTC time as ``2026-11-21T12:00:00Z`` (the ``created`` field's form)."""
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _fmt(a: np.ndarray) -> str:
    return np.array2string(a, precision=6, separator=", ", max_line_width=200).replace("\n", "")


def _as_matrix(value: Any, name: str, shape: tuple[int, int]) -> tuple[np.ndarray | None, list[str]]:
    """``value`` as a float64 array of ``shape``, or None with a message."""
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None, [f"{name} must be a {shape[0]}x{shape[1]} array of numbers; got {value!r}"]
    if m.shape != shape:
        return None, [f"{name} must be {shape[0]}x{shape[1]}; got shape {m.shape}"]
    if not np.isfinite(m).all():
        return None, [f"{name} must be finite; got {_fmt(m)}"]
    return m, []


def intrinsics_problems(K: Any, width: Any = None, height: Any = None, name: str = "camera.K") -> list[str]:
    """Violations of a pinhole matrix ``K`` (3,3) ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``.

    With a valid image size, the principal point must lie within half an image of the image
    (``-W/2 <= cx <= 3W/2``, same for ``cy``).
    """
    m, problems = _as_matrix(K, name, (3, 3))
    if m is None:
        return problems
    fx, fy = m[0, 0], m[1, 1]
    if fx <= 0 or fy <= 0:
        problems.append(f"{name} must be 3x3 with positive fx, fy; got fx={fx:g}, fy={fy:g}")
    if m[1, 0] != 0 or np.abs(m[2] - [0.0, 0.0, 1.0]).max() > 1e-9:
        problems.append(f"{name} must have the form [[fx, s, cx], [0, fy, cy], [0, 0, 1]]; got {_fmt(m)}")
    if _is_int(width) and _is_int(height) and width > 0 and height > 0:
        cx, cy = m[0, 2], m[1, 2]
        if not (-width / 2 <= cx <= 1.5 * width and -height / 2 <= cy <= 1.5 * height):
            problems.append(f"{name} principal point (cx, cy) = ({cx:g}, {cy:g}) is far outside the "
                            f"{width}x{height} image")
    return problems


def rigid_problems(T: Any, name: str) -> list[str]:
    """Violations of a rigid transform ``T`` (4,4): ``R^T R = I``, ``det R = +1``, last row ``0 0 0 1``."""
    m, problems = _as_matrix(T, name, (4, 4))
    if m is None:
        return problems
    R = m[:3, :3]
    if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > RIGID_TOL:
        problems.append(f"{name} last row must be [0, 0, 0, 1]; got {_fmt(m[3])}")
    orth = np.abs(R.T @ R - np.eye(3)).max()
    if orth > RIGID_TOL:
        problems.append(f"{name} is not a rigid transform: max |R^T R - I| = {orth:.3g} > {RIGID_TOL:g}")
    det = np.linalg.det(R)
    if abs(det - 1.0) > RIGID_TOL:
        problems.append(f"{name} is not a rigid transform: det R = {det:.6g}, expected +1")
    return problems


def camera_problems(raw: Any) -> list[str]:
    """Violations of the ``camera`` object of ``episode.json``."""
    if not isinstance(raw, dict):
        return [f"camera must be an object; got {type(raw).__name__}"]
    problems = [f"camera.{k} is missing" for k in ("name", "width", "height", "K") if k not in raw]
    if "name" in raw and not isinstance(raw["name"], str):
        problems.append(f"camera.name must be a string; got {raw['name']!r}")
    for k in ("width", "height"):
        if k in raw and not (_is_int(raw[k]) and raw[k] > 0):
            problems.append(f"camera.{k} must be a positive integer; got {raw[k]!r}")
    if "K" in raw:
        problems += intrinsics_problems(raw["K"], raw.get("width"), raw.get("height"))
    dist = raw.get("dist", [])
    if not (isinstance(dist, list) and all(_is_number(d) and math.isfinite(d) for d in dist)
            and len(dist) in DIST_LENGTHS):
        problems.append(f"camera.dist must be a list of {DIST_LENGTHS} finite numbers "
                        f"(OpenCV order); got {dist!r}")
    mount = raw.get("mount", "base")
    if not (isinstance(mount, str) and mount):
        problems.append(f"camera.mount must be 'base' or a link name; got {mount!r}")
    if raw.get("T_mount_cam") is not None:
        problems += rigid_problems(raw["T_mount_cam"], "camera.T_mount_cam")
    return problems


def robot_problems(raw: Any) -> list[str]:
    """Violations of the ``robot`` object of ``episode.json``."""
    if not isinstance(raw, dict):
        return [f"robot must be an object; got {type(raw).__name__}"]
    problems = [f"robot.{k} is missing" for k in _ROBOT_KEYS if k not in raw]
    for k in ("model", "description"):
        if k in raw and not (isinstance(raw[k], str) and raw[k]):
            problems.append(f"robot.{k} must be a non-empty string; got {raw[k]!r}")
    names = raw.get("joint_names", [])
    if "joint_names" in raw and not (isinstance(names, list) and len(names) == 6
                                     and all(isinstance(n, str) for n in names)):
        problems.append(f"robot.joint_names must be a list of 6 strings (q1..q6); got {names!r}")
    return problems


def meta_problems(raw: Any) -> list[str]:
    """Every violation of the format in a parsed ``episode.json`` (empty when it is valid)."""
    if not isinstance(raw, dict):
        return [f"must hold a JSON object; got {type(raw).__name__}"]
    problems = [f"missing field '{k}'" for k in _META_REQUIRED if k not in raw]
    if "format" in raw and raw["format"] != FORMAT:
        problems.append(f"format must be {FORMAT!r}; got {raw['format']!r}")
    if "version" in raw and not (_is_int(raw["version"]) and raw["version"] == VERSION):
        problems.append(f"version must be {VERSION} (the version this code reads); got {raw['version']!r}")
    if "complete" in raw and not isinstance(raw["complete"], bool):
        problems.append(f"complete must be true or false; got {raw['complete']!r}")
    for k in ("source", "created"):
        if k in raw and not (isinstance(raw[k], str) and raw[k]):
            problems.append(f"{k} must be a non-empty string; got {raw[k]!r}")
    if "robot" in raw:
        problems += robot_problems(raw["robot"])
    if "camera" in raw:
        problems += camera_problems(raw["camera"])
    if "fps" in raw and not (_is_number(raw["fps"]) and math.isfinite(raw["fps"]) and raw["fps"] > 0):
        problems.append(f"fps must be a positive number; got {raw['fps']!r}")
    if "frame_count" in raw and not (_is_int(raw["frame_count"]) and raw["frame_count"] >= 0):
        problems.append(f"frame_count must be a non-negative integer; got {raw['frame_count']!r}")
    scale = raw.get("depth_scale")
    if scale is not None and not (_is_number(scale) and math.isfinite(scale) and scale > 0):
        problems.append(f"depth_scale must be a positive number (metres per depth unit) or null; got {scale!r}")
    labels = raw.get("labels", {})
    if not isinstance(labels, dict):
        problems.append(f"labels must be an object mapping mask values to names; got {labels!r}")
    else:
        for key, name in labels.items():
            if not (key.isdigit() and int(key) <= 255):
                problems.append(f"labels key {key!r} must be a mask value 0..255")
            if not isinstance(name, str):
                problems.append(f"labels[{key!r}] must be a string; got {name!r}")
    objects = raw.get("objects", [])
    if not (isinstance(objects, list) and all(isinstance(o, str) for o in objects)):
        problems.append(f"objects must be a list of names; got {objects!r}")
    return problems


def _raise_if(problems: list[str]) -> None:
    if problems:
        raise EpisodeFormatError("; ".join(problems))


@dataclass(eq=False)
class CameraInfo:
    """The camera that took an episode's images (OpenCV pinhole convention).

    Attributes:
        name: camera name, e.g. ``"ego"`` or ``"cam_high"``.
        width, height: image size in pixels.
        K: (3, 3) float64 intrinsics ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.
        dist: (D,) float64 distortion coefficients in OpenCV order, D in (0, 4, 5, 8, 12, 14).
        mount: ``"base"`` for a camera fixed to the robot base, or a link name (``"link6"``).
        T_mount_cam: (4, 4) float64 camera-to-mount transform (metres), None until calibrated.
        extra: unknown ``camera`` keys, written back unchanged.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))
    mount: str = "base"
    T_mount_cam: np.ndarray | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        try:
            self.K = np.asarray(self.K, dtype=np.float64)
            self.dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
            if self.T_mount_cam is not None:
                self.T_mount_cam = np.asarray(self.T_mount_cam, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise EpisodeFormatError(f"camera: K, dist and T_mount_cam must be arrays of numbers: {exc}") from None
        _raise_if(camera_problems(self._raw()))
        self.width, self.height = int(self.width), int(self.height)
        _raise_if([f"camera.extra must not repeat the field {k!r}" for k in self.extra if k in _CAMERA_KEYS])

    def _raw(self) -> dict[str, Any]:
        def plain(a: Any) -> Any:
            return a.tolist() if isinstance(a, (np.ndarray, np.generic)) else a

        return {"name": self.name, "width": plain(self.width), "height": plain(self.height),
                "K": plain(self.K), "dist": plain(self.dist), "mount": self.mount,
                "T_mount_cam": plain(self.T_mount_cam)}

    @classmethod
    def from_dict(cls, raw: Any) -> CameraInfo:
        """Parse the ``camera`` object; raises :class:`EpisodeFormatError` listing every problem."""
        _raise_if(camera_problems(raw))
        return cls(name=raw["name"], width=raw["width"], height=raw["height"], K=raw["K"],
                   dist=raw.get("dist", []), mount=raw.get("mount", "base"),
                   T_mount_cam=raw.get("T_mount_cam"),
                   extra={k: v for k, v in raw.items() if k not in _CAMERA_KEYS})

    def to_dict(self) -> dict[str, Any]:
        """The JSON object (plain lists; unknown keys from ``extra`` last)."""
        return {**self._raw(), **self.extra}


@dataclass(eq=False)
class RobotInfo:
    """The arm that made an episode.

    Attributes:
        model: e.g. ``"agilex_piper"``.
        joint_names: the 6 joint names that ``q1..q6`` are, in order.
        description: how to read the joint angles: a URDF path relative to the episode folder,
            or ``"builtin:agilex_piper"`` (piper_sdk's own kinematics).
        extra: unknown ``robot`` keys, written back unchanged.
    """

    model: str = "agilex_piper"
    joint_names: list[str] = field(default_factory=lambda: [f"joint{i}" for i in range(1, 7)])
    description: str = "builtin:agilex_piper"
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.joint_names = list(self.joint_names)
        _raise_if(robot_problems(self.to_dict()))
        _raise_if([f"robot.extra must not repeat the field {k!r}" for k in self.extra if k in _ROBOT_KEYS])

    @classmethod
    def from_dict(cls, raw: Any) -> RobotInfo:
        """Parse the ``robot`` object; raises :class:`EpisodeFormatError` listing every problem."""
        _raise_if(robot_problems(raw))
        return cls(model=raw["model"], joint_names=raw["joint_names"], description=raw["description"],
                   extra={k: v for k, v in raw.items() if k not in _ROBOT_KEYS})

    def to_dict(self) -> dict[str, Any]:
        """The JSON object (unknown keys from ``extra`` last)."""
        return {"model": self.model, "joint_names": list(self.joint_names),
                "description": self.description, **self.extra}


@dataclass(eq=False, kw_only=True)
class EpisodeMeta:
    """The content of ``episode.json`` (``docs/episode-format.md``).

    Attributes:
        format, version: ``"manisplat-episode"``, 1.
        complete: False while recording and after a crash, until ``recover``.
        source: ``"recorder"``, ``"simulation"``, ``"augmentation"`` or ``"import:<format>"``.
        created: UTC creation time, ``2026-11-21T12:00:00Z``.
        robot, camera: see :class:`RobotInfo`, :class:`CameraInfo`.
        fps: declared camera rate in Hz.
        frame_count: number of rows of ``frames.csv`` (set when the episode is closed).
        depth_scale: metres per unit of the uint16 depth images, None without depth.
        labels: mask value -> name (``background``, ``robot/<link>``, ``object/<name>``, ...).
        objects: names of the objects the task manipulates.
        extra: unknown top-level keys (and ``recovery`` entries), written back unchanged.
    """

    format: str = FORMAT
    version: int = VERSION
    complete: bool = False
    source: str = "recorder"
    created: str = field(default_factory=utc_now)
    robot: RobotInfo
    camera: CameraInfo
    fps: float
    frame_count: int = 0
    depth_scale: float | None = None
    labels: dict[int, str] = field(default_factory=dict)
    objects: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.fps = float(self.fps)
        if self.depth_scale is not None:
            self.depth_scale = float(self.depth_scale)
        self.labels = {int(k): v for k, v in self.labels.items()}
        self.objects = list(self.objects)
        _raise_if(meta_problems(self.to_dict()))
        _raise_if([f"extra must not repeat the field {k!r}" for k in self.extra if k in _META_KEYS])

    @classmethod
    def from_dict(cls, raw: Any) -> EpisodeMeta:
        """Parse a loaded ``episode.json``; raises :class:`EpisodeFormatError` listing every problem."""
        _raise_if(meta_problems(raw))
        return cls(format=raw["format"], version=raw["version"], complete=raw["complete"],
                   source=raw["source"], created=raw["created"],
                   robot=RobotInfo.from_dict(raw["robot"]), camera=CameraInfo.from_dict(raw["camera"]),
                   fps=raw["fps"], frame_count=raw["frame_count"], depth_scale=raw.get("depth_scale"),
                   labels={int(k): v for k, v in raw.get("labels", {}).items()},
                   objects=raw.get("objects", []),
                   extra={k: v for k, v in raw.items() if k not in _META_KEYS})

    def to_dict(self) -> dict[str, Any]:
        """The JSON object in the documented key order (unknown keys from ``extra`` last)."""
        return {"format": self.format, "version": self.version, "complete": self.complete,
                "source": self.source, "created": self.created, "robot": self.robot.to_dict(),
                "camera": self.camera.to_dict(), "fps": self.fps, "frame_count": self.frame_count,
                "depth_scale": self.depth_scale,
                "labels": {str(k): v for k, v in sorted(self.labels.items())},
                "objects": list(self.objects), **self.extra}


def read_meta_json(path: Path) -> dict[str, Any]:
    """The parsed JSON object of an ``episode.json`` file; raises :class:`EpisodeFormatError`
    naming the file when it is missing, not JSON or not an object."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise EpisodeFormatError(f"{path}: missing (not an episode folder?)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise EpisodeFormatError(f"{path}: cannot read: {exc}") from exc
    try:
        return parse_meta_text(text)
    except EpisodeFormatError as exc:
        raise EpisodeFormatError(f"{path}: {exc}") from None


def parse_meta_text(text: str) -> dict[str, Any]:
    """The JSON object in ``text``; raises :class:`EpisodeFormatError` when it is not JSON or not an object."""
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as exc:
        raise EpisodeFormatError(f"not valid JSON: {exc}") from None
    if not isinstance(raw, dict):
        raise EpisodeFormatError(f"must hold a JSON object; got {type(raw).__name__}")
    return raw


def load_meta(path: Path) -> EpisodeMeta:
    """Read and check an ``episode.json``; errors name the file and every bad field."""
    raw = read_meta_json(path)
    try:
        return EpisodeMeta.from_dict(raw)
    except EpisodeFormatError as exc:
        raise EpisodeFormatError(f"{path}: {exc}") from None


def save_meta(path: Path, meta: EpisodeMeta) -> None:
    """Write ``episode.json`` atomically and durably (temporary file, fsync, rename)."""
    text = json.dumps(meta.to_dict(), indent=1) + "\n"
    atomic_write_bytes(Path(path), text.encode("utf-8"))
