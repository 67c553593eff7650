"""Format version 2: the writer, validate, recover, info and copy on every arm and camera."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from v2_factory import ARMS, CAMERAS, H, W, frame_values, images, joint_sample, open_writer_v2, write_v2

from manisplat.episode import Episode, recover, validate
from manisplat.episode.cli import main


def test_writer_round_trip(tmp_path):
    ep = Episode.open(write_v2(tmp_path / "ep", 6))
    assert ep.meta.version == 2 and ep.meta.complete and ep.meta.frame_count == 6
    raw = json.loads((tmp_path / "ep" / "episode.json").read_text())
    assert list(raw["arms"]) == list(ARMS) and list(raw["cameras"]) == list(CAMERAS) and "robot" not in raw
    assert ep.columns[:16] == ("index", "t", *(f"{a}.{c}" for a in ARMS
                                                for c in ("q1", "q2", "q3", "q4", "q5", "q6", "gripper")))
    for arm in ARMS:
        rows = [frame_values(i) for i in range(6)]
        assert np.array_equal(ep.arm_frames(arm).q, [[r[f"{arm}.q{j}"] for j in range(1, 7)] for r in rows])
        assert np.array_equal(ep.arm_frames(arm).actions[:, 6], [r[f"{arm}.a_gripper"] for r in rows])
        joints = ep.joints(arm)
        assert len(joints) == 24 and np.array_equal(joints.q[5], joint_sample(arm, 5)["q"])
    for cam in CAMERAS:
        assert all(np.array_equal(ep.rgb(i, cam), images(i, cam)["rgb"]) for i in range(6))
        assert sorted(p.name for p in (tmp_path / "ep" / "rgb" / cam).iterdir()) == [f"{i:06d}.png" for i in range(6)]
    assert np.array_equal(ep.camera_times("cam_left_wrist"), ep.camera_times("cam_high") + 0.004)
    assert np.allclose(ep.depth(1, "cam_high"), images(1, "cam_high")["depth"] * 1e-3)
    assert not (tmp_path / "ep" / "depth" / "cam_left_wrist").exists()
    report = validate(tmp_path / "ep")
    assert report.ok and not report.warnings, str(report)


def test_writer_checks_every_camera_and_arm(tmp_path):
    with open_writer_v2(tmp_path / "ep") as w:
        arms = {a: np.zeros(7) for a in ARMS}
        rgb = {c: np.zeros((H, W, 3), np.uint8) for c in CAMERAS}
        acts = {a: np.zeros(7) for a in ARMS}
        cam_t = {"cam_left_wrist": 0.0}
        with pytest.raises(ValueError, match=r"rgb of camera 'cam_right_wrist' must be \(24, 32, 3\) uint8"):
            w.add_frame(0.0, arms, {**rgb, "cam_right_wrist": np.zeros((H, W + 1, 3), np.uint8)}, actions=acts,
                        camera_t=cam_t, extra={"seq": 0})
        with pytest.raises(ValueError, match=r"rgb must give exactly .*missing \['cam_high'\]"):
            w.add_frame(0.0, arms, {c: rgb[c] for c in CAMERAS[1:]}, actions=acts, camera_t=cam_t, extra={"seq": 0})
        with pytest.raises(ValueError, match=r"arms must give exactly .*missing \['right'\]"):
            w.add_frame(0.0, {"left": np.zeros(7)}, rgb, actions=acts, camera_t=cam_t, extra={"seq": 0})
        w.add_frame(0.0, arms, rgb, actions=acts, camera_t=cam_t, extra={"seq": 0})
        with pytest.raises(ValueError, match="every frame must carry the same images"):
            w.add_frame(0.1, arms, rgb, depth={"cam_high": np.ones((H, W))}, actions=acts, camera_t=cam_t,
                        extra={"seq": 1})
    assert validate(tmp_path / "ep").ok


def test_validate_names_the_camera_and_arm(tmp_path):
    path = write_v2(tmp_path / "ep", 4)
    (path / "rgb" / "cam_right_wrist" / "000002.png").unlink()
    shutil.copy(path / "rgb" / "cam_high" / "000001.png", path / "depth" / "cam_high" / "000001.png")
    (path / "rgb" / "cam_x").mkdir()
    raw = json.loads((path / "episode.json").read_text())
    raw["cameras"]["cam_left_wrist"]["mount"] = "left/link9"
    (path / "episode.json").write_text(json.dumps(raw))
    text = str(validate(path))
    assert "rgb/cam_right_wrist/000002.png (frames.csv line 4): error: missing image for this frame" in text
    assert "depth/cam_high/000001.png (frames.csv line 3): error: must be 1-channel 16-bit" in text
    assert "cameras.cam_left_wrist.mount 'left/link9': arm 'left' has no link 'link9' (its links: base_link" in text
    assert "rgb/cam_x: warning: unexpected: a folder of no camera in episode.json" in text
    lines = (path / "frames.csv").read_text().split("\n")
    (path / "frames.csv").write_text("\n".join([lines[0].replace("right.q3", "right.qq")] + lines[1:]))
    assert "frames.csv:1: error: header must start with index,t,left.q1" in str(validate(path))


def test_recover_keeps_the_complete_frames_of_every_camera(tmp_path):
    """A writer killed while writing frame 6 (its row torn, frame 7's first image already there),
    after a power cut lost one camera's image of frame 5: frames 0..4 are complete in every camera."""
    path = write_v2(tmp_path / "ep", 7)
    raw = json.loads((path / "episode.json").read_text())
    (path / "episode.json").write_text(json.dumps({**raw, "complete": False}))
    text = (path / "frames.csv").read_text()
    (path / "frames.csv").write_text(text[:-25])  # the last row cut mid-line
    (path / "rgb" / "cam_right_wrist" / "000005.png").unlink()
    shutil.copy(path / "rgb" / "cam_high" / "000004.png", path / "rgb" / "cam_high" / "000007.png")
    for arm in ARMS:  # a torn joint sample
        stream = path / f"joints_{arm}.csv"
        stream.write_text(stream.read_text()[:-7])
    assert not validate(path).ok
    report = recover(path)
    assert report.frames_kept == 5 and report.validation.ok, str(report)
    ep = Episode.open(path)
    assert len(ep) == 5 and ep.meta.complete
    for cam in CAMERAS:
        assert sorted(p.name for p in (path / "rgb" / cam).iterdir()) == [f"{i:06d}.png" for i in range(5)]
        assert all(np.array_equal(ep.rgb(i, cam), images(i, cam)["rgb"]) for i in range(5))
    assert sorted(p.name for p in (path / "depth" / "cam_high").iterdir()) == [f"{i:06d}.png" for i in range(5)]
    assert {"rgb/cam_high/000007.png", "rgb/cam_left_wrist/000005.png", "depth/cam_high/000006.png"} <= set(report.moved)
    assert all(len(ep.joints(arm)) == 27 for arm in ARMS)
    assert np.array_equal(ep.arm_frames("right").q[4], [frame_values(4)[f"right.q{j}"] for j in range(1, 7)])


def test_recover_refuses_damage_in_the_middle(tmp_path):
    path = write_v2(tmp_path / "ep", 5)
    (path / "rgb" / "cam_left_wrist" / "000002.png").write_bytes(b"\x89PNG broken")
    with pytest.raises(ValueError, match="rgb/cam_left_wrist/000002.png cannot decode.*2 good frame"):
        recover(path)
    report = recover(path, drop_damaged=True)
    assert report.frames_kept == 4 and report.validation.ok
    assert ("rgb/cam_high/000003.png", "rgb/cam_high/000002.png") in report.renamed


def test_info_lists_arms_and_cameras(tmp_path, capsys):
    path = write_v2(tmp_path / "ep", 3)
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "format    version 2: 2 arm(s) left, right; 3 camera(s) cam_high, cam_left_wrist, cam_right_wrist" in out
    assert "arm left: agilex_piper, angles per builtin:agilex_piper, base at (0.000, 0.300, 0.000) m, actions" in out
    assert "arm right:" in out and "joints_right.csv 12 rows" in out
    assert "camera cam_left_wrist: 32x24, fx=25.00" in out and "mount left/link6" in out
    assert "own times (cam_left_wrist.t)" in out and "depth/cam_high/ 3 png" in out


def write_urdf(tmp_path):
    """A 6-joint URDF with base_link..link6 at tmp_path/robots/two.urdf."""
    urdf = tmp_path / "robots" / "two.urdf"
    urdf.parent.mkdir()
    links = "".join(f'<link name="{n}"/>' for n in ("base_link", "link1", "link2", "link3", "link4", "link5", "link6"))
    joints = "".join(f'<joint name="joint{i}" type="revolute"><parent link="{"base_link" if i == 1 else f"link{i - 1}"}"/>'
                     f'<child link="link{i}"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/>'
                     f'</joint>' for i in range(1, 7))
    urdf.write_text(f'<robot name="two">{links}{joints}</robot>')
    return urdf


def test_copy_embeds_every_arms_robot(tmp_path):
    write_urdf(tmp_path)
    path = write_v2(tmp_path / "ep", 3, description="../robots/two.urdf")
    assert validate(path).ok
    assert main(["copy", "--embed", str(path), str(tmp_path / "copy")]) == 0
    raw = json.loads((tmp_path / "copy" / "episode.json").read_text())
    assert [a["description"] for a in raw["arms"].values()] == ["robot/two.urdf", "robot/two.urdf"]
    shutil.rmtree(tmp_path / "robots")
    report = validate(tmp_path / "copy")
    assert report.ok and not report.warnings, str(report)
    assert main(["copy", str(path), str(tmp_path / "copy2")]) == 2  # the original now points nowhere: refused


CHILD = """
import sys
sys.path.insert(0, {helpers!r})
from v2_factory import add_frame_v2, open_writer_v2
writer = open_writer_v2({path!r}, fsync_every=5)
i = 0
while True:
    add_frame_v2(writer, i)
    print(i, flush=True)
    i += 1
"""


def test_sigkill_mid_episode_keeps_every_reported_frame_of_every_camera(tmp_path):
    """The writer is killed (SIGKILL) after it reported 7 frames: every reported frame comes back
    for every camera and arm."""
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path

    path = tmp_path / "ep"
    child = subprocess.Popen([sys.executable, "-c", CHILD.format(helpers=str(Path(__file__).parent), path=str(path))],
                             stdout=subprocess.PIPE, text=True)
    try:
        reported = [int(child.stdout.readline()) for _ in range(7)]
    finally:
        os.kill(child.pid, signal.SIGKILL)
        child.wait()
        child.stdout.close()
    assert reported == list(range(7)) and not validate(path).ok
    report = recover(path)
    assert report.validation.ok and report.frames_kept >= 7, str(report)
    ep = Episode.open(path)
    for cam in CAMERAS:
        assert all(np.array_equal(ep.rgb(i, cam), images(i, cam)["rgb"]) for i in range(report.frames_kept))
    for arm in ARMS:
        assert np.array_equal(ep.arm_frames(arm).gripper,
                              [frame_values(i)[f"{arm}.gripper"] for i in range(report.frames_kept)])
        assert len(ep.joints(arm)) >= 4 * 7
    for rel in report.moved:  # nothing deleted
        assert (report.backup_dir / rel).exists()


def test_one_arm_one_camera_v2_exports_like_version_1(tmp_path):
    """A version 2 episode with one arm and one camera exports as version 1 does: the ACT exporter
    finds its images in rgb/<camera>/ and its joints in <arm>.q1... (two arms: test_export_arms.py)."""
    from manisplat.episode.exporters.act_hdf5 import export_act_hdf5
    from manisplat.episode.importers.act_hdf5 import import_act_hdf5

    path = write_v2(tmp_path / "ep", 4, arms=("right",), cameras=("cam_high",), camera_times=())
    export_act_hdf5([path], tmp_path / "act", dtype="float64")
    back = import_act_hdf5(tmp_path / "act" / "episode_0.hdf5", tmp_path / "back", K=np.diag([30.0, 30.0, 1.0]),
                           arm="single", camera="cam_high", fps=20.0)
    ep = Episode.open(path)
    assert np.array_equal(back.frames.q, ep.frames.q) and np.array_equal(back.frames.gripper, ep.frames.gripper)
    assert all(np.array_equal(back.rgb(i), images(i, "cam_high")["rgb"]) for i in range(4))


def test_set_robot_of_one_arm(tmp_path, capsys, monkeypatch):
    write_urdf(tmp_path)
    path = write_v2(tmp_path / "ep", 2)
    monkeypatch.chdir(tmp_path)
    assert main(["set-robot", str(path), "robots/two.urdf"]) == 2
    assert "has arms left, right: name one (--arm NAME)" in capsys.readouterr().err
    assert main(["set-robot", str(path), "robots/two.urdf", "--arm", "middle"]) == 2
    assert main(["set-robot", str(path), "robots/two.urdf", "--arm", "right", "--embed"]) == 0
    assert "arms.right.description 'builtin:agilex_piper' -> 'robot/right/two.urdf'" in capsys.readouterr().out
    raw = json.loads((path / "episode.json").read_text())
    assert [a["description"] for a in raw["arms"].values()] == ["builtin:agilex_piper", "robot/right/two.urdf"]
    report = validate(path)
    assert report.ok and not report.warnings, str(report)
