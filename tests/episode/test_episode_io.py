"""Writer -> reader round trip, lazy reading, and the writer's input checks."""

from __future__ import annotations

import json
import logging

import cv2
import numpy as np
import pytest
from episode_factory import (DEPTH_SCALE, EXTRA_COLUMNS, FPS, H, LABELS, W, frame_data, joint_data, open_writer,
                             write_episode)

from manisplat.episode import ACTION_COLUMNS, Episode, EpisodeFormatError, validate


def test_round_trip_is_exact(episode):
    ep = Episode.open(episode)
    assert len(ep) == 8 and ep.meta.complete and ep.meta.frame_count == 8
    assert ep.has_depth and ep.has_masks
    assert ep.meta.labels == LABELS and ep.meta.objects == ["box"] and ep.meta.extra == {"task": "test"}
    assert ep.meta.depth_scale == DEPTH_SCALE and ep.meta.fps == FPS and ep.meta.source == "recorder"
    assert ep.camera.width == W and ep.camera.height == H
    assert list(ep.frames.extra) == list(EXTRA_COLUMNS)
    for i in range(8):
        d = frame_data(i)
        assert ep.frames.index[i] == i
        assert ep.frames.t[i] == d["t"]  # float64 exactly
        assert np.array_equal(ep.frames.q[i], d["q"]) and ep.frames.gripper[i] == d["gripper"]
        assert ep.frames.actions[i].tolist() == [d["extra"][c] for c in ACTION_COLUMNS]
        frame = ep.frame(i)
        assert np.array_equal(frame.rgb, d["rgb"]) and frame.rgb.dtype == np.uint8
        assert np.array_equal(frame.mask, d["mask"])
        assert frame.depth.dtype == np.float32 and frame.depth[0, 0] == 0.0  # NaN stored as invalid
        assert np.allclose(frame.depth[1:], d["depth"][1:], atol=DEPTH_SCALE / 2 + 1e-7)
        assert frame.extra["seq"] == 100 + i
    assert ep.frames.q.dtype == np.float64 and ep.frames.index.dtype == np.int64
    assert [f.index for f in ep] == list(range(8))
    joints = ep.joints()
    assert len(joints) == 32 and joints is ep.joints()
    for k in (0, 31):
        d = joint_data(k)
        assert joints.t[k] == d["t"] and np.array_equal(joints.q[k], d["q"]) and joints.gripper[k] == d["gripper"]
        assert joints.extra["effort1"][k] == d["extra"]["effort1"]
    assert validate(episode).ok


def test_rgb_files_are_bgr_on_disk(episode):
    on_disk = cv2.imread(str(episode / "rgb" / "000002.png"))
    assert np.array_equal(on_disk[..., ::-1], frame_data(2)["rgb"])


def test_awkward_floats_round_trip(tmp_path):
    values = [0.1 + 0.2, 1e-300, -2.0 / 3.0, np.pi, np.nextafter(1.0, 2.0), 5e-324]
    with open_writer(tmp_path / "ep", extra_frame_columns=(), joint_columns=()) as w:
        d = frame_data(0, depth=False, masks=False)
        w.add_frame(values[0], values, 1e-17, d["rgb"])
    ep = Episode.open(tmp_path / "ep")
    assert ep.frames.t[0] == values[0] and ep.frames.q[0].tolist() == values and ep.frames.gripper[0] == 1e-17
    assert ep.depth(0) is None and ep.mask(0) is None and not ep.has_depth and ep.joints() is None
    assert ep.frames.actions is None and ep.gt() is None


def test_jpg_episode(tmp_path):
    path = write_episode(tmp_path / "ep", frames=3, image_format="jpg", depth=False, masks=False)
    assert sorted(p.name for p in (path / "rgb").iterdir()) == ["000000.jpg", "000001.jpg", "000002.jpg"]
    ep = Episode.open(path)
    assert ep.rgb(1).shape == (H, W, 3)
    assert validate(path).ok


def test_images_are_read_lazily(episode):
    (episode / "rgb" / "000003.png").unlink()
    (episode / "depth" / "000005.png").write_bytes(b"")
    ep = Episode.open(episode)  # tables only: no image is touched
    assert len(ep) == 8 and ep.rgb(2).shape == (H, W, 3)
    with pytest.raises(EpisodeFormatError, match="no image for frame 3"):
        ep.rgb(3)
    with pytest.raises(EpisodeFormatError, match=r"000005.png: cannot decode"):
        ep.depth(5)
    frames = iter(ep)
    assert [next(frames).index for _ in range(3)] == [0, 1, 2]
    with pytest.raises(EpisodeFormatError):
        next(frames)
    with pytest.raises(IndexError, match="frame 8 out of range"):
        ep.frame(8)


