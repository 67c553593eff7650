"""The descriptions of cameras and arms in ``episode.json`` and their rules: the one ``camera`` and
``robot`` of version 1, the named ``cameras`` and ``arms`` of version 2 (``docs/episode-format.md``).

Every rule lives in one ``*_problems`` function that returns all the violations of a raw JSON
value as messages naming the field (``camera.K must be 3x3 ...``, ``cameras.cam_high.mount ...``).
``validate`` reports them one by one; the dataclasses run the same functions and raise
:class:`EpisodeFormatError`. Unknown keys are kept in ``extra`` dicts and written back unchanged.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any, Collection

import numpy as np

from manisplat.episode.format import CHROMA_SUBSAMPLING, DIST_LENGTHS, NAME_PATTERN, WORLD_MOUNT, EpisodeFormatError

RIGID_TOL = 1e-6
"""Tolerance of the rigid-transform checks: max |R^T R - I|, |det R - 1| and the last row."""

CAMERA_KEYS = ("name", "width", "height", "K", "dist", "mount", "T_mount_cam")
"""Fields of a version 1 ``camera`` object (a version 2 camera has them all but ``name``)."""
ROBOT_KEYS = ("model", "joint_names", "description")
"""Fields of a version 1 ``robot`` object."""
ARM_KEYS = (*ROBOT_KEYS, "T_world_base")
"""Fields of a version 2 arm: the robot's, plus where its base stands in the world."""
_NAME_RE = re.compile(NAME_PATTERN)


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


def name_problems(name: Any, what: str) -> list[str]:
    """Violations of an arm or camera name of version 2 (it becomes part of column and folder names)."""
    if isinstance(name, str) and _NAME_RE.fullmatch(name):
        return []
    return [f"{what} name {name!r} must be 1..64 letters, digits, '_' or '-' (it names columns and folders)"]


def _dist_problems(dist: Any, prefix: str) -> list[str]:
    if isinstance(dist, list) and all(_is_number(d) and math.isfinite(d) for d in dist) and len(dist) in DIST_LENGTHS:
        return []
    return [f"{prefix}.dist must be a list of {DIST_LENGTHS} finite numbers (OpenCV order); got {dist!r}"]


def _chroma_problems(raw: dict[str, Any], prefix: str) -> list[str]:
    """Violations of a camera's ``chroma_subsampling`` and ``chroma_red_blue_swapped`` (both optional)."""
    problems = []
    scheme = raw.get("chroma_subsampling")
    if "chroma_subsampling" in raw and scheme not in CHROMA_SUBSAMPLING:
        problems.append(f"{prefix}.chroma_subsampling must be one of {', '.join(CHROMA_SUBSAMPLING)}; got {scheme!r}")
    if "chroma_red_blue_swapped" in raw:
        if not isinstance(raw["chroma_red_blue_swapped"], bool):
            problems.append(f"{prefix}.chroma_red_blue_swapped must be true or false; got "
                            f"{raw['chroma_red_blue_swapped']!r}")
        if "chroma_subsampling" not in raw:
            problems.append(f"{prefix}.chroma_red_blue_swapped is given without chroma_subsampling")
    return problems


def _image_size_problems(raw: dict[str, Any], prefix: str) -> list[str]:
    return [f"{prefix}.{k} must be a positive integer; got {raw[k]!r}" for k in ("width", "height")
            if k in raw and not (_is_int(raw[k]) and raw[k] > 0)]


def camera_problems(raw: Any) -> list[str]:
    """Violations of the ``camera`` object of a version 1 ``episode.json``."""
    if not isinstance(raw, dict):
        return [f"camera must be an object; got {type(raw).__name__}"]
    problems = [f"camera.{k} is missing" for k in ("name", "width", "height", "K") if k not in raw]
    if "name" in raw and not isinstance(raw["name"], str):
        problems.append(f"camera.name must be a string; got {raw['name']!r}")
    problems += _image_size_problems(raw, "camera")
    if "K" in raw:
        problems += intrinsics_problems(raw["K"], raw.get("width"), raw.get("height"))
    problems += _dist_problems(raw.get("dist", []), "camera")
    mount = raw.get("mount", "base")
    if not (isinstance(mount, str) and mount):
        problems.append(f"camera.mount must be 'base' or a link name; got {mount!r}")
    if raw.get("T_mount_cam") is not None:
        problems += rigid_problems(raw["T_mount_cam"], "camera.T_mount_cam")
    return problems + _chroma_problems(raw, "camera")


def mount_problem(mount: Any, arms: Collection[str], prefix: str) -> str | None:
    """Why a version 2 ``mount`` is not ``"world"`` or ``"<arm>/<link>"`` of one of ``arms``, or None.
    (Whether the link exists in the arm's robot description is checked by ``validate``.)"""
    if mount == WORLD_MOUNT:
        return None
    if isinstance(mount, str) and mount.count("/") == 1:
        arm, link = mount.split("/")
        if arm in arms and link:
            return None
        if link:
            return (f"{prefix}.mount {mount!r} names the arm {arm!r}, which is not in arms "
                    f"({', '.join(arms) or 'none'})")
    return f"{prefix}.mount must be 'world' or '<arm>/<link>' (e.g. 'left/link6'); got {mount!r}"


