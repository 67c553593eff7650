"""Export of a two-arm, three-camera (Cobot Magic) version 2 episode: ACT HDF5 re-imported by
``import-act --calib`` bit-exact, LeRobot v3.0 with a 14-D state and one video per camera, and back
through ``import-lerobot --calib --units``."""

from __future__ import annotations

import json

import av
import cv2
import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from episode_factory import write_episode
from test_import_cobot import CAMERAS, T, write_calib, write_cobot

from manisplat.episode import Episode, EpisodeFormatError, validate
from manisplat.episode.cli import main
from manisplat.episode.exporters.act_hdf5 import export_act_hdf5
from manisplat.episode.images import StoredChroma

NAMES = [f"{arm}.{c}" for arm in ("left", "right") for c in ("q1", "q2", "q3", "q4", "q5", "q6", "gripper")]


def _imported(tmp_path, *, compress: bool = False, dtype: str = "float32", degrees: bool = False):
    """A Cobot Magic file imported with --calib: (episode folder, calibration, what the file holds).
    With ``degrees`` the joints are stored in degrees (as some PiPER plugins write them)."""
    data = write_cobot(tmp_path / "episode_0.hdf5", compress=compress, dtype=dtype)
    if degrees:
        with h5py.File(tmp_path / "episode_0.hdf5", "r+") as f:
            qpos = f["observations/qpos"][()]
            qpos[:, [0, 1, 2, 3, 4, 5, 7, 8, 9, 10, 11, 12]] *= 180 / np.pi
            f["observations/qpos"][...] = data["qpos"] = qpos
    calib = write_calib(tmp_path / "episode_0.calib.json")
    out = tmp_path / "ep"
    assert main(["import-act", str(tmp_path / "episode_0.hdf5"), "--calib", str(calib), "--out", str(out)]) == 0
    return out, calib, data


def _joints(ep: Episode) -> np.ndarray:
    """(T, 14) float64: each arm's q1..q6, gripper, left then right."""
    return np.concatenate([np.column_stack([ep.arm_frames(a).q, ep.arm_frames(a).gripper]) for a in ep.arms], axis=1)


@pytest.mark.parametrize("dtype, option", [("float32", []), ("float64", ["--float64"])])
def test_act_export_has_14_columns_a_key_per_camera_and_reimports_bit_exact(tmp_path, capsys, dtype, option):
    ep_path, calib, data = _imported(tmp_path, dtype=dtype)
    out = tmp_path / "act"
    assert main(["export", str(ep_path), "--format", "act-hdf5", "--out", str(out), *option]) == 0
    with h5py.File(out / "episode_0.hdf5", "r") as f:
        assert f["observations/qpos"].dtype == dtype and f["observations/qpos"].shape == (T, 14)
        assert np.array_equal(f["observations/qpos"][()], data["qpos"])  # the file's columns, in its order
        assert np.array_equal(f["action"][()], data["action"]) and f["action"].attrs["source"] == "actions"
        assert f["observations/qvel"].shape == (T, 14) and json.loads(f.attrs["qpos_names"]) == NAMES
        assert sorted(f["observations/images"]) == sorted(CAMERAS) and "compress_len" not in f
        for cam in CAMERAS:
            assert np.array_equal(f[f"observations/images/{cam}"][()], data["images"][cam])
    capsys.readouterr()
    back = tmp_path / "back"
    assert main(["import-act", str(out / "episode_0.hdf5"), "--calib", str(calib), "--out", str(back)]) == 0
    first, again = Episode.open(ep_path), Episode.open(back)
    assert np.array_equal(_joints(again), _joints(first)) and np.array_equal(_joints(again), data["qpos"])
    for arm in ("left", "right"):
        assert np.array_equal(again.arm_frames(arm).actions, first.arm_frames(arm).actions)
    for cam in CAMERAS:
        assert all(np.array_equal(again.rgb(i, cam), data["images"][cam][i]) for i in range(T))


