"""import-act --calib: a whole Cobot Magic HDF5 file (two arms, three cameras) as a version 2 episode."""

from __future__ import annotations

import copy
import json

import h5py
import numpy as np
import pytest

from manisplat.episode import Episode, EpisodeFormatError, validate
from manisplat.episode.cli import main
from manisplat.episode.images import StoredChroma
from manisplat.episode.importers.cobot_magic import import_cobot_magic

from episode_factory import jpeg_rows

T, W, H = 5, 32, 24
CAMERAS = ("cam_high", "cam_left_wrist", "cam_right_wrist")
C, S = np.cos(np.radians(32.0)), np.sin(np.radians(32.0))
T_WRIST = [[-1.0, 0.0, 0.0, 0.0], [0.0, -C, -S, 0.075], [0.0, -S, C, 0.05], [0.0, 0.0, 0.0, 1.0]]
CALIB = {
    "fps": 20.0,
    "cameras": {
        "cam_high": {"K": [[30.0, 0.0, 15.5], [0.0, 30.0, 11.5], [0.0, 0.0, 1.0]], "dist": [], "width": W,
                     "height": H, "mount": "world",
                     "T_mount_cam": [[0.0, -1.0, 0.0, -0.25], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.75],
                                     [0.0, 0.0, 0.0, 1.0]], "depth": {"unit_m": 0.001}},
        "cam_left_wrist": {"K": [[25.0, 0.0, 15.5], [0.0, 25.0, 11.5], [0.0, 0.0, 1.0]], "dist": [],
                           "mount": "left/link6", "T_mount_cam": T_WRIST},
        "cam_right_wrist": {"K": [[25.0, 0.0, 15.5], [0.0, 25.0, 11.5], [0.0, 0.0, 1.0]], "dist": [],
                            "mount": "right/link6", "T_mount_cam": T_WRIST},
    },
    "arms": {
        "left": {"T_world_base": [[1.0, 0, 0, 0], [0, 1.0, 0, 0.3], [0, 0, 1.0, 0], [0, 0, 0, 1.0]],
                 "description": "builtin:agilex_piper"},
        "right": {"T_world_base": [[1.0, 0, 0, 0], [0, 1.0, 0, -0.3], [0, 0, 1.0, 0], [0, 0, 0, 1.0]],
                  "description": "builtin:agilex_piper"},
    },
}


def write_cobot(path, *, compress: bool, dtype: str = "float64") -> dict:
    """A Cobot Magic HDF5 file of T frames: (T, 14) qpos, effort and action, three 32x24 cameras (JPEG rows
    padded with zeros plus compress_len when ``compress``), depth for cam_high only. Returns the
    arrays a reader must get back (decoded images for compressed files)."""
    rng = np.random.default_rng(7)
    data = {"qpos": rng.uniform(-2, 2, (T, 14)).astype(dtype), "action": rng.uniform(-2, 2, (T, 14)).astype(dtype),
            "effort": rng.uniform(-1, 1, (T, 14)).astype(dtype),
            "images": {c: rng.integers(0, 256, (T, H, W, 3), dtype=np.uint8) for c in CAMERAS},
            "depth": rng.integers(1, 3000, (T, H, W), dtype=np.uint16)}
    data["qpos"][:, [6, 13]] = rng.uniform(0, 0.07, (T, 2)).astype(dtype)
    with h5py.File(path, "w") as f:
        f.attrs["sim"], f.attrs["compress"] = True, compress
        f["observations/qpos"] = data["qpos"]
        f["observations/qvel"] = np.zeros((T, 14))
        f["observations/effort"] = data["effort"]
        f["action"] = data["action"]
        if compress:
            rows, data["images"], lengths = jpeg_rows(data["images"])
            for c in CAMERAS:
                f[f"observations/images/{c}"] = rows[c]
            f["compress_len"] = lengths.astype(np.float32)
        else:
            for c in CAMERAS:
                f[f"observations/images/{c}"] = data["images"][c]
        f["observations/images_depth/cam_high"] = data["depth"]
    return data


def write_calib(path, calib=CALIB):
    path.write_text(json.dumps(calib))
    return path


