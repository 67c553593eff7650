"""``rig.json``: what ``manisplat-calibrate solve-rig`` writes and ``apply`` puts into version 2 episodes.

Fields: ``format`` ("manisplat-rig-calibration"), ``version`` (1), ``date``, ``world`` (what the
world frame is), ``T_world_board``; ``cameras.<cam>``: ``K``, ``dist``, ``width``, ``height``,
``mount`` (``world`` or ``<arm>/<link>``), ``T_mount_cam`` (4x4, ``T_world_cam`` for ``world``),
``residuals`` and ``uncertainty``; ``arms.<arm>``: ``T_world_base`` (4x4), ``from_camera``,
``uncertainty``; provenance: ``board``, ``corner_offset_px``, ``opencv``, ``episode``,
``rejected_frames``. The ``cameras`` and ``arms`` entries have the keys of a Cobot Magic
calibration sidecar (docs/cobot-magic.md) and of a version 2 ``episode.json``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from manisplat.calib.camera import CameraModel
from manisplat.calib.errors import CalibrationError, InputError, read_json
from manisplat.calib.poses import is_rigid
from manisplat.calib.result import _finite_tree, write_calibrated_meta
from manisplat.calib.rig import BASES_WORLD, RigSolve
from manisplat.episode.fsio import atomic_write_bytes
from manisplat.episode.format import WORLD_MOUNT
from manisplat.episode.meta import read_meta_json, utc_now

RIG_FORMAT = "manisplat-rig-calibration"
VERSION = 1


def _world_text(world: str) -> str:
    if world == BASES_WORLD:
        return "midpoint of the arm bases, z their mean up axis, x their mean forward axis (Cobot Magic)"
    return f"the frame of {world}"


def build_rig(solved: RigSolve, board: dict) -> dict[str, Any]:
    """The ``rig.json`` object of a :class:`~.rig.RigSolve`."""
    cameras: dict[str, Any] = {}
    for name, c in solved.cameras.items():
        entry: dict[str, Any] = {**c.camera.to_dict(), "mount": c.mount, "T_mount_cam": c.T_mount_cam.tolist()}
        if c.hand_eye is not None:
            entry["method"] = "eye-in-hand, board still in the world"
            entry["residuals"] = c.hand_eye.residual_stats()
            entry["uncertainty"] = c.hand_eye.uncertainty()
            entry["start"] = c.hand_eye.start
        else:
            s = c.static
            entry["method"] = "PnP of the still board over every view"
            entry["residuals"] = {"rms_px": s.rms_px, "max_px": s.max_px, "views_used": s.views,
                                  "single_view_spread_deg": s.spread_deg, "single_view_spread_mm": s.spread_mm}
        cameras[name] = entry
    arms = {arm: {"T_world_base": T.tolist(), "from_camera": solved.base_from[arm],
                  "uncertainty": {k: solved.cameras[solved.base_from[arm]].hand_eye.uncertainty()[k]
                                  for k in ("other_rot_std_deg", "other_trans_std_mm")}}
            for arm, T in solved.T_world_base.items()}
    rig = {"format": RIG_FORMAT, "version": VERSION, "date": utc_now(), "world": solved.world,
           "world_frame": _world_text(solved.world), "T_world_board": solved.T_world_board.tolist(),
           "cameras": cameras, "arms": arms, "board": board, "corner_offset_px": solved.corner_offset_px,
           "opencv": cv2.__version__, "episode": str(solved.episode),
           "rejected_frames": {n: {str(k): v for k, v in c.rejected.items()} for n, c in solved.cameras.items()}}
    _finite_tree(rig, "rig")
    return rig


def save_rig(path: str | Path, rig: dict[str, Any]) -> None:
    """Write ``rig.json`` atomically."""
    atomic_write_bytes(Path(path), (json.dumps(rig, indent=1) + "\n").encode("utf-8"))


def is_rig(cal: Any) -> bool:
    """Whether a loaded calibration file is a ``rig.json``."""
    return isinstance(cal, dict) and cal.get("format") == RIG_FORMAT


def check_rig(path: str | Path, rig: dict[str, Any]) -> dict[str, Any]:
    """``rig`` checked field by field; errors name the file and the field."""
    for group, needed in (("cameras", ("K", "dist", "width", "height", "mount", "T_mount_cam")), ("arms", ("T_world_base",))):
        entries = rig.get(group)
        if not isinstance(entries, dict):
            raise InputError(f"{path}: {group} must be an object")
        for name, entry in entries.items():
            missing = [k for k in needed if not isinstance(entry, dict) or k not in entry]
            if missing:
                raise InputError(f"{path}: {group}.{name} is missing {missing}")
            key = "T_mount_cam" if group == "cameras" else "T_world_base"
            if not is_rigid(np.asarray(entry[key], dtype=np.float64)):
                raise InputError(f"{path}: {group}.{name}.{key} is not a rigid 4x4 transform")
            if group == "cameras":
                try:
                    CameraModel(K=entry["K"], dist=entry["dist"], width=entry["width"], height=entry["height"])
                except CalibrationError as exc:
                    raise InputError(f"{path}: cameras.{name}: {exc}") from None
    return rig


def load_rig(path: str | Path) -> dict[str, Any]:
    """Read and check a ``rig.json``."""
    rig = read_json(Path(path), "rig calibration file")
    if not is_rig(rig):
        raise InputError(f"{path}: not a {RIG_FORMAT} file")
    return check_rig(path, rig)


def apply_rig(rig: dict[str, Any], episode: str | Path, *, source: str = "") -> list[str]:
    """Write ``rig`` into the version 2 ``EPISODE/episode.json`` atomically, keeping every other field.

    Sets every camera's ``K``, ``dist``, ``mount``, ``T_mount_cam`` and every arm's ``T_world_base``,
    with ``calibration`` = {date, file} on each. Refuses a version 1 episode, a camera of another
    image size, and an episode whose arms or world cameras the rig does not cover (they would stay
    in another world). Returns what was left as recorded (wrist cameras the rig lacks) and what
    of the rig the episode lacks, as messages.
    """
    path = Path(episode) / "episode.json"
    raw = read_meta_json(path)
    if not isinstance(raw.get("arms"), dict) or not isinstance(raw.get("cameras"), dict):
        raise InputError(f"{path}: version 1 (one camera): apply a calibration.json from `manisplat-calibrate "
                         "solve`; a rig calibration is for version 2 episodes")
    arms, cameras = raw["arms"], raw["cameras"]
    in_world = [c for c, cam in cameras.items() if c not in rig["cameras"] and cam.get("mount") == WORLD_MOUNT]
    uncovered = [f"arm {a}" for a in arms if a not in rig["arms"]] + [f"camera {c}" for c in in_world]
    if uncovered:
        raise InputError(f"{path}: the rig calibration does not cover {', '.join(uncovered)}: they would stay in "
                         "another world frame; calibrate the rig with them")
    stamp = {"date": rig.get("date"), "file": source}
    notes = [f"camera {c} kept as recorded (not in the rig)" for c in cameras if c not in rig["cameras"]]
    notes += [f"{what} {n} of the rig is not in the episode" for what, group, have in
              (("camera", rig["cameras"], cameras), ("arm", rig["arms"], arms)) for n in group if n not in have]
    for name, cal in rig["cameras"].items():
        cam = cameras.get(name)
        if cam is None:
            continue
        if (cam.get("width"), cam.get("height")) != (cal["width"], cal["height"]):
            raise InputError(f"{path}: camera {name} images are {cam.get('width')}x{cam.get('height')} but the rig "
                             f"calibrated it at {cal['width']}x{cal['height']}; calibrate at the recording size")
        cam.update({k: cal[k] for k in ("K", "dist", "mount", "T_mount_cam")}, calibration=stamp)
    for name, cal in rig["arms"].items():
        if name in arms:
            arms[name].update(T_world_base=cal["T_world_base"], calibration=stamp)
    write_calibrated_meta(path, raw)
    return notes
