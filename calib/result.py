"""``calibration.json``: what ``manisplat-calibrate solve`` writes and ``apply`` puts into episodes.

Fields: ``format`` ("manisplat-calibration"), ``version`` (1), ``date`` (UTC), ``K`` (3x3),
``dist`` (OpenCV order), ``width``, ``height``, ``mount`` ("base" or a link), ``T_mount_cam``
(4x4 camera-to-mount, metres), ``latency_s`` (camera timestamp minus true exposure time, s, or
null) and ``latency_std_s``, ``residuals`` (corner reprojection statistics, px, and per view),
``uncertainty`` (1-sigma), plus provenance: ``board``, ``link``, ``T_link_board`` or
``T_base_board``, ``closed_forms``, ``motion``, ``corner_offset_px``, ``opencv``, ``episode``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from manisplat.calib.camera import CameraModel
from manisplat.calib.errors import CalibrationError, InputError, read_json
from manisplat.calib.handeye import is_eye_to_hand
from manisplat.calib.poses import is_rigid
from manisplat.episode.fsio import atomic_write_bytes
from manisplat.episode.meta import EpisodeMeta, read_meta_json, utc_now

FORMAT = "manisplat-calibration"
VERSION = 1


def _finite_tree(x: Any, where: str = "calibration") -> None:
    """Raise when any number in a JSON-ready tree is NaN or infinite (no NaN leaves)."""
    if isinstance(x, float) and not math.isfinite(x):
        raise CalibrationError(f"{where} is not finite ({x})")
    if isinstance(x, dict):
        for k, v in x.items():
            _finite_tree(v, f"{where}.{k}")
    elif isinstance(x, list):
        for k, v in enumerate(x):
            _finite_tree(v, f"{where}[{k}]")


def build_calibration(solved, board: dict, latency: dict | None = None) -> dict[str, Any]:
    """The ``calibration.json`` object of an :class:`~.episode_solve.EpisodeSolve`."""
    r = solved.result
    cal: dict[str, Any] = {
        "format": FORMAT, "version": VERSION, "date": utc_now(),
        **solved.camera.to_dict(),
        "mount": r.mount, "T_mount_cam": r.T_mount_cam.tolist(),
        "latency_s": None if latency is None else latency["latency_s"],
        "latency_std_s": None if latency is None else latency["latency_std_s"],
        "residuals": {**r.residual_stats(), "per_view": r.per_view()},
        "uncertainty": r.uncertainty(),
        "link": r.link,
        ("T_link_board" if is_eye_to_hand(r.mount) else "T_base_board"): r.T_other.tolist(),
        "board": board,
        "start": r.start,
        "closed_forms": r.closed_forms,
        "motion": {**r.diversity.to_dict(), "distinct_poses": r.poses},
        "rejected_frames": {str(k): v for k, v in solved.rejected.items()},
        "notes": r.notes,
        "corner_offset_px": solved.corner_offset_px,
        "opencv": cv2.__version__,
        "episode": str(solved.episode),
    }
    if latency is not None:
        cal["latency"] = latency
    _finite_tree({k: v for k, v in cal.items() if k != "closed_forms"})
    return cal


def save_calibration(path: str | Path, cal: dict[str, Any]) -> None:
    """Write ``calibration.json`` atomically."""
    atomic_write_bytes(Path(path), (json.dumps(cal, indent=1) + "\n").encode("utf-8"))


def load_calibration(path: str | Path) -> dict[str, Any]:
    """Read and check a ``calibration.json``; errors name the file and the field."""
    path = Path(path)
    cal = read_json(path, "calibration file")
    if not isinstance(cal, dict) or cal.get("format") != FORMAT:
        raise InputError(f"{path}: not a {FORMAT} file")
    missing = [k for k in ("K", "dist", "width", "height", "mount", "T_mount_cam") if k not in cal]
    if missing:
        raise InputError(f"{path}: missing field(s) {missing}")
    try:
        CameraModel(K=cal["K"], dist=cal["dist"], width=cal["width"], height=cal["height"])
    except CalibrationError as exc:
        raise InputError(f"{path}: {exc}") from None
    if cal["T_mount_cam"] is not None and not is_rigid(np.asarray(cal["T_mount_cam"], dtype=np.float64)):
        raise InputError(f"{path}: T_mount_cam is not a rigid 4x4 transform")
    lat = cal.get("latency_s")
    if lat is not None and not (isinstance(lat, (int, float)) and math.isfinite(lat)):
        raise InputError(f"{path}: latency_s must be a finite number or null")
    return cal


def apply_calibration(cal: dict[str, Any], episode: str | Path, *, source: str = "") -> dict[str, Any]:
    """Write ``cal`` into ``EPISODE/episode.json`` atomically, keeping every other field.

    Sets ``camera.K``, ``dist``, ``mount``, ``T_mount_cam`` and ``camera.latency_s`` (when
    known) and records ``camera.calibration`` = {date, file}. Refuses an episode whose image
    size differs from the calibration's. Returns the new camera object.
    """
    path = Path(episode) / "episode.json"
    raw = read_meta_json(path)
    cam = raw.get("camera")
    if isinstance(raw.get("cameras"), dict):
        raise InputError(f"{path}: version 2 (cameras {', '.join(raw['cameras'])}): a calibration.json calibrates "
                         "one camera of a one-arm episode; calibrate the rig with `manisplat-calibrate solve-rig` "
                         "and apply its rig.json")
    if not isinstance(cam, dict):
        raise InputError(f"{path}: has no camera object")
    if (cam.get("width"), cam.get("height")) != (cal["width"], cal["height"]):
        raise InputError(f"{path}: images are {cam.get('width')}x{cam.get('height')} but the calibration is for "
                               f"{cal['width']}x{cal['height']}; calibrate at the recording size")
    cam.update({"K": cal["K"], "dist": cal["dist"], "mount": cal["mount"], "T_mount_cam": cal["T_mount_cam"]})
    if cal.get("latency_s") is not None:
        cam["latency_s"] = cal["latency_s"]
    cam["calibration"] = {"date": cal.get("date"), "file": source}
    write_calibrated_meta(path, raw)
    return cam


def write_calibrated_meta(path: Path, raw: dict[str, Any]) -> None:
    """Write the calibrated ``episode.json`` ``raw`` to ``path`` atomically, once it parses as a
    valid episode (else :class:`CalibrationError`, and the file stays as it was)."""
    try:
        EpisodeMeta.from_dict(raw)
    except ValueError as exc:
        raise CalibrationError(f"{path}: the calibrated episode.json would be invalid: {exc}") from None
    atomic_write_bytes(path, (json.dumps(raw, indent=1) + "\n").encode("utf-8"))
