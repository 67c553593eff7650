"""The built-in sample episode: valid, and its images agree with its ground truth."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from manisplat.episode import validate
from manisplat.episode.synthetic import BOX_LABEL, write_sample_episode
from manisplat.robot import load_robot


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    return write_sample_episode(tmp_path_factory.mktemp("sample") / "ep", frames=24, width=96, height=72)


def test_sample_is_a_valid_complete_episode(sample):
    report = validate(sample)
    assert report.ok, str(report)
    assert not report.problems


def test_ground_truth_matches_recorded_joints(sample):
    import csv

    gt = np.load(sample / "gt.npz")
    with open(sample / "frames.csv") as fh:
        rows = list(csv.DictReader(fh))
    q = np.array([[float(r[f"q{i}"]) for i in range(1, 7)] for r in rows])
    robot = load_robot("builtin:agilex_piper")
    assert np.allclose(robot.tcp_pose(torch.tensor(q)).numpy(), gt["T_base_tcp"], atol=1e-12)
    assert np.array_equal(gt["t"], [float(r["t"]) for r in rows])
    # the box is carried rigidly: its pose in the TCP frame is constant while lifted
    carried = np.isin(gt["phase"], ["lift", "transfer", "lower"])
    rel = np.linalg.inv(gt["T_base_tcp"][carried]) @ gt["T_base_box"][carried]
    assert carried.sum() >= 3 and np.allclose(rel, rel[0], atol=1e-12)
    assert np.linalg.norm(gt["T_base_box"][-1, :2, 3] - gt["T_base_box"][0, :2, 3]) > 0.15  # it was moved


def test_images_agree_with_ground_truth(sample):
    import cv2

    gt = np.load(sample / "gt.npz")
    K, T_cam_base = gt["K"], gt["T_cam_base"]
    for k in (0, len(gt["t"]) - 1):  # box resting at the start and at the end
        center = T_cam_base @ gt["T_base_box"][k][:, 3]
        u, v = (K @ center[:3] / center[2])[:2]
        mask = cv2.imread(str(sample / "masks" / f"{k:06d}.png"), cv2.IMREAD_UNCHANGED)
        depth = cv2.imread(str(sample / "depth" / f"{k:06d}.png"), cv2.IMREAD_UNCHANGED) * 1e-4
        assert mask[int(round(v)), int(round(u))] == BOX_LABEL
        # the surface the centre's ray meets is at most half the box's diagonal nearer than the centre
        assert -0.001 < center[2] - depth[int(round(v)), int(round(u))] < 0.04 * 3 ** 0.5 / 2 + 0.001


def test_cli_sample_then_validate(tmp_path, capsys):
    from manisplat.episode.cli import main

    out = tmp_path / "cli_sample"
    assert main(["sample", str(out), "--frames", "12", "--width", "64", "--height", "48"]) == 0
    assert main(["validate", str(out)]) == 0
    assert main(["sample", str(out), "--frames", "12"]) == 2  # refuses to overwrite without --overwrite
    assert "overwrite" in capsys.readouterr().err
