"""Two arms and three cameras (Cobot Magic) calibrated from one version 2 episode with a still
board, rendered here with exact ground truth: each wrist camera's T_link6_cam, each arm's base and
the head camera in one world, the choice of that world, rig.json written into a version 2
episode by `apply`, and the refusals."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from manisplat.calib.board import save_board
from manisplat.calib.cli import main
from manisplat.calib.errors import InputError, NotEnoughDataError
from manisplat.calib.poses import inv_T, make_T, pose_difference, rodrigues
from manisplat.calib.rig import solve_rig, world_in_board
from manisplat.calib.synth_rig import ARMS, HEAD, WRIST, write_rig_episode
from manisplat.episode import Episode
from manisplat.exit_codes import ExitCode


@pytest.fixture(scope="module")
def rig_episode(tmp_path_factory, spec):
    """A 10-frame rig episode (head 640x480, wrists 480x360), its board file and its truth."""
    root = tmp_path_factory.mktemp("rig")
    truth = write_rig_episode(root / "ep", spec, 10, np.random.default_rng(3))
    save_board(root / "board.json", spec)
    return root / "ep", root / "board.json", truth


@pytest.fixture(scope="module")
def solved(rig_episode, spec):
    return solve_rig(rig_episode[0], spec)


def test_every_wrist_camera_base_and_the_head_camera_are_found(rig_episode, solved):
    _, _, truth = rig_episode
    for arm in ARMS:
        rot, mm = pose_difference(solved.T_world_base[arm], truth.T_world_base[arm])
        assert rot < 0.05 and mm < 0.2, (arm, rot, mm)
        camera = solved.cameras[WRIST[arm]]
        assert camera.mount == f"{arm}/link6" and solved.base_from[arm] == WRIST[arm]
        rot, mm = pose_difference(camera.T_mount_cam, truth.T_link6_cam[arm])
        assert rot < 0.05 and mm < 0.2, (WRIST[arm], rot, mm)
    head = solved.cameras[HEAD]
    rot, mm = pose_difference(head.T_mount_cam, truth.T_world_head)
    assert head.mount == "world" and rot < 0.1 and mm < 1.5, (rot, mm)
    assert head.static.views == 10 and head.static.rms_px < 0.2


def test_the_world_is_the_bases_an_arm_or_a_camera(rig_episode, spec, solved):
    _, _, truth = rig_episode
    T_board_base = {arm: inv_T(solved.T_world_board) @ T for arm, T in solved.T_world_base.items()}
    T_board_head = inv_T(solved.T_world_board) @ solved.cameras[HEAD].T_mount_cam
    left = inv_T(world_in_board("left", T_board_base, {HEAD: T_board_head})) @ T_board_base["right"]
    rot, mm = pose_difference(left, inv_T(truth.T_world_base["left"]) @ truth.T_world_base["right"])
    assert rot < 0.05 and mm < 0.3
    head = inv_T(world_in_board(HEAD, T_board_base, {HEAD: T_board_head})) @ T_board_base["left"]
    rot, mm = pose_difference(head, inv_T(truth.T_world_head) @ truth.T_world_base["left"])
    assert rot < 0.1 and mm < 1.5
    with pytest.raises(InputError, match="not 'bases', an arm .left, right. or a camera fixed in the world .cam_high."):
        world_in_board("table", T_board_base, {HEAD: T_board_head})
    facing = {"a": np.eye(4), "b": make_T(rodrigues([np.pi, 0.0, 0.0]), [0.0, 0.0, 0.5])}  # z up and z down
    with pytest.raises(InputError, match="point in opposite directions"):
        world_in_board("bases", facing, {})
    turned = world_in_board("bases", {"a": make_T(rodrigues([0, 0, 0.2]), [0, 1, 0]),
                                      "b": make_T(rodrigues([0, 0, -0.2]), [0, -1, 0])}, {})
    assert np.allclose(turned, np.eye(4), atol=1e-12)  # the midpoint and the mean forward axis
    tilted = world_in_board("bases", {"a": make_T(rodrigues([0, 0.3, 0]), [0, 1, 0]),
                                      "b": make_T(rodrigues([0.3, 0, 0]), [0, -1, 0])}, {})
    R = tilted[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
    z = rodrigues([0, 0.3, 0])[:, 2] + rodrigues([0.3, 0, 0])[:, 2]
    assert np.allclose(R[:, 2], z / np.linalg.norm(z), atol=1e-12)  # z: the mean up axis


def test_solve_rig_and_apply_write_every_camera_and_base_into_the_episode(rig_episode, tmp_path, capsys):
    episode, board, truth = rig_episode
    assert main(["solve-rig", str(episode), "--board", str(board), "--out", str(tmp_path / "rig.json")]) == 0
    rig = json.loads((tmp_path / "rig.json").read_text())
    assert set(rig["cameras"]) == {HEAD, *WRIST.values()} and set(rig["arms"]) == set(ARMS)
    copy = tmp_path / "ep"
    shutil.copytree(episode, copy)
    assert main(["apply", str(tmp_path / "rig.json"), str(copy)]) == 0
    ep = Episode.open(copy)
    for arm in ARMS:
        assert np.array_equal(ep.arms[arm].T_world_base, np.array(rig["arms"][arm]["T_world_base"]))
        rot, mm = pose_difference(ep.arms[arm].T_world_base, truth.T_world_base[arm])
        assert rot < 0.05 and mm < 0.2
    for name, cam in ep.cameras.items():
        assert np.array_equal(cam.T_mount_cam, np.array(rig["cameras"][name]["T_mount_cam"])), name
        assert cam.mount == rig["cameras"][name]["mount"] and cam.extra["calibration"]["date"] == rig["date"]
    assert main(["apply", str(tmp_path / "rig.json"), str(copy)]) == 0  # again: the same values
    capsys.readouterr()


def test_apply_refuses_what_it_cannot_write(rig_episode, calib_episode, tmp_path, capsys):
    episode, board, _ = rig_episode
    assert main(["solve-rig", str(episode), "--board", str(board), "--out", str(tmp_path / "rig.json")]) == 0
    one_arm, _, _ = calib_episode
    v1 = tmp_path / "v1"
    shutil.copytree(one_arm, v1)
    capsys.readouterr()
    assert main(["apply", str(tmp_path / "rig.json"), str(v1)]) == ExitCode.BAD_INPUT
    assert "version 1 (one camera)" in capsys.readouterr().err
    assert main(["solve-rig", str(v1), "--board", str(board), "--out", str(tmp_path / "v1.json")]) == ExitCode.BAD_INPUT
    assert "version 1 (one arm, one camera): calibrate it with `manisplat-calibrate solve`" in capsys.readouterr().err
    calibration = {"format": "manisplat-calibration", "K": [[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]],
                   "dist": [], "width": 640, "height": 480, "mount": "base", "T_mount_cam": np.eye(4).tolist()}
    (tmp_path / "calibration.json").write_text(json.dumps(calibration))
    v2 = tmp_path / "v2"
    shutil.copytree(episode, v2)
    assert main(["apply", str(tmp_path / "calibration.json"), str(v2)]) == ExitCode.BAD_INPUT
    assert "version 2 (cameras cam_high, cam_left_wrist, cam_right_wrist)" in capsys.readouterr().err
    rig = json.loads((tmp_path / "rig.json").read_text())
    del rig["arms"]["right"]
    (tmp_path / "partial.json").write_text(json.dumps(rig))
    assert main(["apply", str(tmp_path / "partial.json"), str(v2)]) == ExitCode.BAD_INPUT
    assert "does not cover arm right" in capsys.readouterr().err
    rig = json.loads((tmp_path / "rig.json").read_text())
    rig["cameras"][HEAD]["width"] = 1280
    (tmp_path / "size.json").write_text(json.dumps(rig))
    assert main(["apply", str(tmp_path / "size.json"), str(v2)]) == ExitCode.BAD_INPUT
    assert "camera cam_high images are 640x480 but the rig calibrated it at 1280x480" in capsys.readouterr().err
    assert Episode.open(v2).arms["left"].T_world_base is None  # nothing written by a refused apply


def test_an_arm_without_a_camera_cannot_be_placed(rig_episode, spec, tmp_path):
    broken = tmp_path / "ep"
    shutil.copytree(rig_episode[0], broken)
    meta = json.loads((broken / "episode.json").read_text())
    meta["cameras"]["cam_right_wrist"]["mount"] = "left/link6"
    (broken / "episode.json").write_text(json.dumps(meta))
    with pytest.raises(NotEnoughDataError, match="arm right carries no camera"):
        solve_rig(broken, spec)


def test_a_wrist_cameras_frames_are_skipped_while_its_arm_moves(rig_episode, spec, tmp_path):
    moving = tmp_path / "ep"
    shutil.copytree(rig_episode[0], moving)
    ep = Episode.open(moving)
    q, t = ep.arm_frames("right").q, ep.arm_frames("right").t
    lines = ["t,q1,q2,q3,q4,q5,q6,gripper"]
    for k in range(len(ep)):  # still around each frame (moving half-way between them), but swinging at frame 4
        samples = [(dt, q[k, 0] + (0.05 * np.sign(dt) if k == 4 else 0.0)) for dt in (-0.05, 0.0, 0.05)]
        for dt, q1 in samples + ([(0.25, q[k + 1, 0])] if k + 1 < len(ep) else []):
            row = q[k + 1] if dt == 0.25 else q[k]
            lines.append(",".join(repr(float(x)) for x in (t[k] + dt, q1, *row[1:], 0.0)))
    (moving / "joints_right.csv").write_text("\n".join(lines) + "\n")
    solved = solve_rig(moving, spec)
    assert "arm moving" in solved.cameras["cam_right_wrist"].rejected[4]
    assert 4 not in solved.cameras["cam_left_wrist"].rejected and 4 not in solved.cameras[HEAD].rejected
    assert solved.cameras["cam_right_wrist"].hand_eye.refine.view_used.sum() == len(ep) - 1
