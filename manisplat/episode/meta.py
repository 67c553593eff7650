"""``episode.json``: the typed metadata of an episode (both format versions), its rules, and JSON load/save.

Every rule lives in one ``*_problems`` function that returns all the violations of a raw JSON
value as messages naming the field (``camera.K must be 3x3 ...``). ``validate`` reports them
one by one; the classes run the same functions and raise :class:`EpisodeFormatError`. Unknown
keys are kept in ``extra`` dicts and written back unchanged. The camera and arm descriptions and
their rules live in :mod:`manisplat.episode.infos` (re-exported here).

Version 1 has one ``robot`` and one ``camera``; version 2 has named ``arms`` and ``cameras``.
:class:`EpisodeMeta` holds both as ``arms`` and ``cameras`` dicts (a version 1 episode has one arm,
named ``"arm"``, whose base is the world), and offers the one-arm view (``robot``, ``camera``)
that the tools that are not multi-arm yet read; on an episode with several arms or cameras
that view raises :class:`EpisodeFormatError` saying so.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from manisplat.episode.format import FORMAT, V1_ARM, VERSION, VERSION_2, WORLD_MOUNT, EpisodeFormatError
from manisplat.episode.fsio import atomic_write_bytes
from manisplat.episode.infos import (ARM_KEYS, CAMERA_KEYS, RIGID_TOL, ROBOT_KEYS, ArmInfo, CameraInfo, RobotInfo,
                                     _is_int, _is_number, _raise_if, arm_problems, camera_problems,
                                     camera_v2_problems, intrinsics_problems, mount_problem, name_problems,
                                     rigid_problems, robot_problems)
from manisplat.episode.layout import Layout, is_v2_raw, v1_layout, v2_layout

__all__ = ["ARM_KEYS", "CAMERA_KEYS", "RIGID_TOL", "ROBOT_KEYS", "ArmInfo", "CameraInfo", "EpisodeMeta", "RobotInfo",
           "arm_problems", "camera_problems", "camera_v2_problems", "intrinsics_problems", "load_meta",
           "meta_problems", "mount_problem", "name_problems", "parse_meta_text", "read_meta_json", "rigid_problems",
           "robot_problems", "save_meta", "utc_now"]

_COMMON_KEYS = ("format", "version", "complete", "source", "created", "fps", "frame_count", "depth_scale", "labels",
                "objects")
_V1_KEYS = (*_COMMON_KEYS, "robot", "camera")
_V2_KEYS = (*_COMMON_KEYS, "arms", "cameras")
_COMMON_REQUIRED = ("format", "version", "complete", "source", "created", "fps", "frame_count")
SINGLE_ARM_NOTE = "format version 1, or version 2 with one arm and one camera"
"""What the one-arm view (``robot``, ``camera``, ``ep.frames``, ``ep.rgb(i)``) reads."""


def utc_now() -> str:
    """The current UTC time as ``2026-11-21T12:00:00Z`` (the ``created`` field's form)."""
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def _common_problems(raw: dict[str, Any]) -> list[str]:
    """Violations of the fields both versions share (all but the arms and cameras)."""
    problems = []
    if "format" in raw and raw["format"] != FORMAT:
        problems.append(f"format must be {FORMAT!r}; got {raw['format']!r}")
    if "complete" in raw and not isinstance(raw["complete"], bool):
        problems.append(f"complete must be true or false; got {raw['complete']!r}")
    for k in ("source", "created"):
        if k in raw and not (isinstance(raw[k], str) and raw[k]):
            problems.append(f"{k} must be a non-empty string; got {raw[k]!r}")
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


def _v1_problems(raw: dict[str, Any]) -> list[str]:
    problems = [f"missing field '{k}'" for k in (*_COMMON_REQUIRED[:5], "robot", "camera", *_COMMON_REQUIRED[5:])
                if k not in raw]
    if "version" in raw and not (_is_int(raw["version"]) and raw["version"] == VERSION):
        problems.append(f"version must be {VERSION} for an episode.json with robot and camera (version "
                        f"{VERSION_2} has arms and cameras); got {raw['version']!r}")
    problems += _common_problems(raw)
    if "robot" in raw:
        problems += robot_problems(raw["robot"])
    if "camera" in raw:
        problems += camera_problems(raw["camera"])
    return problems


def _v2_problems(raw: dict[str, Any]) -> list[str]:
    problems = [f"missing field '{k}'" for k in (*_COMMON_REQUIRED[:5], "arms", "cameras", *_COMMON_REQUIRED[5:])
                if k not in raw]
    if "version" in raw and not (_is_int(raw["version"]) and raw["version"] == VERSION_2):
        problems.append(f"version must be {VERSION_2} for an episode.json with arms and cameras (version "
                        f"{VERSION} has robot and camera); got {raw['version']!r}")
    problems += [f"{k}: a version {VERSION} field; version {VERSION_2} describes it under {k.replace('robot', 'arm')}s"
                 for k in ("robot", "camera") if k in raw]
    problems += _common_problems(raw)
    arms, cameras = raw.get("arms"), raw.get("cameras")
    if "arms" in raw:
        if not (isinstance(arms, dict) and arms):
            problems.append(f"arms must be an object mapping arm names to arms, with at least one; got {arms!r}")
        else:
            for name, arm in arms.items():
                problems += arm_problems(name, arm)
    if "cameras" in raw:
        if not (isinstance(cameras, dict) and cameras):
            problems.append(f"cameras must be an object mapping camera names to cameras, with at least one; "
                            f"got {cameras!r}")
        else:
            arm_names = list(arms) if isinstance(arms, dict) else []
            for name, camera in cameras.items():
                problems += camera_v2_problems(name, camera, arm_names)
            problems += [f"{name!r} names both an arm and a camera: their columns would mix ({name}.*)"
                         for name in cameras if name in arm_names]
    return problems


def meta_problems(raw: Any) -> list[str]:
    """Every violation of the format in a parsed ``episode.json`` of either version (empty when it is valid).

    An ``episode.json`` with ``arms`` or ``cameras`` (or version 2 without ``robot`` and
    ``camera``) is checked as version 2, any other as version 1.
    """
    if not isinstance(raw, dict):
        return [f"must hold a JSON object; got {type(raw).__name__}"]
    return _v2_problems(raw) if is_v2_raw(raw) else _v1_problems(raw)


def _by_name(items: Mapping[str, Any] | Iterable[Any], what: str) -> dict[str, Any]:
    """``items`` (a mapping name -> info, or infos with a ``name``) as a dict keyed by each info's name."""
    if isinstance(items, Mapping):
        wrong = [f"{k!r} -> {v.name!r}" for k, v in items.items() if k != v.name]
        if wrong:
            raise EpisodeFormatError(f"{what}: each key must be its {what[:-1]}'s name; got {', '.join(wrong)}")
        return dict(items)
    out: dict[str, Any] = {}
    for item in items:
        if item.name in out:
            raise EpisodeFormatError(f"{what}: the name {item.name!r} is given twice")
        out[item.name] = item
    return out


def _inverse(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    inv = np.eye(4)
    inv[:3, :3], inv[:3, 3] = R.T, -R.T @ t
    return inv


def base_frame_camera(camera: CameraInfo, arm: ArmInfo) -> CameraInfo:
    """A version 2 ``camera`` in version 1 terms, relative to ``arm``'s base: mount ``"world"``
    becomes ``"base"`` with ``T_base_cam = inv(T_world_base) @ T_world_cam`` (None while either is
    unknown), ``"<arm>/<link>"`` becomes ``"<link>"``."""
    if camera.mount == WORLD_MOUNT:
        mount = "base"
        T = (None if camera.T_mount_cam is None or arm.T_world_base is None
             else _inverse(arm.T_world_base) @ camera.T_mount_cam)
    else:
        mount, T = camera.mount.split("/", 1)[1], camera.T_mount_cam
    return CameraInfo(name=camera.name, width=camera.width, height=camera.height, K=camera.K.copy(),
                      dist=camera.dist.copy(), mount=mount, T_mount_cam=None if T is None else np.array(T),
                      extra=dict(camera.extra))


class EpisodeMeta:
    """The content of ``episode.json`` (``docs/episode-format.md``), either version.

    Give ``robot`` and ``camera`` for a version 1 episode, or ``arms`` and ``cameras`` (mappings
    name -> info, or sequences of infos) for a version 2 one.

    Attributes:
        format, version: ``"manisplat-episode"``, 1 or 2.
        complete: False while recording and after a crash, until ``recover``.
        source: ``"recorder"``, ``"simulation"``, ``"augmentation"`` or ``"import:<format>"``.
        created: UTC creation time, ``2026-11-21T12:00:00Z``.
        arms: name -> :class:`ArmInfo`, in file order (version 1: one, named ``"arm"``, based at the world origin).
        cameras: name -> :class:`CameraInfo`, in file order (version 1: one).
        fps: declared camera rate in Hz.
        frame_count: number of rows of ``frames.csv`` (set when the episode is closed).
        depth_scale: metres per unit of the uint16 depth images (every camera), None without depth.
        labels: mask value -> name (``background``, ``robot/<link>``, ``object/<name>``, ...).
        objects: names of the objects the task manipulates.
        extra: unknown top-level keys (and ``recovery`` entries), written back unchanged.
        origin: where it was read from, for messages (not stored).
    """

    def __init__(self, *, format: str = FORMAT, version: int | None = None, complete: bool = False,
                 source: str = "recorder", created: str | None = None, robot: RobotInfo | None = None,
                 camera: CameraInfo | None = None, arms: Mapping[str, ArmInfo] | Iterable[ArmInfo] | None = None,
                 cameras: Mapping[str, CameraInfo] | Iterable[CameraInfo] | None = None, fps: float,
                 frame_count: int = 0, depth_scale: float | None = None, labels: Mapping[int, str] | None = None,
                 objects: Iterable[str] | None = None, extra: Mapping[str, Any] | None = None) -> None:
        one = robot is not None or camera is not None
        many = arms is not None or cameras is not None
        if one == many or (one and (robot is None or camera is None)) or (many and (arms is None or cameras is None)):
            raise EpisodeFormatError("EpisodeMeta needs robot and camera (version 1) or arms and cameras (version 2)")
        self.format = format
        self.version = (VERSION if one else VERSION_2) if version is None else version
        self.complete = complete
        self.source = source
        self.created = utc_now() if created is None else created
        if one:
            if self.version != VERSION:
                raise EpisodeFormatError(f"version must be {VERSION} with robot and camera; got {self.version!r}")
            self.arms: dict[str, ArmInfo] = {V1_ARM: ArmInfo.from_robot(robot, V1_ARM, np.eye(4))}
            self.cameras: dict[str, CameraInfo] = {camera.name: camera}
        else:
            self.arms, self.cameras = _by_name(arms, "arms"), _by_name(cameras, "cameras")
        self.fps = float(fps)
        self.frame_count = frame_count
        self.depth_scale = None if depth_scale is None else float(depth_scale)
        self.labels = {int(k): v for k, v in (labels or {}).items()}
        self.objects = list(objects or [])
        self.extra = dict(extra or {})
        self.origin = "this episode"
        _raise_if(meta_problems(self.to_dict()))
        keys = _V1_KEYS if self.version == VERSION else _V2_KEYS
        _raise_if([f"extra must not repeat the field {k!r}" for k in self.extra if k in keys])

    @property
    def arm_names(self) -> list[str]:
        return list(self.arms)

    @property
    def camera_names(self) -> list[str]:
        return list(self.cameras)

    def _refuse_several(self, arms: bool = True, cameras: bool = True) -> None:
        for wanted, what, names in ((arms, "arms", self.arms), (cameras, "cameras", self.cameras)):
            if wanted and len(names) != 1:
                raise EpisodeFormatError(f"{self.origin} has {what} {', '.join(names)}: this tool reads one-arm "
                                         f"episodes ({SINGLE_ARM_NOTE})")

    @property
    def layout(self) -> Layout:
        """Where each arm's columns and each camera's images are (:mod:`manisplat.episode.layout`)."""
        if self.version == VERSION:
            return v1_layout(next(iter(self.cameras)))
        return v2_layout(self.arms, self.cameras)

    def refuse_several(self, *, arms: bool = True, cameras: bool = True) -> None:
        """Raise :class:`EpisodeFormatError` naming them when the episode has several arms (with
        ``arms``) or several cameras (with ``cameras``): the one-arm view cannot read it."""
        self._refuse_several(arms, cameras)

    @property
    def robot(self) -> ArmInfo:
        """The one arm (version 1's ``robot``); raises :class:`EpisodeFormatError` naming the arms
        or cameras when the episode has several."""
        self._refuse_several()
        return next(iter(self.arms.values()))

    @property
    def camera(self) -> CameraInfo:
        """The one camera, in version 1 terms (relative to the one arm's base, see
        :func:`base_frame_camera`; a version 2 episode gives a copy: change ``cameras[name]``);
        raises :class:`EpisodeFormatError` naming the arms or cameras when there are several."""
        self._refuse_several()
        camera = next(iter(self.cameras.values()))
        return camera if self.version == VERSION else base_frame_camera(camera, self.robot)

    @classmethod
    def from_dict(cls, raw: Any) -> EpisodeMeta:
        """Parse a loaded ``episode.json`` of either version; raises :class:`EpisodeFormatError`
        listing every problem."""
        _raise_if(meta_problems(raw))
        common = dict(format=raw["format"], version=raw["version"], complete=raw["complete"], source=raw["source"],
                      created=raw["created"], fps=raw["fps"], frame_count=raw["frame_count"],
                      depth_scale=raw.get("depth_scale"), labels={int(k): v for k, v in raw.get("labels", {}).items()},
                      objects=raw.get("objects", []))
        if is_v2_raw(raw):
            arms = [ArmInfo.from_v2_dict(name, arm) for name, arm in raw["arms"].items()]
            cameras = [CameraInfo.from_v2_dict(name, cam, list(raw["arms"])) for name, cam in raw["cameras"].items()]
            return cls(**common, arms=arms, cameras=cameras, extra={k: v for k, v in raw.items() if k not in _V2_KEYS})
        return cls(**common, robot=RobotInfo.from_dict(raw["robot"]), camera=CameraInfo.from_dict(raw["camera"]),
                   extra={k: v for k, v in raw.items() if k not in _V1_KEYS})

    def to_dict(self) -> dict[str, Any]:
        """The JSON object in the documented key order (unknown keys from ``extra`` last)."""
        head = {"format": self.format, "version": self.version, "complete": self.complete, "source": self.source,
                "created": self.created}
        if self.version == VERSION and len(self.arms) == 1 and len(self.cameras) == 1:
            (arm,), (camera,) = self.arms.values(), self.cameras.values()
            head.update(robot=RobotInfo.to_dict(arm), camera=camera.to_dict())
        else:
            head.update(arms={n: a.to_v2_dict() for n, a in self.arms.items()},
                        cameras={n: c.to_v2_dict() for n, c in self.cameras.items()})
        return {**head, "fps": self.fps, "frame_count": self.frame_count, "depth_scale": self.depth_scale,
                "labels": {str(k): v for k, v in sorted(self.labels.items())}, "objects": list(self.objects),
                **self.extra}


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
        meta = EpisodeMeta.from_dict(raw)
    except EpisodeFormatError as exc:
        raise EpisodeFormatError(f"{path}: {exc}") from None
    meta.origin = str(Path(path).parent)
    return meta


def save_meta(path: Path, meta: EpisodeMeta) -> None:
    """Write ``episode.json`` atomically and durably (temporary file, fsync, rename)."""
    text = json.dumps(meta.to_dict(), indent=1) + "\n"
    atomic_write_bytes(Path(path), text.encode("utf-8"))
