"""The examples a new user runs first keep working."""

from __future__ import annotations

import runpy
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_sample_overlay_example(tmp_path):
    module = runpy.run_path(str(ROOT / "examples" / "sample_overlay.py"))
    path = module["main"](str(tmp_path))
    sheet = cv2.imread(str(path))
    assert sheet is not None and sheet.shape[1] > sheet.shape[0]


def test_fit_image_example(tmp_path):
    from manisplat.splat import load_ply

    module = runpy.run_path(str(ROOT / "examples" / "fit_image.py"))
    result = module["main"](str(tmp_path), steps=120)
    assert result["psnr"] > 25.0 and result["gaussians"] > 2000  # densified and fitting
    assert len(load_ply(tmp_path / "fit.ply")["means"]) == result["gaussians"]


def _centroid(alpha) -> np.ndarray:
    v, u = np.nonzero(np.ones_like(alpha))
    w = alpha.ravel()
    return np.array([(u * w).sum(), (v * w).sum()]) / w.sum()


def test_twin_new_poses_example(tmp_path):
    from manisplat.episode import Episode

    module = runpy.run_path(str(ROOT / "examples" / "twin_new_poses.py"))
    r = module["main"](str(tmp_path), iters=200, frames=24, width=80, height=60)
    twin, recorded, new = (r[k].numpy() for k in ("twin", "recorded", "new"))
    assert np.isfinite(new).all()
    assert 10 * np.log10(1 / ((twin - recorded) ** 2).mean()) > 22.0  # the twin reproduces the frame
    assert np.abs(new - twin).max(-1).mean() > 0.01  # the arm and the box moved
    # the box is drawn where its new pose projects: its alpha centroid moves by the projected shift
    cam = Episode.open(tmp_path / "episode").camera
    T_cam_base = np.linalg.inv(cam.T_mount_cam)

    def project(p: np.ndarray) -> np.ndarray:
        x = cam.K @ (T_cam_base[:3, :3] @ p + T_cam_base[:3, 3])
        return x[:2] / x[2]

    before, after = r["T_base_box"].numpy()[:3, 3], r["T_base_box_new"].numpy()[:3, 3]
    expected = project(after) - project(before)
    moved = _centroid(r["box_alpha_new"].numpy()) - _centroid(r["box_alpha"].numpy())
    assert np.linalg.norm(expected) > 3.0 and np.linalg.norm(moved - expected) < 1.0, (moved, expected)
    assert cv2.imread(str(tmp_path / "new_poses.png")).shape[1] == 3 * 80


@pytest.mark.parametrize("example", ["sample_overlay.py", "fit_image.py", "twin_new_poses.py", "augment_for_lerobot.py"])
def test_an_example_never_writes_into_a_used_folder(tmp_path, example):
    from manisplat.episode.synthetic import write_sample_episode

    users = write_sample_episode(tmp_path / "my_episode", frames=8, width=32, height=24)
    before = {p: p.read_bytes() for p in users.rglob("*") if p.is_file()}
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / example), str(users)], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 1 and "not a new or empty folder" in proc.stderr and "Traceback" not in proc.stderr
    assert {p: p.read_bytes() for p in users.rglob("*") if p.is_file()} == before


def test_augment_for_lerobot_example(tmp_path, capsys):
    import json

    from manisplat.episode.synthetic import write_sample_episode

    episode = write_sample_episode(tmp_path / "recording", frames=32, width=64, height=48)
    module = runpy.run_path(str(ROOT / "examples" / "augment_for_lerobot.py"))
    result = module["main"](str(tmp_path / "out"), episode=str(episode), n=2, iters=5)
    info = json.loads((result["dataset"] / "meta" / "info.json").read_text())
    assert result["episodes"] == info["total_episodes"] == 3  # the recording and two new ones
    provenance = json.loads((result["dataset"] / "meta" / "augmentation.json").read_text())
    assert sum(e["augmented"] for e in provenance["episodes"]) == 2
    report = json.loads((tmp_path / "out" / "augmented" / "augment_report.json").read_text())
    assert report["start_range_deg"] == 10.0  # the recommended scattered start (docs/training-policies.md)
    assert "lerobot-train" in capsys.readouterr().out and f"--dataset.root={result['dataset']}" in result["train_command"]
