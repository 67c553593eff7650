"""benchmarks.bench_reconstruct_cobot --supersample: a sample's copy whose images are its states
drawn as a camera would record them, stored as the recorder stored the sample's."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from benchmarks import bench_reconstruct_cobot
from benchmarks.bench_reconstruct_cobot import CAMERAS, camera_like
from benchmarks.bench_sim_shadow_map import recorder_jpeg, recorder_jpeg_bytes

FRAMES, H, W = 2, 24, 32


def _sample(data: Path) -> Path:
    """A two-frame Cobot Magic sample: every camera's frames grey JPEGs (ALOHA's padding), its
    joints, depth, truth, objects and calibration."""
    sample = data / "cobot_tiny"
    sample.mkdir(parents=True)
    grey = [recorder_jpeg_bytes(np.full((H, W, 3), 128, np.uint8), 90) for _ in range(FRAMES)]
    with h5py.File(sample / "episode_0.hdf5", "w") as f:
        for camera in CAMERAS:
            padded = np.zeros((FRAMES, max(map(len, grey)) + 7), np.uint8)
            for k, encoded in enumerate(grey):
                padded[k, :len(encoded)] = np.frombuffer(encoded, np.uint8)
            f.create_dataset(f"observations/images/{camera}", data=padded)
            f.create_dataset(f"observations/images_depth/{camera}", data=np.full((FRAMES, H, W), 700, np.uint16))
        f["observations/qpos"] = np.arange(FRAMES * 14, dtype=float).reshape(FRAMES, 14)
        f["compress_len"] = np.full((len(CAMERAS), FRAMES), len(grey[0]), np.float32)
        f.attrs["compress"] = True
    np.savez(sample / "episode_0.gt.npz", q=np.zeros((FRAMES, 14)), T_world_box=np.tile(np.eye(4), (FRAMES, 1, 1)),
             info=json.dumps({"args": {"jpeg_quality": 90}}))
    (sample / "episode_0.objects.json").write_text(json.dumps({"task": "dual_pick_place", "objects": {"box": {}}}))
    (sample / "episode_0.calib.json").write_text("{}")
    return sample


def _drawn(folder: Path) -> dict[str, list[np.ndarray]]:
    """What the state renderer would have drawn into ``folder`` (its report present, so nothing
    runs): each camera's frames a colour of their own."""
    drawn = folder / "cobot_tiny_drawn"
    images = {}
    for c, camera in enumerate(CAMERAS):
        (drawn / camera / "rgb").mkdir(parents=True)
        images[camera] = [np.full((H, W, 3), (40 + 60 * c, 200 - 50 * k, 90), np.uint8) for k in range(FRAMES)]
        for k, rgb in enumerate(images[camera]):
            cv2.imwrite(str(drawn / camera / "rgb" / f"{k:06d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    (drawn / "render.json").write_text("{}")
    return images


def test_the_copy_holds_the_drawn_images_as_the_recorder_stores_them_and_keeps_the_rest(tmp_path):
    sample = _sample(tmp_path / "data")
    folder = tmp_path / "camera_like_x3"
    drawn = _drawn(folder)
    original = (sample / "episode_0.hdf5").read_bytes()

    assert camera_like(tmp_path / "no_simulator", tmp_path / "data", "cobot_tiny", folder, 3) == folder / "data"

    assert (sample / "episode_0.hdf5").read_bytes() == original  # the source is not touched
    assert (folder / "robots").is_symlink()  # where the calibration's "../../robots/..." leads
    with h5py.File(folder / "data" / "cobot_tiny" / "episode_0.hdf5", "r") as f:
        for row, camera in enumerate(CAMERAS):
            stored = np.asarray(f[f"observations/images/{camera}"])
            for k in range(FRAMES):
                length = int(f["compress_len"][row, k])
                assert stored[k, length:].sum() == 0 and stored[k, length - 2:length].tolist() == [0xFF, 0xD9]
                decoded = cv2.imdecode(stored[k, :length], cv2.IMREAD_COLOR)
                assert np.array_equal(decoded, recorder_jpeg(drawn[camera][k], 90))  # the recorder's bytes
        assert np.array_equal(f["observations/qpos"], np.arange(FRAMES * 14, dtype=float).reshape(FRAMES, 14))
        assert np.all(np.asarray(f["observations/images_depth/cam_high"]) == 700)
    for name in ("episode_0.gt.npz", "episode_0.objects.json", "episode_0.calib.json"):
        assert (folder / "data" / "cobot_tiny" / name).read_bytes() == (sample / name).read_bytes()


def test_a_copy_made_before_is_kept(tmp_path):
    _sample(tmp_path / "data")
    folder = tmp_path / "camera_like_x3"
    _drawn(folder)
    camera_like(tmp_path / "no_simulator", tmp_path / "data", "cobot_tiny", folder, 3)
    made = (folder / "data" / "cobot_tiny" / "episode_0.hdf5").stat().st_mtime_ns
    camera_like(tmp_path / "no_simulator", tmp_path / "data", "cobot_tiny", folder, 3)
    assert (folder / "data" / "cobot_tiny" / "episode_0.hdf5").stat().st_mtime_ns == made


@pytest.mark.parametrize("n", ["0", "2"])
def test_supersampling_asks_for_an_odd_factor(n, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        bench_reconstruct_cobot.main(["--supersample", n, "--data", str(tmp_path), "--out", str(tmp_path / "r.json")])
    assert stop.value.code == 2 and "--supersample takes an odd number" in capsys.readouterr().err


@pytest.mark.parametrize("px", ["0", "-2048", "fine"])
def test_the_shadow_map_asks_for_a_positive_size(px, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        bench_reconstruct_cobot.main(["--shadow-map-px", px, "--data", str(tmp_path), "--out", str(tmp_path / "r.json")])
    assert stop.value.code == 2 and "argument --shadow-map-px:" in capsys.readouterr().err
