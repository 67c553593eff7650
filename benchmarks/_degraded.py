"""Shared by the degraded-recording benchmarks: oak-preset copies of the shared episodes (made
with ../shared/tools/degrade/degrade_episode.py, whose truth stays beside the copy) and one
``manisplat-reconstruct`` run read back as a table row."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from benchmarks._harness import BenchContext
from manisplat.episode import Episode
from manisplat.reconstruct.extrinsic import pose_difference

SOURCES = ("sim_pick_place_small", "sim_reach_only_small")


def robot_of(episode: Path) -> str:
    """The episode's robot description as an absolute path (copies live elsewhere)."""
    description = Episode.open(episode).meta.robot.description
    if description.startswith("builtin:"):
        return description
    return str((episode / description).resolve())


def degraded(ctx: BenchContext, source: str, seed: int, root: Path) -> tuple[Path, dict]:
    """An oak-preset copy of shared/data/``source`` under ``root`` and what the tool applied."""
    src = ctx.require_shared("data", source)
    tool = ctx.require_shared("tools", "degrade", "degrade_episode.py")
    dst = root / f"{source}_oak{seed}"
    subprocess.run([sys.executable, str(tool), str(src), str(dst), "--preset", "oak", "--seed", str(seed)],
                   check=True, capture_output=True)
    return dst, json.loads(dst.with_name(dst.name + ".degrade.json").read_text())


def reconstruct(episode: Path, out: Path, iters: int, robot: str, *extra: str) -> Path:
    """The output folder of one ``manisplat-reconstruct`` run."""
    from manisplat.reconstruct.cli import main

    assert main([str(episode), "--out", str(out), "--iters", str(iters), "--robot", robot, "-q", *extra]) == 0
    return out


def row(twin: Path, T_true: np.ndarray, T_recorded: np.ndarray, true_gain: list[float] | None = None) -> dict:
    """Held-out PSNR/SSIM per region (exposure interpolated, and colour fitted on static pixels),
    the object's pose error by both definitions, the extrinsic error before and after, and (with
    ``true_gain``, degrade_episode.py's per-frame exposure) how the fitted gains follow it."""
    metrics = json.loads((twin / "metrics.json").read_text())
    camera = json.loads((twin / "camera_refined.json").read_text())
    out = {"wall_s": metrics["wall_s"]}
    for key in ("psnr", "psnr_full_colour", "psnr_colour_fitted", "ssim"):
        for region, value in (metrics.get(key) or {}).items():
            out[f"{key}_{region}"] = value
    for name, err in metrics.get("pose", {}).items():
        out["object"], out["et_cm"], out["er_deg"] = name, err["et_cm"], err["er_deg"]
        anchored = metrics.get("pose_anchored", {}).get(name)
        if anchored:
            out["anchored_et_cm"], out["anchored_er_deg"] = anchored["et_cm"], anchored["er_deg"]
    out["extrinsic_error_before_deg"], out["extrinsic_error_before_mm"] = pose_difference(T_true, T_recorded)
    used = np.asarray(camera["T_mount_cam"])
    out["extrinsic_error_after_deg"], out["extrinsic_error_after_mm"] = pose_difference(T_true, used)
    depth = camera["correction"]["robot_depth"]
    if depth:
        out["correction_sigma_deg"], out["correction_sigma_mm"] = depth["sigma_rotation_deg"], depth["sigma_translation_mm"]
        out["time_offset_ms"] = depth["time_offset_ms"]
    if true_gain is not None and (twin / "exposure.csv").is_file():
        fitted = np.loadtxt(twin / "exposure.csv", delimiter=",", skiprows=1)
        train = fitted[:, 1] == 0
        # brightness (channel mean) against the true auto-exposure gain; white balance is not in the record
        out["exposure_corr_train"] = float(np.corrcoef(fitted[train, 2:].mean(1), np.asarray(true_gain)[train])[0, 1])
    return out