def camera_v2_problems(name: Any, raw: Any, arms: Collection[str]) -> list[str]:
    """Violations of the camera ``name`` of a version 2 ``cameras`` object (mounts on ``arms``)."""
    prefix = f"cameras.{name}"
    problems = name_problems(name, "camera")
    if not isinstance(raw, dict):
        return problems + [f"{prefix} must be an object; got {type(raw).__name__}"]
    problems += [f"{prefix}.{k} is missing" for k in ("width", "height", "K", "mount", "T_mount_cam") if k not in raw]
    if "name" in raw:
        problems.append(f"{prefix}.name: not a field in version 2 (the key of cameras is the name)")
    problems += _image_size_problems(raw, prefix)
    if "K" in raw:
        problems += intrinsics_problems(raw["K"], raw.get("width"), raw.get("height"), name=f"{prefix}.K")
    problems += _dist_problems(raw.get("dist", []), prefix)
    if "mount" in raw:
        problem = mount_problem(raw["mount"], arms, prefix)
        problems += [problem] if problem else []
    if raw.get("T_mount_cam") is not None:
        problems += rigid_problems(raw["T_mount_cam"], f"{prefix}.T_mount_cam")
    latency = raw.get("latency_s")
    if latency is not None and not (_is_number(latency) and math.isfinite(latency)):
        problems.append(f"{prefix}.latency_s must be a finite number (s); got {latency!r}")
    return problems + _chroma_problems(raw, prefix)


def robot_problems(raw: Any, prefix: str = "robot") -> list[str]:
    """Violations of the ``robot`` object of a version 1 ``episode.json`` (or, with ``prefix``
    ``arms.<name>``, of the robot fields of a version 2 arm)."""
    if not isinstance(raw, dict):
        return [f"{prefix} must be an object; got {type(raw).__name__}"]
    problems = [f"{prefix}.{k} is missing" for k in ROBOT_KEYS if k not in raw]
    for k in ("model", "description"):
        if k in raw and not (isinstance(raw[k], str) and raw[k]):
            problems.append(f"{prefix}.{k} must be a non-empty string; got {raw[k]!r}")
    names = raw.get("joint_names", [])
    if "joint_names" in raw and not (isinstance(names, list) and len(names) == 6
                                     and all(isinstance(n, str) for n in names)):
        problems.append(f"{prefix}.joint_names must be a list of 6 strings (q1..q6); got {names!r}")
    return problems


def arm_problems(name: Any, raw: Any) -> list[str]:
    """Violations of the arm ``name`` of a version 2 ``arms`` object."""
    prefix = f"arms.{name}"
    problems = name_problems(name, "arm") + robot_problems(raw, prefix)
    if isinstance(raw, dict):
        if "T_world_base" not in raw:
            problems.append(f"{prefix}.T_world_base is missing (4x4, or null until the base is calibrated)")
        elif raw["T_world_base"] is not None:
            problems += rigid_problems(raw["T_world_base"], f"{prefix}.T_world_base")
    return problems


def _raise_if(problems: list[str]) -> None:
    if problems:
        raise EpisodeFormatError("; ".join(problems))


def _plain(a: Any) -> Any:
    return a.tolist() if isinstance(a, (np.ndarray, np.generic)) else a


def _matrix_or_none(value: Any, what: str) -> np.ndarray | None:
    if value is None:
        return None
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise EpisodeFormatError(f"{what} must be an array of numbers: {exc}") from None


