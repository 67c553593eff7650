"""episode.json: typed metadata, its rules and round trip."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from manisplat.episode import CameraInfo, EpisodeFormatError, EpisodeMeta, load_meta, save_meta

RAW = {
    "format": "manisplat-episode", "version": 1, "complete": True, "source": "simulation",
    "created": "2026-11-21T12:00:00Z",
    "robot": {"model": "agilex_piper", "joint_names": [f"joint{i}" for i in range(1, 7)],
              "description": "builtin:agilex_piper", "urdf_sha": "abc"},
    "camera": {"name": "ego", "width": 320, "height": 240,
               "K": [[257.3, 0.0, 159.5], [0.0, 257.3, 119.5], [0.0, 0.0, 1.0]], "dist": [],
               "mount": "base", "T_mount_cam": [[0.0, -1.0, 0.0, 0.1], [1.0, 0.0, 0.0, 0.2],
                                                [0.0, 0.0, 1.0, 0.3], [0.0, 0.0, 0.0, 1.0]],
               "serial": "1234"},
    "fps": 16.0, "frame_count": 120, "depth_scale": 0.0001,
    "labels": {"0": "background", "10": "object/box"}, "objects": ["box"],
    "generator": {"tool": "gen.py"},
}


def test_round_trip_keeps_unknown_keys():
    meta = EpisodeMeta.from_dict(copy.deepcopy(RAW))
    assert meta.extra == {"generator": {"tool": "gen.py"}}
    assert meta.camera.extra == {"serial": "1234"} and meta.robot.extra == {"urdf_sha": "abc"}
    assert meta.camera.K.dtype == np.float64 and meta.camera.T_mount_cam.shape == (4, 4)
    assert meta.labels == {0: "background", 10: "object/box"}
    assert meta.to_dict() == RAW


def test_save_and_load(tmp_path):
    meta = EpisodeMeta.from_dict(copy.deepcopy(RAW))
    save_meta(tmp_path / "episode.json", meta)
    assert json.loads((tmp_path / "episode.json").read_text()) == RAW
    assert not list(tmp_path.glob("*.tmp"))
    assert load_meta(tmp_path / "episode.json").to_dict() == RAW


@pytest.mark.parametrize("K, expected", [
    ([[-5.0, 0, 159.5], [0, 257.3, 119.5], [0, 0, 1]], "camera.K must be 3x3 with positive fx, fy"),
    ([[257.3, 0, 159.5], [0, 257.3, 119.5]], "camera.K must be 3x3; got shape (2, 3)"),
    ([[float("nan"), 0, 159.5], [0, 257.3, 119.5], [0, 0, 1]], "camera.K must be finite"),
    ([[257.3, 0, 2000.0], [0, 257.3, 119.5], [0, 0, 1]], "principal point (cx, cy) = (2000, 119.5) is far outside"),
    ([[257.3, 0, 159.5], [0, 257.3, 119.5], [0, 0, 2]], "camera.K must have the form"),
])
def test_bad_K_is_named(tmp_path, K, expected):
    raw = copy.deepcopy(RAW)
    raw["camera"]["K"] = K
    (tmp_path / "episode.json").write_text(json.dumps(raw))
    with pytest.raises(EpisodeFormatError, match="episode.json") as info:
        load_meta(tmp_path / "episode.json")
    assert expected in str(info.value)


@pytest.mark.parametrize("T, expected", [
    (np.diag([1.0, 1.0, -1.0, 1.0]), "det R = -1"),
    (np.diag([1.0, 2.0, 1.0, 1.0]), "max |R^T R - I|"),
    (np.vstack([np.eye(4)[:3], [0.0, 0.0, 1.0, 1.0]]), "last row must be [0, 0, 0, 1]"),
])
def test_non_rigid_T_mount_cam(T, expected):
    raw = copy.deepcopy(RAW)
    raw["camera"]["T_mount_cam"] = T.tolist()
    with pytest.raises(EpisodeFormatError, match="camera.T_mount_cam") as info:
        EpisodeMeta.from_dict(raw)
    assert expected in str(info.value)


def test_every_problem_is_listed():
    raw = copy.deepcopy(RAW)
    raw.update(format="other", version=2, fps=-1)
    raw["camera"]["width"] = 0
    del raw["frame_count"]
    with pytest.raises(EpisodeFormatError) as info:
        EpisodeMeta.from_dict(raw)
    for text in ("format must be", "version must be 1", "fps must be a positive number",
                 "camera.width must be a positive integer", "missing field 'frame_count'"):
        assert text in str(info.value)


def test_camera_constructor_checks():
    with pytest.raises(EpisodeFormatError, match="positive fx, fy"):
        CameraInfo(name="c", width=32, height=24, K=np.diag([0.0, 1.0, 1.0]))
    cam = CameraInfo(name="c", width=np.int64(32), height=24, K=np.diag([10.0, 10.0, 1.0]))
    assert cam.width == 32 and type(cam.width) is int and cam.T_mount_cam is None


def test_unreadable_json(tmp_path):
    (tmp_path / "episode.json").write_text("{not json")
    with pytest.raises(EpisodeFormatError, match="episode.json: not valid JSON"):
        load_meta(tmp_path / "episode.json")
    with pytest.raises(EpisodeFormatError, match="missing"):
        load_meta(tmp_path / "nothing" / "episode.json")