def test_act_export_writes_the_calibration_that_reads_it_back(tmp_path, capsys):
    """Each file of a version 2 export has its ``episode_<N>.calib.json``: import-act --calib with
    it alone gives back the arms, the cameras (renamed keys included) and the joints."""
    ep_path, _, data = _imported(tmp_path)
    out = tmp_path / "act"
    assert main(["export", str(ep_path), str(ep_path), "--format", "act-hdf5", "--out", str(out), "--float64",
                 "--image-key", f"{CAMERAS[0]}=top"]) == 0
    assert (out / "episode_1.calib.json").is_file()
    capsys.readouterr()
    back = tmp_path / "back"
    assert main(["import-act", str(out / "episode_0.hdf5"), "--calib", str(out / "episode_0.calib.json"),
                 "--out", str(back)]) == 0
    first, again = Episode.open(ep_path), Episode.open(back)
    assert np.array_equal(_joints(again), data["qpos"]) and again.meta.fps == first.meta.fps
    assert list(again.arms) == list(first.arms)
    for name, arm in first.arms.items():
        assert np.array_equal(again.arms[name].T_world_base, arm.T_world_base)
        assert again.arms[name].description == arm.description  # builtin:agilex_piper
    renamed = {CAMERAS[0]: "top", **{c: c for c in CAMERAS[1:]}}
    assert sorted(again.cameras) == sorted(renamed.values())
    for camera, key in renamed.items():
        a, b = first.cameras[camera], again.cameras[key]
        assert (a.width, a.height, a.mount) == (b.width, b.height, b.mount)
        assert np.array_equal(a.K, b.K) and np.array_equal(a.T_mount_cam, b.T_mount_cam)
    assert main(["export", str(ep_path), "--format", "act-hdf5", "--out", str(out), "--overwrite",
                 "--camera", CAMERAS[1]]) == 0  # an earlier export's sidecars go with its files
    assert sorted(p.name for p in out.iterdir()) == ["augmentation.json", "episode_0.calib.json", "episode_0.hdf5"]
    assert list(json.loads((out / "episode_0.calib.json").read_text())["cameras"]) == [CAMERAS[1]]


def test_the_calibration_names_a_urdf_by_its_absolute_path(tmp_path):
    """An episode names its URDF relative to its folder; the sidecar, beside the export, by its
    absolute path (import-act resolves a relative one against the sidecar's folder)."""
    from manisplat.episode.exporters.act_calibration import _description

    ep_path, _, _ = _imported(tmp_path)
    ep = Episode.open(ep_path)
    assert _description(ep, "builtin:agilex_piper") == {"description": "builtin:agilex_piper"}
    assert _description(ep, "robot/piper.urdf") == {"urdf": str((ep_path / "robot" / "piper.urdf").resolve())}


def test_compressed_act_export_pads_every_camera_to_one_length(tmp_path):
    ep_path, calib, _ = _imported(tmp_path)
    ep = Episode.open(ep_path)
    out = tmp_path / "act"
    assert main(["export", str(ep_path), "--format", "act-hdf5", "--out", str(out), "--compress"]) == 0
    with h5py.File(out / "episode_0.hdf5", "r") as f:
        lengths = f["compress_len"][()]
        assert lengths.shape == (3, T) and f.attrs["compress"]
        width = {f[f"observations/images/{cam}"].shape for cam in CAMERAS}
        assert width == {(T, int(lengths.max()))}  # one padded length for all cameras, as ALOHA writes them
        for c, cam in enumerate(CAMERAS):
            row = f[f"observations/images/{cam}"][2]
            assert not row[int(lengths[c, 2]):].any()
            expected = cv2.imdecode(cv2.imencode(".jpg", ep.rgb(2, cam), [cv2.IMWRITE_JPEG_QUALITY, 90])[1], 1)
            assert np.array_equal(cv2.imdecode(row, cv2.IMREAD_COLOR), expected)
    back = tmp_path / "back"
    assert main(["import-act", str(out / "episode_0.hdf5"), "--calib", str(calib), "--out", str(back)]) == 0
    assert np.array_equal(_joints(Episode.open(back)), _joints(ep))