@pytest.mark.parametrize("compress, dtype", [(False, "float64"), (True, "float32")])
def test_import_every_arm_and_camera(tmp_path, capsys, compress, dtype):
    data = write_cobot(tmp_path / "episode_0.hdf5", compress=compress, dtype=dtype)
    calib = write_calib(tmp_path / "episode_0.calib.json")
    out = tmp_path / "ep"
    assert main(["import-act", str(tmp_path / "episode_0.hdf5"), "--calib", str(calib), "--out", str(out)]) == 0
    assert "imported 5 frames of the arms left, right and the cameras cam_high" in capsys.readouterr().out
    report = validate(out)
    assert report.ok and not report.warnings, str(report)
    assert main(["info", str(out)]) == 0
    info = capsys.readouterr().out
    assert "format    version 2: 2 arm(s) left, right; 3 camera(s) cam_high, cam_left_wrist, cam_right_wrist" in info
    assert "base at (0.000, -0.300, 0.000) m" in info and "mount right/link6" in info

    ep = Episode.open(out)
    assert ep.meta.version == 2 and ep.meta.fps == 20.0 and np.array_equal(ep.camera_times("cam_high"), np.arange(T) / 20)
    qpos = data["qpos"].astype(np.float64)  # float32 widens exactly: the stored values, bit for bit
    action = data["action"].astype(np.float64)
    for arm, cols in (("left", slice(0, 7)), ("right", slice(7, 14))):
        table = ep.arm_frames(arm)
        assert np.array_equal(table.q, qpos[:, cols][:, :6]) and np.array_equal(table.gripper, qpos[:, cols][:, 6])
        assert np.array_equal(table.actions, action[:, cols])
        assert np.array_equal(table.extra["gripper_effort"], data["effort"][:, cols][:, 6].astype(np.float64))
    header = (out / "frames.csv").read_text().split("\n")[0].split(",")
    rows = np.array([[float(v) for v in line.split(",")] for line in (out / "frames.csv").read_text().split("\n")[1:-1]])
    assert np.array_equal(rows[:, header.index("right.q4")], qpos[:, 10])  # the text itself reads back exactly
    for cam in CAMERAS:
        assert all(np.array_equal(ep.rgb(i, cam), data["images"][cam][i]) for i in range(T))
    assert np.array_equal(np.rint(ep.depth(3, "cam_high") / 1e-3).astype(np.uint16), data["depth"][3])
    assert ep.depth(3, "cam_left_wrist") is None
    assert np.array_equal(ep.cameras["cam_left_wrist"].T_mount_cam, T_WRIST)
    assert ep.cameras["cam_left_wrist"].width == W and ep.meta.extra["import"]["compress"] is compress
    # JPEG rows: how the recorder's encoder kept the colour (cv2.imencode of RGB arrays: red taken for blue)
    assert all(ep.chroma_subsampling(c) == (StoredChroma("4:2:0", True) if compress else None) for c in CAMERAS)
    with pytest.raises(EpisodeFormatError, match="has arms left, right: this tool reads one-arm episodes"):
        ep.frames


def test_an_effort_of_another_shape_is_named(tmp_path):
    write_cobot(tmp_path / "e.hdf5", compress=False)
    with h5py.File(tmp_path / "e.hdf5", "a") as f:
        del f["observations/effort"]
        f["observations/effort"] = np.zeros((T, 12))
    with pytest.raises(EpisodeFormatError, match=r"/observations/effort has shape \(5, 12\); expected \(5, 14\)"):
        import_cobot_magic(tmp_path / "e.hdf5", tmp_path / "ep", write_calib(tmp_path / "e.calib.json"))
    assert not (tmp_path / "ep").exists()


def test_without_calibration_the_error_names_what_is_missing(tmp_path, capsys):
    write_cobot(tmp_path / "e.hdf5", compress=False)
    assert main(["import-act", str(tmp_path / "e.hdf5"), "--out", str(tmp_path / "ep")]) == 2
    err = capsys.readouterr().err
    for text in ("holds 3 camera(s) (cam_high, cam_left_wrist, cam_right_wrist) and arms (left, right) but no "
                 "calibration", "K (intrinsics), mount", "T_mount_cam", "T_world_base", "--calib FILE.calib.json",
                 "--arm left|right --camera NAME --K"):
        assert text in err
    assert not (tmp_path / "ep").exists()


def test_incomplete_calibration_names_the_fields(tmp_path):
    write_cobot(tmp_path / "e.hdf5", compress=False)
    calib = copy.deepcopy(CALIB)
    del calib["cameras"]["cam_right_wrist"]["K"]
    calib["cameras"]["cam_left_wrist"]["mount"] = "middle/link6"
    del calib["arms"]["right"]["T_world_base"]
    with pytest.raises(EpisodeFormatError) as info:
        import_cobot_magic(tmp_path / "e.hdf5", tmp_path / "ep", write_calib(tmp_path / "c.json", calib))
    for text in ("c.json: ", "cameras.cam_right_wrist.K is missing", "cameras.cam_left_wrist.mount 'middle/link6' "
                 "names the arm 'middle'", "arms.right.T_world_base is missing"):
        assert text in str(info.value)
    calib = copy.deepcopy(CALIB)
    del calib["cameras"]["cam_high"]
    with pytest.raises(EpisodeFormatError, match="no camera cam_high \\(the file e.hdf5 has cam_high, cam_left_wrist"):
        import_cobot_magic(tmp_path / "e.hdf5", tmp_path / "ep", write_calib(tmp_path / "c.json", calib))
    calib = copy.deepcopy(CALIB)
    del calib["fps"]
    with pytest.raises(EpisodeFormatError, match="no frame rate: give --fps"):
        import_cobot_magic(tmp_path / "e.hdf5", tmp_path / "ep", write_calib(tmp_path / "c.json", calib))
    calib["cameras"]["cam_high"]["width"] = 64
    with pytest.raises(EpisodeFormatError, match="images are 32x24 but .* says 64x24"):
        import_cobot_magic(tmp_path / "e.hdf5", tmp_path / "ep", write_calib(tmp_path / "c.json", calib), fps=30)
    assert not (tmp_path / "ep").exists()


def test_calib_and_one_arm_options_do_not_mix(tmp_path, capsys):
    write_cobot(tmp_path / "e.hdf5", compress=False)
    argv = ["import-act", str(tmp_path / "e.hdf5"), "--calib", str(write_calib(tmp_path / "c.json")), "--out",
            str(tmp_path / "ep")]
    assert main([*argv, "--arm", "left", "--K", "30,30,16,12"]) == 2
    assert "--K, --arm belong to a one-arm import" in capsys.readouterr().err
    assert main([*argv, "--fps", "10"]) == 0 and Episode.open(tmp_path / "ep").meta.fps == 10
