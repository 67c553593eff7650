"""Import a whole AgileX Cobot Magic (ACT-style, dual-arm) HDF5 episode as a version 2 episode:
both arms, every camera, depth, actions, with the calibration a ``*.calib.json`` sidecar gives.

The HDF5 layout is :mod:`manisplat.episode.importers.act_hdf5`'s: ``/observations/qpos`` (T, 14)
= left 6 joints + gripper, right 6 joints + gripper; ``/action`` (T, 14) optional;
``/observations/images/<cam>`` raw (T, H, W, 3) uint8 RGB or ``compress``ed JPEG rows;
``/observations/images_depth/<cam>`` (T, H, W) uint16 optional. Such files hold no calibration:
the sidecar (``docs/cobot-magic.md``) gives, per camera, ``K``, ``dist``, ``mount`` (``world`` or
``<arm>/<link>``) and ``T_mount_cam``, and per arm ``T_world_base`` and its robot description.

Joints are copied as the file holds them (float64, or float32 widened exactly to float64), so
``frames.csv`` reads back bit-exact.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from manisplat.episode.format import GRIPPER_EFFORT_COLUMN, EpisodeFormatError
from manisplat.episode.importers.act_hdf5 import (SOURCE, _camera_dataset, _chroma_subsampling, _contents, _dataset,
                                                 _images)
from manisplat.episode.infos import ArmInfo, CameraInfo, arm_problems, camera_v2_problems
from manisplat.episode.reader import Episode
from manisplat.episode.writer_v2 import EpisodeWriterV2

log = logging.getLogger(__name__)

DEFAULT_COLUMNS = {"left": (list(range(0, 6)), 6), "right": (list(range(7, 13)), 13)}
"""``qpos``/``action`` columns (6 joints, gripper) of the arms of the 14-D Cobot Magic layout."""
DEPTH_UNIT_M = 0.001
"""Cobot Magic depth images are uint16 millimetres unless the sidecar says otherwise."""
HOW_TO_CALIBRATE = ("give them with --calib FILE.calib.json (per camera K, dist, mount, T_mount_cam; per arm "
                    "T_world_base and urdf or description; see docs/cobot-magic.md), or import one arm and one "
                    "camera as a version 1 episode with --arm left|right --camera NAME --K fx,fy,cx,cy")


#: what a calibration file gives of a camera (besides ``depth``), as an episode stores it
CALIBRATION_CAMERA_KEYS = ("width", "height", "K", "dist", "mount", "T_mount_cam", "latency_s")


@dataclass
class CobotCalibration:
    """What a ``*.calib.json`` sidecar says about a recording.

    Attributes:
        path: the sidecar.
        arms: name -> :class:`ArmInfo` (description resolved, ``T_world_base`` (4, 4) float64).
        columns: arm name -> (6 joint columns, gripper column) of ``qpos`` and ``action``.
        cameras: name -> its ``K``, ``dist``, ``mount`` (version 2: ``world`` or ``<arm>/<link>``),
            ``T_mount_cam`` and, when given, ``width``, ``height``, ``latency_s``.
        sizes: camera name -> (width, height) when the sidecar gives them.
        depth_units: camera name -> metres per depth unit.
        fps: the recording rate, or None when the sidecar has none.
    """

    path: Path
    arms: dict[str, ArmInfo]
    columns: dict[str, tuple[list[int], int]]
    cameras: dict[str, dict[str, Any]]
    sizes: dict[str, tuple[int, int]] = field(default_factory=dict)
    depth_units: dict[str, float] = field(default_factory=dict)
    fps: float | None = None

    @property
    def gripper_effort_columns(self) -> list[str]:
        """Each arm's ``frames.csv`` column ``<arm>.gripper_effort``, in the order of :attr:`columns`."""
        return [f"{arm}.{GRIPPER_EFFORT_COLUMN}" for arm in self.columns]

    def gripper_efforts(self, row: np.ndarray) -> dict[str, float]:
        """:attr:`gripper_effort_columns` -> each arm's gripper column of one row (D,) laid out like
        ``qpos``, as stored."""
        return {column: float(row[g]) for column, (_, g) in zip(self.gripper_effort_columns, self.columns.values())}