def test_lerobot_export_has_14_d_state_and_a_video_per_camera(tmp_path):
    ep_path, _, data = _imported(tmp_path)
    out = tmp_path / "ds"
    assert main(["export", str(ep_path), "--format", "lerobot", "--out", str(out), "--codec", "h264",
                 "--task", "handover"]) == 0
    info = json.loads((out / "meta" / "info.json").read_text())
    features = info["features"]
    assert features["observation.state"] == {"dtype": "float32", "shape": [14], "names": NAMES}
    assert features["action"]["shape"] == [14]
    videos = [k for k, f in features.items() if f["dtype"] == "video"]
    assert videos == [f"observation.images.{c}" for c in CAMERAS]
    assert [k for k in features if k.startswith("depth.")] == ["depth.cam_high"]  # the one camera with depth
    rows = pq.read_table(out / "data" / "chunk-000" / "file-000.parquet")
    assert np.array_equal(np.array(rows.column("observation.state").to_pylist(), dtype=np.float32),
                          data["qpos"].astype(np.float32))
    assert np.array_equal(np.array(rows.column("depth.cam_high").to_pylist()[3], dtype=np.uint16), data["depth"][3])
    episodes = pq.read_table(out / "meta" / "episodes" / "chunk-000" / "file-000.parquet").to_pylist()[0]
    stats = json.loads((out / "meta" / "stats.json").read_text())
    for key in videos:
        assert episodes[f"videos/{key}/to_timestamp"] == pytest.approx(T / 20)
        assert np.array(stats[key]["mean"]).shape == (3, 1, 1)
        with av.open(str(out / "videos" / key / "chunk-000" / "file-000.mp4")) as video:
            assert sum(1 for _ in video.decode(video=0)) == T
    record = json.loads((out / "meta" / "augmentation.json").read_text())
    assert record["cameras"] == list(CAMERAS) and record["depth_cameras"] == ["cam_high"]


def test_import_lerobot_reads_every_arm_and_camera_back(tmp_path, capsys):
    ep_path, calib, data = _imported(tmp_path)
    out = tmp_path / "ds"
    assert main(["export", str(ep_path), "--format", "lerobot", "--out", str(out), "--codec", "h264", "--crf", "0",
                 "--task", "handover"]) == 0
    back = tmp_path / "back"
    capsys.readouterr()
    assert main(["import-lerobot", str(out), "--episode", "0", "--calib", str(calib), "--units", "rad,m",
                 "--out", str(back)]) == 0
    assert "arms left, right, cameras cam_high, cam_left_wrist, cam_right_wrist" in capsys.readouterr().out
    first, again = Episode.open(ep_path), Episode.open(back)
    assert again.meta.version == 2 and list(again.cameras) == list(CAMERAS)
    assert all(again.chroma_subsampling(c) == StoredChroma("4:2:0", False) for c in CAMERAS)  # the videos'
    report = validate(back)
    assert report.ok and not report.warnings, str(report)
    assert np.array_equal(_joints(again), _joints(first))  # float32 stored, widened exactly both ways
    for arm in ("left", "right"):
        assert np.array_equal(again.arm_frames(arm).actions, first.arm_frames(arm).actions)
    assert np.array_equal(again.cameras["cam_left_wrist"].T_mount_cam, first.cameras["cam_left_wrist"].T_mount_cam)
    assert np.array_equal(np.rint(again.depth(3, "cam_high") / 1e-3).astype(np.uint16), data["depth"][3])
    assert again.depth(3, "cam_left_wrist") is None
    def gray(ep, cam):  # yuv420p halves the colour of these noise images; brightness survives CRF 0
        return cv2.cvtColor(ep.rgb(4, cam), cv2.COLOR_RGB2GRAY).astype(int)

    for cam, other in zip(CAMERAS, CAMERAS[1:] + CAMERAS[:1]):  # each camera's own frames, in order
        error = np.abs(gray(again, cam) - gray(first, cam)).mean()
        assert error < 8 and error < np.abs(gray(again, cam) - gray(first, other)).mean() / 4, error


