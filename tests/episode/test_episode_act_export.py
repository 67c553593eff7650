"""export_act_hdf5() / ``manisplat-episode export --format act-hdf5``: layout, round trips through
import-act, provenance, and bad input refused before anything is written."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from episode_factory import mark_incomplete, write_episode

from manisplat.episode import EpisodeFormatError, EpisodeWriter, import_act_hdf5
from manisplat.episode.cli import main
from manisplat.episode.exporters import export_act_hdf5
from manisplat.episode.exporters.act_hdf5 import ExportDestinationError, velocities
from manisplat.episode.meta import CameraInfo, RobotInfo
from manisplat.episode.reader import Episode
from manisplat.episode.synthetic import write_sample_episode

FPS = 16.0


@pytest.fixture(scope="module")
def sample(tmp_path_factory) -> Path:
    """The sample episode (16 frames, 64x48, 16 fps, with actions); tests must not modify it."""
    return write_sample_episode(tmp_path_factory.mktemp("sample") / "demo", frames=16, fps=FPS, width=64,
                                height=48)


def _copy(src: Path, dst: Path, **meta_changes) -> Path:
    shutil.copytree(src, dst)
    meta = json.loads((dst / "episode.json").read_text())
    (dst / "episode.json").write_text(json.dumps({**meta, **meta_changes}))
    return dst


def _import(path: Path, ep: Episode, tmp: Path, name: str) -> Episode:
    return import_act_hdf5(path, tmp / name, K=ep.camera, arm="single", camera=ep.camera.name, fps=ep.meta.fps)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)


def test_layout_and_float64_round_trip_is_bit_exact(sample, tmp_path):
    ep = Episode.open(sample)
    export_act_hdf5([sample], tmp_path / "out", dtype="float64")
    path = tmp_path / "out" / "episode_0.hdf5"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["augmentation.json", "episode_0.hdf5"]
    T, H, W = len(ep), 48, 64
    with h5py.File(path, "r") as f:
        assert f.attrs["sim"] is np.True_ and f.attrs["compress"] is np.False_ and f.attrs["fps"] == FPS
        assert f.attrs["manisplat_source"] == "simulation" and "manisplat_parent" not in f.attrs
        for name in ("observations/qpos", "observations/qvel", "action"):
            assert f[name].shape == (T, 7) and f[name].dtype == np.float64, name
        images = f["observations/images/ego"]
        assert images.shape == (T, H, W, 3) and images.dtype == np.uint8 and images.chunks == (1, H, W, 3)
        assert f["action"].attrs["source"] == "actions" and "compress_len" not in f
        qpos = np.concatenate([ep.frames.q, ep.frames.gripper[:, None]], axis=1)
        assert np.array_equal(f["observations/qvel"][:], velocities(ep.frames.t, qpos))
        assert np.array_equal(f["observations/qvel"][0], np.zeros(7))
        assert np.allclose(f["observations/qvel"][3], (qpos[3] - qpos[2]) / (ep.frames.t[3] - ep.frames.t[2]))
    back = _import(path, ep, tmp_path, "back")
    assert np.array_equal(back.frames.q, ep.frames.q) and np.array_equal(back.frames.gripper, ep.frames.gripper)
    assert np.array_equal(back.frames.actions, ep.frames.actions)
    assert np.array_equal(back.frames.t, np.arange(T) / FPS)
    for i in range(T):
        assert np.array_equal(back.rgb(i), ep.rgb(i))


def test_float32_default_round_trips_to_float32_precision(tmp_path):
    src = write_episode(tmp_path / "ep")  # full float64 precision joints
    ep = Episode.open(src)
    export_act_hdf5([src], tmp_path / "out")
    with h5py.File(tmp_path / "out" / "episode_0.hdf5", "r") as f:
        assert f["observations/qpos"].dtype == np.float32 and f["action"].dtype == np.float32
    back = _import(tmp_path / "out" / "episode_0.hdf5", ep, tmp_path, "back")
    assert np.array_equal(back.frames.q, ep.frames.q.astype(np.float32).astype(np.float64))
    assert np.array_equal(back.frames.actions, ep.frames.actions.astype(np.float32).astype(np.float64))
    assert not np.array_equal(back.frames.q, ep.frames.q)  # float32 does lose bits: the flag matters
    assert np.max(np.abs(back.frames.q - ep.frames.q)) < 2e-7


def test_compressed_as_aloha_writes_it(sample, tmp_path):
    ep = Episode.open(sample)
    assert main(["export", str(sample), "--format", "act-hdf5", "--out", str(tmp_path / "out"), "--compress",
                 "--image-key", "cam_high"]) == 0
    path = tmp_path / "out" / "episode_0.hdf5"
    with h5py.File(path, "r") as f:
        assert f.attrs["compress"] is np.True_
        ds, lengths = f["observations/images/cam_high"], f["compress_len"][:]
        assert ds.ndim == 2 and ds.dtype == np.uint8 and ds.chunks == (1, ds.shape[1])
        assert lengths.shape == (1, len(ep)) and lengths.dtype == np.float32 and lengths.max() == ds.shape[1]
        for i in range(len(ep)):
            row, n = ds[i], int(lengths[0, i])
            assert bytes(row[:2]) == b"\xff\xd8" and bytes(row[n - 2:n]) == b"\xff\xd9" and not row[n:].any()
    back = import_act_hdf5(path, tmp_path / "back", K=ep.camera.K, arm="single", camera="cam_high", fps=FPS)
    assert back.meta.extra["import"]["compress"] is True
    assert np.array_equal(back.frames.q, ep.frames.q.astype(np.float32).astype(np.float64))
    for i in range(len(ep)):
        assert _psnr(back.rgb(i), ep.rgb(i)) > 30.0, i


def test_without_actions_the_action_is_the_next_qpos(tmp_path):
    rng = np.random.default_rng(3)
    cam = CameraInfo(name="ego", width=32, height=24, K=np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]]))
    with EpisodeWriter(tmp_path / "ep", cam, RobotInfo(), 10.0) as writer:
        for i in range(5):
            writer.add_frame(i * 0.1 + 0.01 * i * i, rng.uniform(-1, 1, 6), 0.01 * i,
                             rng.integers(0, 256, (24, 32, 3), dtype=np.uint8))
    ep = Episode.open(tmp_path / "ep")
    entries = export_act_hdf5([tmp_path / "ep"], tmp_path / "out", dtype="float64")
    qpos = np.concatenate([ep.frames.q, ep.frames.gripper[:, None]], axis=1)
    with h5py.File(tmp_path / "out" / "episode_0.hdf5", "r") as f:
        assert f["action"].attrs["source"] == "next_qpos" and entries[0]["action"] == "next_qpos"
        assert np.array_equal(f["action"][:], np.concatenate([qpos[1:], qpos[-1:]]))
        assert f.attrs["sim"] is np.False_  # source recorder
        qvel = f["observations/qvel"][:]
    dt = np.diff(ep.frames.t)  # the frame times, not 1 / fps: these frames are unevenly spaced
    assert np.array_equal(qvel[0], np.zeros(7)) and np.allclose(qvel[1:], np.diff(qpos, axis=0) / dt[:, None])


def test_provenance_marks_augmented_episodes(sample, tmp_path):
    aug = _copy(sample, tmp_path / "episode_0003", source="augmentation", parent="demo")
    (aug / "augmentation.json").write_text(json.dumps({"parent": "demo", "seed": 7, "segments": []}))
    entries = export_act_hdf5([sample, aug], tmp_path / "out")
    record = json.loads((tmp_path / "out" / "augmentation.json").read_text())
    assert record["complete"] is True and record["files"] == entries and record["fps"] == FPS
    assert [(e["file"], e["source"], e["augmented"], e["parent"], e["seed"]) for e in entries] == [
        ("episode_0.hdf5", "simulation", False, None, None),
        ("episode_1.hdf5", "augmentation", True, "demo", 7)]
    assert entries[1]["episode"] == str(aug.resolve())
    with h5py.File(tmp_path / "out" / "episode_1.hdf5", "r") as f:
        assert f.attrs["manisplat_parent"] == "demo" and f.attrs["sim"] is np.True_


def test_mismatched_fps_and_sizes_refused_before_anything_is_written(sample, tmp_path):
    other = write_episode(tmp_path / "ep10hz")  # 10 fps, 32x24
    with pytest.raises(EpisodeFormatError, match="different fps.*demo 16, ep10hz 10"):
        export_act_hdf5([sample, other], tmp_path / "out")
    assert not (tmp_path / "out").exists()
    same_fps = _copy(other, tmp_path / "ep16hz", fps=FPS)
    with pytest.raises(EpisodeFormatError, match="different image sizes.*demo 64x48, ep16hz 32x24"):
        export_act_hdf5([sample, same_fps], tmp_path / "out")
    assert not (tmp_path / "out").exists()
    assert main(["export", str(sample), str(other), "--format", "act-hdf5", "--out", str(tmp_path / "out")]) == 2
    assert not (tmp_path / "out").exists()


def test_missing_camera_image_or_incomplete_episode_refused(sample, tmp_path):
    with pytest.raises(EpisodeFormatError, match="no camera 'cam_high'; the episode's camera is 'ego'"):
        export_act_hdf5([sample], tmp_path / "out", camera="cam_high")
    gap = _copy(sample, tmp_path / "gap")
    (gap / "rgb" / "000009.png").unlink()
    with pytest.raises(EpisodeFormatError, match="no image for 1 of 16 frames.*frame 9"):
        export_act_hdf5([sample, gap], tmp_path / "out")
    crashed = _copy(sample, tmp_path / "crashed")
    mark_incomplete(crashed)
    with pytest.raises(EpisodeFormatError, match="incomplete episode.*recover"):
        export_act_hdf5([crashed], tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_non_empty_out_refused_unless_overwrite(sample, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "episode_7.hdf5").write_bytes(b"an earlier export")
    with pytest.raises(ExportDestinationError, match="not empty; pass --overwrite"):
        export_act_hdf5([sample], out)
    assert main(["export", str(sample), "--format", "act-hdf5", "--out", str(out)]) == 2
    assert "is not empty" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["episode_7.hdf5", "notes.txt"]
    assert main(["export", str(sample), "--format", "act-hdf5", "--out", str(out), "--overwrite"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["augmentation.json", "episode_0.hdf5", "notes.txt"]
    (tmp_path / "file").write_text("x")
    assert main(["export", str(sample), "--format", "act-hdf5", "--out", str(tmp_path / "file")]) == 2


@pytest.mark.parametrize("compress", [False, True])
def test_a_failed_export_leaves_nothing_and_the_same_command_runs_again(sample, tmp_path, compress):
    broken = _copy(sample, tmp_path / "broken")
    data = (broken / "rgb" / "000011.png").read_bytes()
    (broken / "rgb" / "000011.png").write_bytes(data[: len(data) // 2])  # truncated: fails mid-episode
    out = tmp_path / "exports" / "out"
    command = ["export", str(sample), str(broken), "--format", "act-hdf5", "--out", str(out)] + ["--compress"] * compress
    with pytest.raises(EpisodeFormatError, match="000011.png: cannot decode"):
        export_act_hdf5([sample, broken, sample], out, compress=compress)
    assert list((tmp_path / "exports").iterdir()) == []  # neither OUT nor the hidden staging folder
    (broken / "rgb" / "000011.png").write_bytes(data)
    assert main(command) == 0
    assert sorted(p.name for p in out.iterdir()) == ["augmentation.json", "episode_0.hdf5", "episode_1.hdf5"]
    assert json.loads((out / "augmentation.json").read_text())["complete"] is True


def test_a_failed_overwrite_keeps_the_earlier_export(sample, tmp_path):
    out = tmp_path / "out"
    export_act_hdf5([sample], out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    broken = _copy(sample, tmp_path / "broken")
    (broken / "rgb" / "000003.png").write_bytes(b"not a png")
    with pytest.raises(EpisodeFormatError, match="000003.png: cannot decode"):
        export_act_hdf5([sample, broken], out, overwrite=True)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert not list(tmp_path.glob(".out.partial-*"))


def test_files_reach_out_only_when_all_are_written(sample, tmp_path, monkeypatch):
    out, seen = tmp_path / "out", []
    rgb = Episode.rgb

    def spy(self, i, camera=None):
        seen.append(out.exists())
        return rgb(self, i, camera)

    monkeypatch.setattr(Episode, "rgb", spy)
    export_act_hdf5([sample, sample], out)
    assert len(seen) == 32 and not any(seen)
    assert sorted(p.name for p in out.iterdir()) == ["augmentation.json", "episode_0.hdf5", "episode_1.hdf5"]


def test_fps_resamples_to_the_nearest_frames(sample, tmp_path):
    ep = Episode.open(sample)
    assert main(["export", str(sample), "--format", "act-hdf5", "--out", str(tmp_path / "out"), "--fps", "8",
                 "--float64"]) == 0
    with h5py.File(tmp_path / "out" / "episode_0.hdf5", "r") as f:
        assert f.attrs["fps"] == 8.0 and f["observations/qpos"].shape == (8, 7)
        assert np.array_equal(f["observations/qpos"][:, :6], ep.frames.q[::2])
        assert np.array_equal(f["action"][:], ep.frames.actions[::2])
        qpos = np.concatenate([ep.frames.q, ep.frames.gripper[:, None]], axis=1)[::2]
        assert np.array_equal(f["observations/qvel"][:], velocities(ep.frames.t[::2], qpos))
        assert np.array_equal(f["observations/images/ego"][3], ep.rgb(6))
    record = json.loads((tmp_path / "out" / "augmentation.json").read_text())
    assert record["fps"] == 8.0 and record["files"][0]["recorded_frames"] == [0, 14]
    with pytest.raises(EpisodeFormatError, match="below the export's 20 fps"):
        export_act_hdf5([sample], tmp_path / "out20", fps=20)
    assert not (tmp_path / "out20").exists()
