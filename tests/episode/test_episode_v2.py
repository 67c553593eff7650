"""Format version 2 (named arms and cameras): reading, the one-arm view and its refusal."""

from __future__ import annotations

import json

import numpy as np
import pytest
from v2_factory import ARMS, CAMERAS, DEPTH_SCALE, T_HIGH, T_WORLD_BASE, frame_values, images, write_by_hand

from manisplat.episode import Episode, EpisodeFormatError, EpisodeMeta


def test_reads_every_arm_and_camera(tmp_path):
    ep = Episode.open(write_by_hand(tmp_path / "ep"))
    assert ep.meta.version == 2 and len(ep) == 5
    assert list(ep.arms) == list(ARMS) and list(ep.cameras) == list(CAMERAS)
    assert np.array_equal(ep.arms["right"].T_world_base, T_WORLD_BASE["right"])
    assert ep.cameras["cam_left_wrist"].mount == "left/link6" and ep.cameras["cam_high"].mount == "world"
    for arm in ARMS:
        table = ep.arm_frames(arm)
        rows = [frame_values(i) for i in range(5)]
        assert np.array_equal(table.q, [[r[f"{arm}.q{j}"] for j in range(1, 7)] for r in rows])
        assert np.array_equal(table.gripper, [r[f"{arm}.gripper"] for r in rows])
        assert np.array_equal(table.actions, [[r[f"{arm}.a{j}"] for j in range(1, 7)] + [r[f"{arm}.a_gripper"]]
                                              for r in rows])
        assert set(table.extra) == {"a1", "a2", "a3", "a4", "a5", "a6", "a_gripper", "seq"}
    for cam in CAMERAS:
        for i in range(5):
            assert np.array_equal(ep.rgb(i, cam), images(i, cam)["rgb"])
        assert ep.has_images("depth", cam) == (cam == "cam_high")
    assert np.allclose(ep.depth(3, "cam_high"), images(3, "cam_high")["depth"] * DEPTH_SCALE)
    assert ep.depth(3, "cam_left_wrist") is None and ep.mask(0, "cam_high") is None
    assert np.array_equal(ep.camera_times("cam_high"), np.arange(5) / 20.0)
    with pytest.raises(EpisodeFormatError, match="no camera 'cam_low'; cameras: cam_high, cam_left_wrist"):
        ep.rgb(0, "cam_low")


@pytest.mark.parametrize("use", ["camera", "frames", "robot", "rgb", "frame", "iter", "joints"])
def test_several_arms_refuse_the_one_arm_view(tmp_path, use):
    path = write_by_hand(tmp_path / "ep")
    ep = Episode.open(path)
    calls = {"camera": lambda: ep.camera, "frames": lambda: ep.frames, "robot": lambda: ep.meta.robot,
             "rgb": lambda: ep.rgb(0), "frame": lambda: ep.frame(0), "iter": lambda: next(iter(ep)),
             "joints": lambda: ep.joints()}
    what = "cameras cam_high, cam_left_wrist, cam_right_wrist" if use == "rgb" else "arms left, right"
    with pytest.raises(EpisodeFormatError, match=f"{path} has {what}: this tool reads one-arm episodes"):
        calls[use]()


def test_one_arm_one_camera_is_read_as_version_1(tmp_path):
    """A version 2 episode with one arm and one camera keeps the one-arm view working: the camera
    comes relative to the arm's base, as version 1 states it."""
    ep = Episode.open(write_by_hand(tmp_path / "ep", arms=("right",), cameras=("cam_high",)))
    assert ep.meta.version == 2 and ep.meta.robot.name == "right"
    assert np.array_equal(ep.frames.q, ep.arm_frames("right").q) and ep.frames.actions.shape == (5, 7)
    cam = ep.camera
    assert cam.mount == "base"
    T_base_cam = np.linalg.inv(np.array(T_WORLD_BASE["right"])) @ np.array(T_HIGH)
    assert np.allclose(cam.T_mount_cam, T_base_cam, atol=1e-15) and cam.T_mount_cam[1, 3] == 0.3
    assert np.array_equal(ep.rgb(2), images(2, "cam_high")["rgb"]) and ep.has_depth and not ep.has_masks
    assert ep.frame(1).q.shape == (6,) and len(list(ep)) == 5
    wrist = Episode.open(write_by_hand(tmp_path / "w", arms=("left",), cameras=("cam_left_wrist",)))
    assert wrist.camera.mount == "link6" and wrist.cameras["cam_left_wrist"].mount == "left/link6"


def test_meta_rules(tmp_path):
    path = write_by_hand(tmp_path / "ep")
    raw = json.loads((path / "episode.json").read_text())
    assert EpisodeMeta.from_dict(json.loads(json.dumps(raw))).to_dict() == raw  # round trip, unknown keys kept
    bad = json.loads(json.dumps(raw))
    bad["cameras"]["cam_left_wrist"]["mount"] = "middle/link6"
    bad["cameras"]["cam_high"]["mount"] = "base"
    bad["arms"]["left"]["T_world_base"] = np.diag([1.0, 1.0, -1.0, 1.0]).tolist()
    bad["version"] = 1
    del bad["cameras"]["cam_right_wrist"]["K"]
    with pytest.raises(EpisodeFormatError) as info:
        EpisodeMeta.from_dict(bad)
    for text in ("cameras.cam_left_wrist.mount 'middle/link6' names the arm 'middle', which is not in arms (left, "
                 "right)", "cameras.cam_high.mount must be 'world' or '<arm>/<link>'",
                 "arms.left.T_world_base is not a rigid transform", "version must be 2 for an episode.json with arms",
                 "cameras.cam_right_wrist.K is missing"):
        assert text in str(info.value)
    bad = json.loads(json.dumps(raw))
    bad["arms"]["le.ft"] = bad["arms"].pop("left")
    with pytest.raises(EpisodeFormatError, match="arm name 'le.ft' must be"):
        EpisodeMeta.from_dict(bad)
    bad = json.loads(json.dumps(raw))
    bad["cameras"]["right"] = bad["cameras"].pop("cam_high")
    with pytest.raises(EpisodeFormatError, match="'right' names both an arm and a camera"):
        EpisodeMeta.from_dict(bad)