def add_effort(dataset, effort: np.ndarray) -> None:
    """Give a one-episode LeRobot dataset an ``observation.effort`` feature (T, D) as ALOHA-style
    datasets have (float32, laid out like ``observation.state``)."""
    info_path = dataset / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    info["features"]["observation.effort"] = {"dtype": "float32", "shape": [effort.shape[1]], "names": None}
    info_path.write_text(json.dumps(info, indent=4))
    path = dataset / "data" / "chunk-000" / "file-000.parquet"
    rows = pq.read_table(path)
    column = pa.array(effort.astype(np.float32).tolist(), type=pa.list_(pa.float32(), effort.shape[1]))
    pq.write_table(rows.append_column("observation.effort", column), path)


def test_import_lerobot_reads_each_grippers_effort(tmp_path, capsys):
    """observation.effort's gripper columns become each arm's gripper_effort (what dates releases)."""
    ep_path, calib, data = _imported(tmp_path)
    out = tmp_path / "ds"
    assert main(["export", str(ep_path), "--format", "lerobot", "--out", str(out), "--codec", "h264",
                 "--task", "handover", "--no-depth"]) == 0
    command = ["import-lerobot", str(out), "--episode", "0", "--calib", str(calib), "--units", "rad,m"]
    assert main([*command, "--out", str(tmp_path / "without")]) == 0
    assert "gripper_effort" not in Episode.open(tmp_path / "without").arm_frames("left").extra
    add_effort(out, data["effort"])
    assert main([*command, "--out", str(tmp_path / "back")]) == 0
    back = Episode.open(tmp_path / "back")
    stored = data["effort"].astype(np.float32).astype(np.float64)
    for arm, gripper in (("left", 6), ("right", 13)):
        assert np.array_equal(back.arm_frames(arm).extra["gripper_effort"], stored[:, gripper])
    assert validate(tmp_path / "back").ok
    add_effort(out, data["effort"][:, :12])  # a layout whose grippers cannot be told
    capsys.readouterr()
    assert main([*command, "--out", str(tmp_path / "bad")]) == 2
    assert "observation.effort has shape [12]; expected observation.state's [14]" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_import_lerobot_needs_units_and_refuses_values_not_in_them(tmp_path, capsys):
    ep_path, calib, data = _imported(tmp_path, degrees=True)
    out = tmp_path / "ds"
    assert main(["export", str(ep_path), "--format", "lerobot", "--out", str(out), "--codec", "h264",
                 "--task", "handover", "--no-depth"]) == 0
    command = ["import-lerobot", str(out), "--episode", "0", "--calib", str(calib), "--out", str(tmp_path / "back")]
    capsys.readouterr()
    assert main(command) == 2
    err = capsys.readouterr().err
    assert "joint and gripper units are not declared" in err and "stored values: left: joints -" in err
    assert "--units JOINT,GRIPPER" in err
    assert main([*command, "--units", "normalized"]) == 2
    assert "normalised to +-100 depend on the per-joint ranges" in capsys.readouterr().err
    assert main([*command, "--units", "rad,m"]) == 2
    err = capsys.readouterr().err
    assert "not in the declared units rad,m: arm left: joints up to" in err and "are not radians" in err
    assert not (tmp_path / "back").exists()
    assert main([*command, "--units", "deg,m"]) == 0
    stored = data["qpos"].astype(np.float32).astype(np.float64)
    left = Episode.open(tmp_path / "back").arm_frames("left")
    assert np.array_equal(left.q, stored[:, :6] * (np.pi / 180)) and np.array_equal(left.gripper, stored[:, 6])
    assert main([*command, "--units", "deg,mm", "--overwrite"]) == 0
    assert np.array_equal(Episode.open(tmp_path / "back").arm_frames("right").gripper, stored[:, 13] * 0.001)