@dataclass(eq=False)
class CameraInfo:
    """A camera that took an episode's images (OpenCV pinhole convention).

    Attributes:
        name: camera name, e.g. ``"ego"`` or ``"cam_high"`` (in version 2, its key in ``cameras``).
        width, height: image size in pixels.
        K: (3, 3) float64 intrinsics ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.
        dist: (D,) float64 distortion coefficients in OpenCV order, D in (0, 4, 5, 8, 12, 14).
        mount: version 1: ``"base"`` for a camera fixed to the robot base, or a link name
            (``"link6"``); version 2: ``"world"`` or ``"<arm>/<link>"`` (``"left/link6"``).
        T_mount_cam: (4, 4) float64 camera-to-mount transform (metres), None until calibrated.
        extra: unknown ``camera`` keys (``latency_s``, ``calibration``, ...), written back unchanged.
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
        except (TypeError, ValueError) as exc:
            raise EpisodeFormatError(f"camera: K, dist and T_mount_cam must be arrays of numbers: {exc}") from None
        self.T_mount_cam = _matrix_or_none(self.T_mount_cam, "camera.T_mount_cam")
        _raise_if(camera_problems(self._raw()))
        self.width, self.height = int(self.width), int(self.height)
        _raise_if([f"camera.extra must not repeat the field {k!r}" for k in self.extra if k in CAMERA_KEYS])

    def _raw(self) -> dict[str, Any]:
        return {"name": self.name, "width": _plain(self.width), "height": _plain(self.height),
                "K": _plain(self.K), "dist": _plain(self.dist), "mount": self.mount,
                "T_mount_cam": _plain(self.T_mount_cam)}

    @classmethod
    def from_dict(cls, raw: Any) -> CameraInfo:
        """Parse the version 1 ``camera`` object; raises :class:`EpisodeFormatError` listing every problem."""
        _raise_if(camera_problems(raw))
        return cls(name=raw["name"], width=raw["width"], height=raw["height"], K=raw["K"],
                   dist=raw.get("dist", []), mount=raw.get("mount", "base"),
                   T_mount_cam=raw.get("T_mount_cam"),
                   extra={k: v for k, v in raw.items() if k not in CAMERA_KEYS})

    @classmethod
    def from_v2_dict(cls, name: str, raw: Any, arms: Collection[str]) -> CameraInfo:
        """Parse the camera ``name`` of a version 2 ``cameras`` object (its mount on one of ``arms``)."""
        _raise_if(camera_v2_problems(name, raw, arms))
        return cls(name=name, width=raw["width"], height=raw["height"], K=raw["K"], dist=raw.get("dist", []),
                   mount=raw["mount"], T_mount_cam=raw["T_mount_cam"],
                   extra={k: v for k, v in raw.items() if k not in CAMERA_KEYS})

    def to_dict(self) -> dict[str, Any]:
        """The version 1 JSON object (plain lists; unknown keys from ``extra`` last)."""
        return {**self._raw(), **self.extra}

    def to_v2_dict(self) -> dict[str, Any]:
        """The version 2 JSON object: the version 1 one without ``name`` (the key names the camera)."""
        raw = self.to_dict()
        del raw["name"]
        return raw


@dataclass(eq=False)
class RobotInfo:
    """The arm that made a version 1 episode.

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
        _raise_if([f"robot.extra must not repeat the field {k!r}" for k in self.extra if k in ROBOT_KEYS])

    @classmethod
    def from_dict(cls, raw: Any) -> RobotInfo:
        """Parse the ``robot`` object; raises :class:`EpisodeFormatError` listing every problem."""
        _raise_if(robot_problems(raw))
        return cls(model=raw["model"], joint_names=raw["joint_names"], description=raw["description"],
                   extra={k: v for k, v in raw.items() if k not in ROBOT_KEYS})

    def to_dict(self) -> dict[str, Any]:
        """The version 1 JSON object (unknown keys from ``extra`` last)."""
        return {"model": self.model, "joint_names": list(self.joint_names),
                "description": self.description, **self.extra}


@dataclass(eq=False)
class ArmInfo(RobotInfo):
    """One named arm of an episode: its robot (as :class:`RobotInfo`) and where its base stands.

    Version 2 episodes list their arms by name; a version 1 episode has one, named ``"arm"``,
    whose base is the world (``T_world_base`` the identity).

    Attributes:
        name: the arm's name, its key in ``arms`` (``"left"``); its ``frames.csv`` columns are
            ``<name>.q1`` ... and its joint stream ``joints_<name>.csv``.
        T_world_base: (4, 4) float64 pose of the arm's base in the episode's world frame
            (metres), None until calibrated.
    """

    name: str = "arm"
    T_world_base: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.joint_names = list(self.joint_names)
        self.T_world_base = _matrix_or_none(self.T_world_base, f"arms.{self.name}.T_world_base")
        _raise_if(arm_problems(self.name, self.to_v2_dict()))
        _raise_if([f"arms.{self.name}.extra must not repeat the field {k!r}" for k in self.extra if k in ARM_KEYS])

    @classmethod
    def from_robot(cls, robot: RobotInfo, name: str = "arm", T_world_base: Any = None) -> ArmInfo:
        """The arm ``name`` with ``robot``'s fields (an :class:`ArmInfo` is returned as is)."""
        if isinstance(robot, ArmInfo):
            return robot
        return cls(model=robot.model, joint_names=list(robot.joint_names), description=robot.description,
                   extra=dict(robot.extra), name=name, T_world_base=T_world_base)

    @classmethod
    def from_v2_dict(cls, name: str, raw: Any) -> ArmInfo:
        """Parse the arm ``name`` of a version 2 ``arms`` object."""
        _raise_if(arm_problems(name, raw))
        return cls(model=raw["model"], joint_names=raw["joint_names"], description=raw["description"],
                   name=name, T_world_base=raw["T_world_base"],
                   extra={k: v for k, v in raw.items() if k not in ARM_KEYS})

    def to_v2_dict(self) -> dict[str, Any]:
        """The version 2 JSON object (unknown keys from ``extra`` last)."""
        return {"model": self.model, "joint_names": list(self.joint_names), "description": self.description,
                "T_world_base": _plain(self.T_world_base), **self.extra}