def _description(path: Path, name: str, arm: dict[str, Any]) -> str:
    """The robot description of an arm of the sidecar: ``description`` as given, or ``urdf``
    (relative to the sidecar) as an absolute path."""
    if isinstance(arm.get("description"), str) and arm["description"]:
        return arm["description"]
    urdf = arm.get("urdf")
    if not (isinstance(urdf, str) and urdf):
        raise EpisodeFormatError(f"{path}: arms.{name}: no robot description: give 'urdf' (a URDF path relative to "
                                 "this file) or 'description' (e.g. builtin:agilex_piper)")
    file = Path(os.path.abspath(path.parent / urdf))
    if not file.is_file():
        raise EpisodeFormatError(f"{path}: arms.{name}.urdf {urdf!r} not found (looked at {file})")
    return str(file)


def _columns(path: Path, name: str, arm: dict[str, Any]) -> tuple[list[int], int]:
    joints, gripper = arm.get("qpos_columns"), arm.get("gripper_column")
    if joints is None and gripper is None:
        if name not in DEFAULT_COLUMNS:
            raise EpisodeFormatError(f"{path}: arms.{name}: no qpos_columns and gripper_column, and {name!r} is not "
                                     f"an arm of the 14-D Cobot Magic layout ({', '.join(DEFAULT_COLUMNS)})")
        return DEFAULT_COLUMNS[name]
    if not (isinstance(joints, list) and len(joints) == 6 and all(isinstance(j, int) and j >= 0 for j in joints)
            and isinstance(gripper, int) and gripper >= 0):
        raise EpisodeFormatError(f"{path}: arms.{name}: qpos_columns must be 6 column numbers and gripper_column "
                                 f"one; got {joints!r}, {gripper!r}")
    return joints, gripper


