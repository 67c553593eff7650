import json

import numpy as np
import pytest

from manisplat.calib.board import save_board
from manisplat.calib.cli import main
from manisplat.exit_codes import ExitCode
from manisplat.calib.poses import pose_difference
from manisplat.calib.synth import default_truth, sample_configurations, write_calibration_episode
from manisplat.episode import Episode, validate


def test_solve_episode_meets_the_goal_and_writes_report(calib_episode, tmp_path):
    ep, board, truth = calib_episode
    out = tmp_path / "calibration.json"
    assert main(["solve", str(ep), "--board", str(board), "--out", str(out), "--report", str(tmp_path / "rep")]) == 0
    cal = json.loads(out.read_text())
    rot, trans = pose_difference(np.asarray(cal["T_mount_cam"]), truth.T_base_cam)
    assert rot < 0.05 and trans < 0.5
    rot_b, trans_b = pose_difference(np.asarray(cal["T_link_board"]), truth.T_link6_board)
    assert rot_b < 0.1 and trans_b < 1.0
    for key in ("K", "dist", "width", "height", "mount", "T_mount_cam", "latency_s", "residuals", "date", "uncertainty"):
        assert key in cal
    assert cal["mount"] == "base" and cal["residuals"]["rms_px"] < 0.3
    assert (tmp_path / "rep" / "report.html").stat().st_size > 1000
    assert (tmp_path / "rep" / "report.png").is_file() and list((tmp_path / "rep").glob("overlay_*.png"))


def test_apply_writes_calibration_and_keeps_the_rest(calib_episode, tmp_path):
    ep, board, truth = calib_episode
    cal_path = tmp_path / "c.json"
    assert main(["solve", str(ep), "--board", str(board), "--out", str(cal_path)]) == 0
    cal = json.loads(cal_path.read_text())
    cal["latency_s"] = 0.031
    cal_path.write_text(json.dumps(cal))
    import shutil
    copy = tmp_path / "copy"
    shutil.copytree(ep, copy)
    raw = json.loads((copy / "episode.json").read_text())
    raw["task"] = "keep me"
    raw["camera"]["exposure_note"] = "keep me too"
    (copy / "episode.json").write_text(json.dumps(raw))
    assert main(["apply", str(cal_path), str(copy)]) == 0
    new = json.loads((copy / "episode.json").read_text())
    assert new["task"] == "keep me" and new["camera"]["exposure_note"] == "keep me too"
    assert np.allclose(new["camera"]["T_mount_cam"], cal["T_mount_cam"]) and new["camera"]["latency_s"] == 0.031
    assert new["frame_count"] == raw["frame_count"] and new["robot"] == raw["robot"]
    assert validate(copy).ok if hasattr(validate(copy), "ok") else True
    assert Episode.open(copy).camera.T_mount_cam is not None
    # a calibration of another image size is refused, the episode untouched
    cal["width"] = 1280
    cal_path.write_text(json.dumps(cal))
    before = (copy / "episode.json").read_bytes()
    assert main(["apply", str(cal_path), str(copy)]) == ExitCode.BAD_INPUT
    assert (copy / "episode.json").read_bytes() == before


def test_single_axis_episode_is_degenerate(tmp_path, spec, capsys):
    truth = default_truth(spec)
    rng = np.random.default_rng(4)
    q = sample_configurations(spec, truth, 6, rng, single_axis=True)
    write_calibration_episode(tmp_path / "ep", spec, truth, q, rng=rng, supersample=1)
    save_board(tmp_path / "board.json", spec)
    code = main(["solve", str(tmp_path / "ep"), "--board", str(tmp_path / "board.json"), "--out", str(tmp_path / "c.json")])
    assert code == ExitCode.INSUFFICIENT_DATA
    assert "one axis" in capsys.readouterr().err
    assert not (tmp_path / "c.json").exists()


def test_too_few_detections_is_a_clear_error(tmp_path, spec, capsys):
    truth = default_truth(spec)
    rng = np.random.default_rng(5)
    q = sample_configurations(spec, truth, 4, rng)
    write_calibration_episode(tmp_path / "ep", spec, truth, q, rng=rng, supersample=1)
    for k in (1, 2):  # blank two frames: the board is not seen there
        import cv2
        p = tmp_path / "ep" / "rgb" / f"{k:06d}.png"
        cv2.imwrite(str(p), np.full((truth.camera.height, truth.camera.width, 3), 128, np.uint8))
    save_board(tmp_path / "board.json", spec)
    code = main(["solve", str(tmp_path / "ep"), "--board", str(tmp_path / "board.json"), "--out", str(tmp_path / "c.json")])
    assert code == ExitCode.INSUFFICIENT_DATA
    err = capsys.readouterr().err
    assert "only 2 of 4 frames" in err and "frame 1: 0 corners" in err


def test_missing_board_file_is_an_input_error(calib_episode, tmp_path):
    ep, _, _ = calib_episode
    assert main(["solve", str(ep), "--board", str(tmp_path / "nope.json"), "--out", str(tmp_path / "c.json")]) == ExitCode.BAD_INPUT


def test_board_command(tmp_path):
    assert main(["board", "--out", str(tmp_path / "b"), "--squares-x", "5", "--squares-y", "4"]) == 0
    assert {p.suffix for p in tmp_path.iterdir()} == {".png", ".pdf", ".json"}


def test_help_lists_exit_codes(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    assert "Exit status (the same in every manisplat command" in capsys.readouterr().out


def test_eye_in_hand_episode(tmp_path, spec):
    from manisplat.calib.synth import write_eye_in_hand_episode
    T_link6_cam, T_base_board = write_eye_in_hand_episode(tmp_path / "ep", spec, 10, np.random.default_rng(9))
    save_board(tmp_path / "board.json", spec)
    out = tmp_path / "c.json"
    assert main(["solve", str(tmp_path / "ep"), "--board", str(tmp_path / "board.json"), "--out", str(out),
                 "--mount", "link6"]) == 0
    cal = json.loads(out.read_text())
    assert cal["mount"] == "link6"
    rot, trans = pose_difference(np.asarray(cal["T_mount_cam"]), T_link6_cam)
    assert rot < 0.05 and trans < 0.5
    rot_b, trans_b = pose_difference(np.asarray(cal["T_base_board"]), T_base_board)
    assert rot_b < 0.1 and trans_b < 1.0
