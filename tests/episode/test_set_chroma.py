"""Saying how a camera's images kept their colour: ``set_chroma_subsampling`` and ``manisplat-episode set-chroma``."""

from __future__ import annotations

import json

import pytest
from episode_factory import write_episode
from v2_factory import CAMERAS, write_v2

from manisplat.episode import Episode
from manisplat.episode.chroma import set_chroma_subsampling
from manisplat.episode.cli import main
from manisplat.episode.format import EpisodeFormatError
from manisplat.episode.images import StoredChroma


def _without_chroma(meta: dict) -> dict:
    return {**meta, "camera": {k: v for k, v in meta["camera"].items() if not k.startswith("chroma_")}}


def test_png_images_are_said_to_have_been_subsampled(tmp_path):
    path = write_episode(tmp_path / "ep", 3)
    before = json.loads((path / "episode.json").read_text())
    assert set_chroma_subsampling(path, "4:2:0") == (None, StoredChroma("4:2:0", False))
    assert Episode.open(path).chroma_subsampling() == StoredChroma("4:2:0", False)
    assert set_chroma_subsampling(path, "4:2:2", red_blue_swapped=True) == (StoredChroma("4:2:0"), StoredChroma("4:2:2", True))
    after = json.loads((path / "episode.json").read_text())
    assert Episode.open(path).chroma_subsampling() == StoredChroma("4:2:2", True)
    assert _without_chroma(after) == before  # nothing else in episode.json changed


def test_a_jpeg_header_is_not_contradicted(tmp_path):
    path = write_episode(tmp_path / "ep", 3, image_format="jpg")  # cv2.imencode: 4:2:0
    before = (path / "episode.json").read_text()
    with pytest.raises(ValueError, match="JPEG files whose header says 4:2:0, not 4:4:4"):
        set_chroma_subsampling(path, "4:4:4")
    assert (path / "episode.json").read_text() == before
    assert set_chroma_subsampling(path, "4:2:0", red_blue_swapped=True) == (StoredChroma("4:2:0"), StoredChroma("4:2:0", True))


def test_an_unknown_scheme_or_camera_is_refused(tmp_path):
    path = write_episode(tmp_path / "ep", 2)
    with pytest.raises(ValueError, match="'4:2:1' is not one of 4:4:4, 4:2:2, 4:2:0"):
        set_chroma_subsampling(path, "4:2:1")
    with pytest.raises(EpisodeFormatError, match="no camera 'side'; cameras: "):
        set_chroma_subsampling(path, "4:2:0", camera="side")
    assert Episode.open(path).chroma_subsampling() is None


def test_one_camera_of_several(tmp_path):
    path = write_v2(tmp_path / "ep", 2)
    with pytest.raises(EpisodeFormatError, match="has cameras cam_high, cam_left_wrist, cam_right_wrist: name one"):
        set_chroma_subsampling(path, "4:2:0")
    set_chroma_subsampling(path, "4:2:0", camera="cam_left_wrist")
    episode = Episode.open(path)
    assert {c: episode.chroma_subsampling(c) for c in CAMERAS} == {
        "cam_high": None, "cam_left_wrist": StoredChroma("4:2:0"), "cam_right_wrist": None}


def test_the_command(tmp_path, capsys):
    path = write_episode(tmp_path / "ep", 2)
    assert main(["set-chroma", str(path), "4:2:0"]) == 0
    assert capsys.readouterr().out.strip() == f"{path}: colour stored not known -> 4:2:0"
    assert main(["info", str(path)]) == 0
    assert "colour stored 4:2:0" in capsys.readouterr().out
    assert main(["set-chroma", str(path), "4:2:0", "--camera", "side"]) == 2
    assert "no camera 'side'" in capsys.readouterr().err
    jpeg = write_episode(tmp_path / "jpg", 2, image_format="jpg")
    assert main(["set-chroma", str(jpeg), "4:2:2"]) == 2
    assert "header says 4:2:0" in capsys.readouterr().err
    assert main(["set-chroma", str(path), "4:2:1"]) == 2  # not a scheme: a usage error


def test_a_wrong_value_is_named_in_a_version_2_episode(tmp_path):
    from manisplat.episode import validate

    path = write_v2(tmp_path / "ep", 2)
    meta = json.loads((path / "episode.json").read_text())
    meta["cameras"]["cam_left_wrist"]["chroma_subsampling"] = "yuv420p"
    (path / "episode.json").write_text(json.dumps(meta))
    report = validate(path)
    assert not report.ok
    assert "cameras.cam_left_wrist.chroma_subsampling must be one of 4:4:4, 4:2:2, 4:2:0, 4:4:0, 4:1:1; got 'yuv420p'" \
        in str(report)
