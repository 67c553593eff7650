"""The built-in two-arm sample episode (format version 2): valid, and each arm moves its own box."""

from __future__ import annotations

import numpy as np
import pytest

from manisplat.episode import Episode, validate
from manisplat.episode.synthetic_arms import write_two_arm_sample_episode

ARMS = ("left", "right")


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    return write_two_arm_sample_episode(tmp_path_factory.mktemp("two_arm") / "ep")


def test_the_sample_is_a_valid_two_arm_episode(sample):
    report = validate(sample)
    assert report.ok and not report.warnings, str(report)
    ep = Episode.open(sample)
    assert ep.meta.version == 2 and len(ep) == 40
    assert list(ep.arms) == list(ARMS) and list(ep.cameras) == ["cam_high"]
    assert ep.cameras["cam_high"].mount == "world"
    assert ep.has_images("depth", "cam_high") and ep.has_images("masks", "cam_high")
    assert ep.meta.objects == ["box_left", "box_right"]
    labels = set(ep.meta.labels.values())
    assert {"robot/left/link6", "robot/right/link6", "object/box_left", "object/box_right", "table"} <= labels
    assert np.allclose(ep.arms["left"].T_world_base[:3, 3], [0, 0.3, 0])


@pytest.mark.parametrize("arm", ARMS)
def test_each_arm_carries_its_own_box(sample, arm):
    gt = Episode.open(sample).gt()
    box, tcp = gt[f"T_world_box_{arm}"], gt[f"T_world_tcp_{arm}"]
    other = gt[f"T_world_tcp_{'right' if arm == 'left' else 'left'}"]
    height = box[:, 2, 3] - box[0, 2, 3]
    carried = np.flatnonzero(height > 0.01)
    assert abs(height[-1]) < 1e-6 and 0.1 < carried.min() / len(box) and carried.max() / len(box) < 0.9
    assert height.max() > 0.08
    assert np.linalg.norm(box[-1, :3, 3] - box[0, :3, 3]) >= 0.08
    relative = np.linalg.inv(tcp[carried]) @ box[carried]  # rigid in its own gripper
    assert np.allclose(relative, relative[0], atol=1e-9) and np.linalg.norm(relative[0, :3, 3]) < 0.01
    assert np.linalg.norm(other[carried, :3, 3] - box[carried, :3, 3], axis=1).min() > 0.1


def test_wrist_cameras_ride_on_link6_and_see_their_own_box_at_the_grasp(tmp_path):
    path = write_two_arm_sample_episode(tmp_path / "ep", duration=2.0, fps=5.0, wrist_cameras=True)
    report = validate(path)
    assert report.ok and not report.warnings, str(report)
    ep = Episode.open(path)
    assert list(ep.cameras) == ["cam_high", "cam_left_wrist", "cam_right_wrist"]
    gt = ep.gt()
    for arm in ARMS:
        cam = ep.cameras[f"cam_{arm}_wrist"]
        assert cam.mount == f"{arm}/link6" and ep.has_images("masks", cam.name)
        box = gt[f"T_world_box_{arm}"]
        grasp = np.flatnonzero(np.any(box != box[0], axis=(1, 2)))[0] - 1  # the last frame before it rides
        label = next(v for v, name in ep.meta.labels.items() if name == f"object/box_{arm}")
        mask = ep.mask(grasp, cam.name)
        assert (mask == label).mean() > 0.05  # about 10 %; 1 % when the gripper is high above it
        assert gt[f"T_world_cam_{cam.name}"].shape == (len(ep), 4, 4)
