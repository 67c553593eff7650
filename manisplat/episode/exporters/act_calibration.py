"""The calibration sidecar of an ACT HDF5 export (``episode_<N>.calib.json``): what the HDF5 file
cannot hold and ``import-act --calib`` needs to read it back whole (``docs/cobot-magic.md``, the
calibration file): the rate, each camera's intrinsics, size, mount and ``T_mount_cam``, each arm's
``T_world_base``, robot description and columns of ``qpos`` / ``action``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from manisplat.episode.importers.cobot_magic import CALIBRATION_CAMERA_KEYS
from manisplat.episode.reader import Episode

CALIBRATION_SUFFIX = ".calib.json"


def _description(ep: Episode, description: str) -> dict[str, str]:
    """``description`` for a ``builtin:`` model, else ``urdf``: the file's absolute path (an
    episode stores it relative to its folder)."""
    if description.startswith("builtin:"):
        return {"description": description}
    return {"urdf": str((ep.path / description).resolve())}


def act_calibration(ep: Episode, keys: dict[str, str], fps: float) -> dict[str, Any]:
    """The sidecar of ``ep`` exported at ``fps`` Hz with its cameras' images under ``keys``
    (camera -> dataset name): cameras by dataset name, arms in the episode's order, arm ``k``'s
    joints in columns ``7k..7k+5`` and its gripper in ``7k+6`` (the exporter's layout)."""
    cameras = {}
    for camera, key in keys.items():
        raw = ep.cameras[camera].to_v2_dict()
        cameras[key] = {k: raw[k] for k in CALIBRATION_CAMERA_KEYS if k in raw}
    arms = {}
    for k, (name, arm) in enumerate(ep.arms.items()):
        raw = arm.to_v2_dict()
        arms[name] = {"model": raw["model"], "joint_names": raw["joint_names"], **_description(ep, raw["description"]),
                      "T_world_base": raw["T_world_base"], "qpos_columns": list(range(7 * k, 7 * k + 6)),
                      "gripper_column": 7 * k + 6}
    return {"fps": float(fps), "cameras": cameras, "arms": arms}


def calibration_path(hdf5: Path) -> Path:
    """``episode_3.hdf5`` -> ``episode_3.calib.json`` (as Cobot Magic sidecars are named)."""
    return hdf5.with_name(hdf5.stem + CALIBRATION_SUFFIX)