def load_calibration(path: str | Path) -> CobotCalibration:
    """Read a Cobot Magic calibration sidecar; raises :class:`EpisodeFormatError` naming the file
    and every missing or wrong field."""
    path = Path(path)
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise EpisodeFormatError(f"{path}: no such calibration file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise EpisodeFormatError(f"{path}: cannot read the calibration: {exc}") from None
    if not isinstance(raw, dict):
        raise EpisodeFormatError(f"{path}: must hold a JSON object")
    missing = [k for k in ("arms", "cameras") if not (isinstance(raw.get(k), dict) and raw[k])]
    if missing:
        raise EpisodeFormatError(f"{path}: no {' and no '.join(missing)} (objects by name): importing a Cobot Magic "
                                 "file whole needs per camera K, mount and T_mount_cam, and per arm T_world_base "
                                 "and its robot description")
    problems = []
    arms, columns = {}, {}
    for name, arm in raw["arms"].items():
        entry = {"model": "agilex_piper", "joint_names": [f"joint{i}" for i in range(1, 7)],
                 "description": "builtin:agilex_piper", **(arm if isinstance(arm, dict) else {})}
        entry = {k: entry[k] for k in ("model", "joint_names", "description", "T_world_base") if k in entry}
        found = arm_problems(name, entry) if isinstance(arm, dict) else [f"arms.{name} must be an object"]
        if found:
            problems += found
            continue
        arms[name] = ArmInfo(name=name, model=entry["model"], joint_names=entry["joint_names"],
                             description=_description(path, name, arm), T_world_base=entry["T_world_base"])
        columns[name] = _columns(path, name, arm)
    cameras, sizes, units = {}, {}, {}
    for name, camera in raw["cameras"].items():
        if not isinstance(camera, dict):
            problems.append(f"cameras.{name} must be an object")
            continue
        entry = {k: camera[k] for k in CALIBRATION_CAMERA_KEYS if k in camera}
        probe = dict(entry)
        if "width" not in probe or "height" not in probe:  # the images give the size (checked then)
            probe.update(width=10 ** 6, height=10 ** 6)
        found = camera_v2_problems(name, probe, list(raw["arms"]))
        if found:
            problems += found
            continue
        cameras[name] = entry
        if "width" in camera and "height" in camera:
            sizes[name] = (camera["width"], camera["height"])
        depth = camera.get("depth")
        unit = depth.get("unit_m", DEPTH_UNIT_M) if isinstance(depth, dict) else DEPTH_UNIT_M
        if not (isinstance(unit, (int, float)) and not isinstance(unit, bool) and unit > 0):
            problems.append(f"cameras.{name}.depth.unit_m must be a positive number; got {unit!r}")
        units[name] = float(unit)
    fps = raw.get("fps")
    if fps is not None and not (isinstance(fps, (int, float)) and not isinstance(fps, bool) and fps > 0):
        problems.append(f"fps must be a positive number; got {fps!r}")
    if problems:
        raise EpisodeFormatError(f"{path}: " + "; ".join(problems))
    return CobotCalibration(path, arms, columns, cameras, sizes, units, None if fps is None else float(fps))


def check_cameras(cal: CobotCalibration, cameras: list[str], holder: str) -> None:
    """Refuse a calibration that lacks one of ``cameras`` (those ``holder``, e.g. "the file X",
    has), naming them; warn about its cameras the recording does not have."""
    uncalibrated = [c for c in cameras if c not in cal.cameras]
    if uncalibrated:
        raise EpisodeFormatError(f"{cal.path}: no camera {', '.join(uncalibrated)} ({holder} has "
                                 f"{', '.join(cameras)}; the calibration has {', '.join(cal.cameras)})")
    for extra in (c for c in cal.cameras if c not in cameras):
        log.warning("%s: camera %s is not in %s; ignored", cal.path, extra, holder)


def _arm_names(width: int) -> str:
    return "left, right" if width == 14 else f"{width} columns"


def _like_qpos(f: h5py.File, name: str, shape: tuple[int, ...], h5_path: Path) -> np.ndarray | None:
    """The optional dataset ``/name`` as float64, laid out like ``/observations/qpos`` (``shape``);
    None when the file has none."""
    if name not in f:
        return None
    ds = _dataset(f, name, h5_path)
    if ds.shape != shape:
        raise EpisodeFormatError(f"{h5_path}: /{name} has shape {ds.shape}; expected {shape} like /observations/qpos")
    return np.asarray(ds[()], dtype=np.float64)


def import_cobot_magic(h5_path: str | Path, out_dir: str | Path, calib: str | Path | CobotCalibration | None, *,
                       fps: float | None = None, gripper_scale: float = 1.0, bgr: bool = False,
                       task: str | None = None, image_format: str = "png", overwrite: bool = False) -> Episode:
    """Convert a whole Cobot Magic HDF5 episode (every arm and camera) into a version 2 episode folder.

    Frame ``i`` gets ``t = i / fps``; each arm's ``q1..q6`` and ``gripper`` from its columns of
    ``/observations/qpos`` (its actions from ``/action`` and its gripper's effort from
    ``/observations/effort``, column ``<arm>.gripper_effort``, when present); every camera's image
    (decoded from JPEG rows when the file is ``compress``ed; stored arrays are RGB, see
    ``bgr``) and its depth when ``images_depth/<cam>`` exists.

    Args:
        h5_path: the ``.hdf5`` file.
        out_dir: episode folder to create.
        calib: the calibration sidecar (``*.calib.json``) or what :func:`load_calibration` read;
            None raises :class:`EpisodeFormatError` naming what the import needs and how to give it.
        fps: recording rate in Hz; default: the sidecar's ``fps``.
        gripper_scale: factor from the file's gripper value to the finger-pad gap in metres.
        bgr: the stored image arrays are BGR, not RGB.
        task: task description, stored as ``episode.json`` ``task``.
        image_format: ``"png"`` (lossless) or ``"jpg"`` for the rgb files.
        overwrite: replace an existing episode at ``out_dir``.

    Returns:
        the new episode, opened for reading.
    """
    h5_path, out_dir = Path(h5_path), Path(out_dir)
    if not h5_path.is_file():
        raise FileNotFoundError(f"{h5_path}: no such file")
    with h5py.File(h5_path, "r") as f:
        qpos_ds = _dataset(f, "observations/qpos", h5_path)
        group = f.get("observations/images")
        if not isinstance(group, h5py.Group) or not len(group):
            raise EpisodeFormatError(f"{h5_path}: no cameras under /observations/images; the file has: {_contents(f)}")
        names = list(group)
        if calib is None:
            raise EpisodeFormatError(
                f"{h5_path}: holds {len(names)} camera(s) ({', '.join(names)}) and arms ({_arm_names(qpos_ds.shape[-1])})"
                f" but no calibration: importing it whole needs, per camera, K (intrinsics), mount (world or "
                f"<arm>/<link>) and T_mount_cam, and per arm T_world_base and its robot description; "
                + HOW_TO_CALIBRATE)
        cal = calib if isinstance(calib, CobotCalibration) else load_calibration(calib)
        check_cameras(cal, names, f"the file {h5_path.name}")
        rate = fps if fps is not None else cal.fps
        if rate is None:
            raise EpisodeFormatError(f"{h5_path}: no frame rate: give --fps, or 'fps' in {cal.path}")

        length, width = qpos_ds.shape[0], qpos_ds.shape[-1]
        if qpos_ds.ndim != 2:
            raise EpisodeFormatError(f"{h5_path}: /observations/qpos has shape {qpos_ds.shape}; expected (T, 14)")
        used = [c for joints, gripper in cal.columns.values() for c in (*joints, gripper)]
        if max(used) >= width or len(set(used)) != len(used):
            raise EpisodeFormatError(f"{h5_path}: /observations/qpos has {width} columns; the arms of {cal.path} "
                                     f"({', '.join(cal.arms)}) need the distinct columns {sorted(used)}")
        qpos = np.asarray(qpos_ds[()], dtype=np.float64)  # float32 widens exactly
        action = _like_qpos(f, "action", qpos_ds.shape, h5_path)
        effort = _like_qpos(f, "observations/effort", qpos_ds.shape, h5_path)
        effort_columns = cal.gripper_effort_columns if effort is not None else []

        streams, depths, cameras = {}, {}, []
        for name in names:
            ds, compressed = _camera_dataset(f, name, length, h5_path)
            frames = _images(ds, compressed, bgr, h5_path)
            first = next(frames, None)
            if first is None:
                raise EpisodeFormatError(f"{h5_path}: {ds.name} holds no frames")
            height, w = first.shape[:2]
            if cal.sizes.get(name, (w, height)) != (w, height):
                raise EpisodeFormatError(f"{h5_path}: {ds.name} images are {w}x{height} but {cal.path} says "
                                         f"{cal.sizes[name][0]}x{cal.sizes[name][1]}")
            streams[name] = (first, frames, compressed)
            entry = {**cal.cameras[name], "width": w, "height": height, **_chroma_subsampling(ds, compressed, bgr, h5_path)}
            cameras.append(CameraInfo.from_v2_dict(name, entry, list(cal.arms)))
            depth = f.get(f"observations/images_depth/{name}")
            if depth is not None:
                if depth.shape != (length, height, w) or depth.dtype != np.uint16:
                    raise EpisodeFormatError(f"{h5_path}: {depth.name} has shape {depth.shape} {depth.dtype}; "
                                             f"expected ({length}, {height}, {w}) uint16")
                depths[name] = depth
        units = {cal.depth_units[n] for n in depths}
        if len(units) > 1:
            raise EpisodeFormatError(f"{cal.path}: the cameras' depth units differ ({sorted(units)} m); an episode "
                                     "has one depth_scale")
        source_info = {"file": h5_path.name, "calibration": cal.path.name, "arms": {
            n: {"qpos_columns": j, "gripper_column": g} for n, (j, g) in cal.columns.items()},
            "cameras": names, "sim": bool(f.attrs.get("sim", False)),
            "compress": any(c for _, _, c in streams.values()), "gripper_scale": gripper_scale}
        extra_meta = {"import": source_info, **({"task": task} if task is not None else {})}
        scale = np.array([1.0] * 6 + [gripper_scale])
        with EpisodeWriterV2(out_dir, list(cal.arms.values()), cameras, rate, source=SOURCE,
                             depth_scale=units.pop() if units else None, image_format=image_format,
                             actions=action is not None, extra_frame_columns=effort_columns, extra_meta=extra_meta,
                             overwrite=overwrite) as writer:
            for i in range(length):
                rgb = {}
                for name, (first, frames, _) in streams.items():
                    rgb[name] = first if i == 0 else next(frames)
                state = {a: qpos[i, [*j, g]] * scale for a, (j, g) in cal.columns.items()}
                acts = None if action is None else {a: action[i, [*j, g]] * scale for a, (j, g) in cal.columns.items()}
                grip = None if effort is None else cal.gripper_efforts(effort[i])
                try:
                    writer.add_frame(i / rate, state, rgb, depth={n: d[i] for n, d in depths.items()}, actions=acts,
                                     extra=grip)
                except ValueError as exc:
                    raise EpisodeFormatError(f"{h5_path}: frame {i}: {exc}") from exc
    log.info("%s: imported %d frames of %d arms and %d cameras into %s", h5_path, length, len(cal.arms),
             len(names), out_dir)
    return Episode.open(out_dir)