def test_import_lerobot_options_of_one_kind_only(tmp_path, capsys):
    ep_path, calib, _ = _imported(tmp_path)
    out = tmp_path / "ds"
    assert main(["export", str(ep_path), "--format", "lerobot", "--out", str(out), "--codec", "h264",
                 "--task", "handover"]) == 0
    capsys.readouterr()
    assert main(["import-lerobot", str(out), "--episode", "0", "--out", str(tmp_path / "b")]) == 2
    assert "a one-arm import needs --camera and --K" in capsys.readouterr().err
    assert main(["import-lerobot", str(out), "--episode", "0", "--calib", str(calib), "--units", "rad,m",
                 "--K", "30,30,15.5,11.5", "--out", str(tmp_path / "b")]) == 2
    assert "--K belong to a one-arm import" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()


def test_cameras_and_image_keys_can_be_chosen(tmp_path, capsys):
    ep_path, _, data = _imported(tmp_path)
    out = tmp_path / "act"
    assert main(["export", str(ep_path), "--format", "act-hdf5", "--out", str(out), "--camera", "cam_high",
                 "--camera", "cam_right_wrist", "--image-key", "cam_high=top"]) == 0
    with h5py.File(out / "episode_0.hdf5", "r") as f:
        assert sorted(f["observations/images"]) == ["cam_right_wrist", "top"]
        assert np.array_equal(f["observations/images/top"][()], data["images"]["cam_high"])
    capsys.readouterr()
    assert main(["export", str(ep_path), "--format", "act-hdf5", "--out", str(tmp_path / "x"),
                 "--image-key", "top"]) == 2
    assert "one image key 'top' for 3 cameras" in capsys.readouterr().err
    assert main(["export", str(ep_path), "--format", "act-hdf5", "--out", str(tmp_path / "x"),
                 "--camera", "cam_low"]) == 2
    assert "no camera 'cam_low'; the episode's cameras are 'cam_high'" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_episodes_with_other_arms_cannot_share_an_export(tmp_path, capsys):
    ep_path, _, _ = _imported(tmp_path)
    one_arm = write_episode(tmp_path / "one_arm", frames=5)
    with pytest.raises(EpisodeFormatError, match="different arms cannot share one ACT export.*ep left, right, "
                                                 "one_arm arm"):
        export_act_hdf5([ep_path, one_arm], tmp_path / "act")
    assert not (tmp_path / "act").exists()


def test_one_arm_import_lerobot_converts_declared_units(tmp_path):
    """--units applies to a one-arm import too (default there: radians and metres, as stored)."""
    src = write_episode(tmp_path / "one_arm", frames=5)
    assert main(["export", str(src), "--format", "lerobot", "--out", str(tmp_path / "ds"), "--codec", "h264",
                 "--task", "reach", "--no-depth"]) == 0
    command = ["import-lerobot", str(tmp_path / "ds"), "--episode", "0", "--camera", "test", "--K", "30,30,15.5,11.5"]
    assert main([*command, "--out", str(tmp_path / "si")]) == 0
    assert main([*command, "--units", "deg,mm", "--out", str(tmp_path / "deg")]) == 0
    si, deg = Episode.open(tmp_path / "si").frames, Episode.open(tmp_path / "deg").frames
    assert np.array_equal(si.q, Episode.open(src).frames.q.astype(np.float32))
    assert np.array_equal(deg.q, si.q * (np.pi / 180)) and np.array_equal(deg.gripper, si.gripper * 0.001)


@pytest.mark.parametrize("arm, gripper", [("left", 6), ("right", 13)])
def test_one_arm_import_lerobot_reads_its_grippers_effort(tmp_path, arm, gripper):
    ep_path, _, data = _imported(tmp_path)
    assert main(["export", str(ep_path), "--format", "lerobot", "--out", str(tmp_path / "ds"), "--codec", "h264",
                 "--task", "handover", "--no-depth"]) == 0
    add_effort(tmp_path / "ds", data["effort"])
    assert main(["import-lerobot", str(tmp_path / "ds"), "--episode", "0", "--camera", "cam_high", "--arm", arm,
                 "--K", "30,30,15.5,11.5", "--out", str(tmp_path / "one")]) == 0
    effort = Episode.open(tmp_path / "one").frames.extra["gripper_effort"]
    assert np.array_equal(effort, data["effort"].astype(np.float32).astype(np.float64)[:, gripper])