def test_gt(episode):
    np.savez(episode / "gt.npz", t=np.arange(8) / FPS, K=np.eye(3))
    gt = Episode.open(episode).gt()
    assert set(gt) == {"t", "K"} and gt["K"].shape == (3, 3)


def test_incomplete_episode_reads_with_warning(tmp_path, caplog):
    writer = open_writer(tmp_path / "ep")
    for i in range(3):
        writer.add_frame(**frame_data(i))
    writer.sync()
    with open(tmp_path / "ep" / "frames.csv", "a") as f:
        f.write("3,0.3,0.1,0.2")  # a torn last line
    with caplog.at_level(logging.WARNING):
        ep = Episode.open(tmp_path / "ep")
    assert len(ep) == 3 and not ep.meta.complete
    assert "recover" in caplog.text and "torn last line" in caplog.text


def test_exception_in_with_block_leaves_incomplete(tmp_path):
    with pytest.raises(RuntimeError, match="stop"):
        with open_writer(tmp_path / "ep") as writer:
            writer.add_frame(**frame_data(0))
            raise RuntimeError("stop")
    assert writer.closed
    meta = json.loads((tmp_path / "ep" / "episode.json").read_text())
    assert meta["complete"] is False and meta["frame_count"] == 0
    assert len(Episode.open(tmp_path / "ep")) == 1


def test_episode_json_is_written_first(tmp_path):
    writer = open_writer(tmp_path / "ep")
    meta = json.loads((tmp_path / "ep" / "episode.json").read_text())
    assert meta["complete"] is False
    assert (tmp_path / "ep" / "frames.csv").read_text().startswith("index,t,q1,q2,q3,q4,q5,q6,gripper,seq,a1")
    writer.close()
    writer.close()  # idempotent
    assert json.loads((tmp_path / "ep" / "episode.json").read_text())["complete"] is True


@pytest.mark.parametrize("change, message", [
    (dict(rgb=np.zeros((H, W), np.uint8)), r"rgb must be \(24, 32, 3\) uint8"),
    (dict(rgb=np.zeros((H, W, 3), np.float32)), r"got \(24, 32, 3\) float32"),
    (dict(q=[0.0] * 7), r"q must hold 6 joint angles .* shape \(7,\)"),
    (dict(q=[0.0, 0.0, np.nan, 0.0, 0.0, 0.0]), "q must be finite"),
    (dict(gripper=np.inf), "gripper must be finite"),
    (dict(t=float("nan")), "t must be finite"),
    (dict(t=0.0), "must be after the previous frame's t"),
    (dict(depth=np.zeros((H, W), np.int32)), "depth must be"),
    (dict(mask=np.zeros((H, W + 1), np.uint8)), "mask must be"),
    (dict(mask=None), "every frame must carry the same images"),
    (dict(extra={"seq": 1.0}), "missing"),
])
def test_writer_rejects_bad_input(tmp_path, change, message):
    with open_writer(tmp_path / "ep") as writer:
        writer.add_frame(**frame_data(0))
        with pytest.raises(ValueError, match=message):
            writer.add_frame(**{**frame_data(1), **change})
        assert writer.frame_count == 1


def test_writer_refuses_to_overwrite(tmp_path, episode):
    with pytest.raises(FileExistsError, match="an episode already exists"):
        open_writer(episode)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match="holds no episode"):
        open_writer(tmp_path / "other", overwrite=True)
    write_episode(episode, frames=2, overwrite=True)
    assert len(Episode.open(episode)) == 2


def test_writer_option_checks(tmp_path):
    with pytest.raises(ValueError, match="image_format"):
        open_writer(tmp_path / "a", image_format="bmp")
    with pytest.raises(ValueError, match="extra_frame_columns"):
        open_writer(tmp_path / "b", extra_frame_columns=("q1",))
    writer = open_writer(tmp_path / "c", depth_scale=None)
    with pytest.raises(ValueError, match="no depth_scale"):
        writer.add_frame(**frame_data(0))
    writer.close()
    with pytest.raises(ValueError, match="closed"):
        writer.add_frame(**frame_data(0))


def test_fsync_every_row(tmp_path):
    path = write_episode(tmp_path / "ep", frames=3, fsync_every=1)
    assert validate(path).ok
