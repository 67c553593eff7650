"""validate(): every problem reported, each with the right file and row."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from episode_factory import H, W

from manisplat.episode import ValidationReport, validate


def edit_row(path: Path, line: int, column: int, value: str, file: str = "frames.csv") -> None:
    """Set field ``column`` of 1-based ``line`` of a CSV file."""
    lines = (path / file).read_text().splitlines(keepends=True)
    fields = lines[line - 1].rstrip("\n").split(",")
    fields[column] = value
    lines[line - 1] = ",".join(fields) + "\n"
    (path / file).write_text("".join(lines))


def edit_meta(path: Path, **camera) -> None:
    meta = json.loads((path / "episode.json").read_text())
    meta["camera"].update(camera)
    (path / "episode.json").write_text(json.dumps(meta))


def only(report: ValidationReport, severity: str = "error"):
    found = [p for p in report.problems if p.severity == severity]
    assert len(found) == 1, str(report)
    return found[0]


def test_good_episode_is_ok(episode):
    report = validate(episode)
    assert report.ok and report.problems == [] and report.frame_rows == 8
    assert "OK (8 frames" in str(report)


def test_deleted_frame_image(episode):
    (episode / "rgb" / "000004.png").unlink()
    p = only(validate(episode))
    assert (p.file, p.row) == ("rgb/000004.png", 6) and "missing image" in p.message
    assert str(p) == "rgb/000004.png (frames.csv line 6): error: missing image for this frame"


def test_nan_row(episode):
    edit_row(episode, 4, 4, "nan")
    p = only(validate(episode))
    assert (p.file, p.row) == ("frames.csv", 4) and "'q3' is nan" in p.message
    assert str(p).startswith("frames.csv:4: error:")


def test_truncated_png(episode):
    png = episode / "rgb" / "000005.png"
    data = png.read_bytes()
    png.write_bytes(data[: len(data) // 2])
    assert cv2.imread(str(png)) is None  # the decoder itself rejects it
    p = only(validate(episode))
    assert (p.file, p.row) == ("rgb/000005.png", 7) and "cannot decode" in p.message
    assert validate(episode, decode_images=False).ok  # --quick does not decode


def test_truncated_at_the_very_end(episode):
    png = episode / "masks" / "000002.png"
    png.write_bytes(png.read_bytes()[:-12])  # only the IEND chunk is lost
    p = only(validate(episode))
    assert (p.file, p.row) == ("masks/000002.png", 4)


def test_duplicated_index(episode):
    edit_row(episode, 5, 0, "2")  # frame 3's row says 2
    report = validate(episode)
    dup = [p for p in report.errors if "duplicate index 2" in p.message]
    assert len(dup) == 1 and (dup[0].file, dup[0].row) == ("frames.csv", 5) and "line 4" in dup[0].message
    assert any(p.file == "rgb/000003.png" and "extra frame" in p.message for p in report.errors)


def test_missing_row(episode):
    lines = (episode / "frames.csv").read_text().splitlines(keepends=True)
    (episode / "frames.csv").write_text("".join(lines[:4] + lines[5:]))  # drop frame 3
    report = validate(episode)
    messages = {(p.file, p.row, p.message) for p in report.errors}
    assert ("frames.csv", 5, "index jumps from 2 to 4: frame(s) 3 missing") in messages
    assert ("frames.csv", None, "has 7 rows but episode.json frame_count is 8") in messages
    assert any(f == "rgb/000003.png" and "extra frame" in m for f, _, m in messages)


def test_non_monotonic_t(episode):
    edit_row(episode, 7, 1, "0.2")  # frame 5 at t=0.2, before frame 4 (t=0.4)
    report = validate(episode)
    p = only(report)
    assert (p.file, p.row) == ("frames.csv", 7) and "strictly increasing" in p.message and "line 6" in p.message


def test_wrong_image_size(episode):
    cv2.imwrite(str(episode / "rgb" / "000001.png"), np.zeros((H // 2, W // 2, 3), np.uint8))
    p = only(validate(episode))
    assert (p.file, p.row) == ("rgb/000001.png", 3) and "size 16x12 does not match the camera's 32x24" in p.message


def test_wrong_channels_and_depth(episode):
    cv2.imwrite(str(episode / "rgb" / "000001.png"), np.zeros((H, W), np.uint8))
    cv2.imwrite(str(episode / "depth" / "000002.png"), np.zeros((H, W), np.uint8))
    cv2.imwrite(str(episode / "masks" / "000003.png"), np.zeros((H, W), np.uint16))
    found = {(p.file, p.message) for p in validate(episode).errors}
    assert found == {("rgb/000001.png", "must be 3-channel 8-bit (rgb); got 1-channel 8-bit"),
                     ("depth/000002.png", "must be 1-channel 16-bit (depth); got 1-channel 8-bit"),
                     ("masks/000003.png", "must be 1-channel 8-bit (masks); got 1-channel 16-bit")}


def test_bad_K(episode):
    edit_meta(episode, K=[[-30.0, 0, 15.5], [0, 31.0, 11.5], [0, 0, 1]])
    p = only(validate(episode))
    assert p.file == "episode.json" and p.row is None and "camera.K" in p.message and "fx=-30" in p.message


def test_non_rigid_transform(episode):
    edit_meta(episode, T_mount_cam=(2 * np.eye(4)).tolist())
    report = validate(episode)
    assert {p.file for p in report.errors} == {"episode.json"}
    assert any("camera.T_mount_cam" in p.message for p in report.errors)


def test_extra_image(episode):
    (episode / "rgb" / "000008.png").write_bytes((episode / "rgb" / "000000.png").read_bytes())
    p = only(validate(episode))
    assert (p.file, p.row) == ("rgb/000008.png", None) and "extra frame" in p.message


def test_every_problem_is_reported(episode):
    (episode / "rgb" / "000004.png").unlink()
    edit_row(episode, 3, 8, "inf")
    edit_meta(episode, width=0)
    report = validate(episode)
    files = {(p.file, p.row) for p in report.errors}
    assert {("rgb/000004.png", 6), ("frames.csv", 3), ("episode.json", None)} <= files
    assert len(str(report).splitlines()) == len(report.problems) + 1


def test_wrong_field_count_and_header(episode):
    lines = (episode / "frames.csv").read_text().splitlines(keepends=True)
    lines[2] = lines[2].rstrip("\n") + ",1.0\n"
    (episode / "frames.csv").write_text("".join(lines))
    p = only(validate(episode))
    assert (p.file, p.row) == ("frames.csv", 3) and "has 18 fields, the header has 17" in p.message
    (episode / "frames.csv").write_text("t,index" + "".join(lines[1:]))
    assert any(p.row == 1 and "header must start with index,t,q1" in p.message for p in validate(episode).errors)


def test_warnings_keep_it_valid(episode):
    edit_row(episode, 2, 8, "0.5")  # gripper 0.5 m
    mask = cv2.imread(str(episode / "masks" / "000006.png"), cv2.IMREAD_UNCHANGED)
    mask[0, 0] = 77
    cv2.imwrite(str(episode / "masks" / "000006.png"), mask)
    (episode / "rgb" / "000009.png.tmp").write_bytes(b"x")
    report = validate(episode)
    assert report.ok
    found = {(p.file, p.row): p.message for p in report.warnings}
    assert "gripper outside [0.0, 0.1] m" in found[("frames.csv", 2)]
    assert "mask value 77" in found[("masks/000006.png", None)]
    assert "temporary file" in found[("rgb/000009.png.tmp", None)]


def test_incomplete_episode(episode):
    meta = json.loads((episode / "episode.json").read_text())
    meta["complete"] = False
    (episode / "episode.json").write_text(json.dumps(meta))
    p = only(validate(episode))
    assert p.file == "episode.json" and "incomplete episode: run `manisplat-episode recover`" in p.message


def test_joints_csv(episode):
    edit_row(episode, 5, 2, "nan", file="joints.csv")
    edit_row(episode, 10, 0, "0.0", file="joints.csv")
    found = {(p.file, p.row) for p in validate(episode).errors}
    assert found == {("joints.csv", 5), ("joints.csv", 10)}


@pytest.mark.parametrize("content, message", [(None, "missing"), ("{oops", "unreadable: not valid JSON")])
def test_broken_episode_json(episode, content, message):
    if content is None:
        (episode / "episode.json").unlink()
    else:
        (episode / "episode.json").write_text(content)
    report = validate(episode)
    p = only(report)
    assert p.file == "episode.json" and message in p.message


def test_missing_frames_csv_and_folder(episode, tmp_path):
    (episode / "frames.csv").unlink()
    assert [(p.file, p.message) for p in validate(episode).errors] == [("frames.csv", "missing")]
    assert not validate(tmp_path / "nowhere").ok
