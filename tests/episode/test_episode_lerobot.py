"""export_lerobot() / import_lerobot() / ``manisplat-episode export --format lerobot`` and
``import-lerobot``: the LeRobot v3.0 layout and schema (as lerobot 0.4.4's own writer produces them),
timestamps, stats, file splitting, round trips, resampling, and bad input refused before anything
is written. lerobot itself is not needed (benchmarks/lerobot_side.py checks with its loader)."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from episode_factory import frame_data, mark_incomplete, open_writer, write_episode

from manisplat.episode import EpisodeFormatError
from manisplat.episode.cli import main
from manisplat.episode.exporters.lerobot import ExportDestinationError, export_lerobot
from manisplat.episode.exporters.lerobot_stats import QUANTILES, stats_sample_indices, vector_stats
from manisplat.episode.images import StoredChroma
from manisplat.episode.importers.lerobot import import_lerobot, stored_colour_keys
from manisplat.episode.reader import Episode
from manisplat.episode.synthetic import write_sample_episode

TASK = "pick the box and place it on the mat"
STATS = {"min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99"}
# what lerobot 0.4.4's LeRobotDataset.create/add_frame/save_episode/finalize writes (checked by hand)
INFO_KEYS = {"codebase_version", "robot_type", "total_episodes", "total_frames", "total_tasks", "chunks_size",
             "data_files_size_in_mb", "video_files_size_in_mb", "fps", "splits", "data_path", "video_path",
             "features"}
DATA_TYPES = {"observation.state": pa.list_(pa.float32(), 7), "action": pa.list_(pa.float32(), 7),
              "depth.ego": pa.list_(pa.list_(pa.uint16())), "timestamp": pa.float32(), "frame_index": pa.int64(),
              "episode_index": pa.int64(), "index": pa.int64(), "task_index": pa.int64()}
EPISODE_COLUMNS = {"episode_index": pa.int64(), "tasks": pa.list_(pa.string()), "length": pa.int64(),
                   "data/chunk_index": pa.int64(), "data/file_index": pa.int64(),
                   "dataset_from_index": pa.int64(), "dataset_to_index": pa.int64(),
                   "videos/observation.images.ego/chunk_index": pa.int64(),
                   "videos/observation.images.ego/file_index": pa.int64(),
                   "videos/observation.images.ego/from_timestamp": pa.float64(),
                   "videos/observation.images.ego/to_timestamp": pa.float64(),
                   "meta/episodes/chunk_index": pa.int64(), "meta/episodes/file_index": pa.int64()}
K = np.array([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def samples(tmp_path_factory) -> list[Path]:
    """Two sample episodes (16 frames, 64x48, 16 fps, with actions and depth); tests must not modify them."""
    root = tmp_path_factory.mktemp("samples")
    return [write_sample_episode(root / f"demo{s}", frames=16, fps=16.0, width=64, height=48, seed=s) for s in (0, 1)]


@pytest.fixture(scope="module")
def dataset(samples, tmp_path_factory) -> Path:
    """The two samples exported with defaults (float32, AV1, depth)."""
    out = tmp_path_factory.mktemp("export") / "ds"
    export_lerobot(samples, out, task=TASK)
    return out


def _copy(src: Path, dst: Path, **meta_changes) -> Path:
    shutil.copytree(src, dst)
    meta = json.loads((dst / "episode.json").read_text())
    (dst / "episode.json").write_text(json.dumps({**meta, **meta_changes}))
    return dst


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)


def _frame_times(path: Path) -> list[tuple[Fraction, bool]]:
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        return [(frame.pts * frame.time_base, frame.key_frame) for frame in container.decode(stream)]


def _rows(ds: Path, name: str = "data") -> pa.Table:
    files = sorted((ds / name).glob("*/*.parquet")) if name == "data" else sorted(
        (ds / "meta" / "episodes").glob("*/*.parquet"))
    return pa.concat_tables([pq.read_table(f) for f in files])


def test_layout_info_and_schemas_are_lerobot_v3(dataset):
    files = sorted(str(p.relative_to(dataset)) for p in dataset.rglob("*") if p.is_file())
    assert files == ["data/chunk-000/file-000.parquet", "meta/augmentation.json",
                     "meta/episodes/chunk-000/file-000.parquet", "meta/info.json", "meta/stats.json",
                     "meta/tasks.parquet", "videos/observation.images.ego/chunk-000/file-000.mp4"]
    info = json.loads((dataset / "meta" / "info.json").read_text())
    assert set(info) == INFO_KEYS
    assert (info["codebase_version"], info["robot_type"], info["fps"], info["total_episodes"], info["total_frames"],
            info["total_tasks"], info["splits"]) == ("v3.0", "piper", 16, 2, 32, 1, {"train": "0:2"})
    assert (info["chunks_size"], info["data_files_size_in_mb"], info["video_files_size_in_mb"]) == (1000, 100, 200)
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    assert info["video_path"] == "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    features = info["features"]
    assert list(features) == ["observation.state", "action", "observation.images.ego", "depth.ego", "timestamp",
                              "frame_index", "episode_index", "index", "task_index"]
    assert features["observation.state"] == {"dtype": "float32", "shape": [7],
                                             "names": ["q1", "q2", "q3", "q4", "q5", "q6", "gripper"]}
    video = features["observation.images.ego"]
    assert (video["dtype"], video["shape"], video["names"]) == ("video", [48, 64, 3], ["height", "width", "channels"])
    assert video["info"] == {"video.height": 48, "video.width": 64, "video.codec": "av1", "video.pix_fmt": "yuv420p",
                             "video.is_depth_map": False, "video.fps": 16, "video.channels": 3, "has_audio": False}
    assert features["depth.ego"] == {"dtype": "uint16", "shape": [48, 64], "names": ["height", "width"]}
    assert features["index"] == {"dtype": "int64", "shape": [1], "names": None}
    schema = pq.read_schema(dataset / "data" / "chunk-000" / "file-000.parquet")
    assert {f.name: f.type for f in schema} == DATA_TYPES
    hf = json.loads(schema.metadata[b"huggingface"])["info"]["features"]
    assert hf["observation.state"] == {"feature": {"dtype": "float32", "_type": "Value"}, "length": 7, "_type": "List"}
    assert hf["depth.ego"] == {"shape": [48, 64], "dtype": "uint16", "_type": "Array2D"}
    episodes = pq.read_schema(dataset / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    plain = {f.name: f.type for f in episodes if not f.name.startswith("stats/")}
    assert plain == EPISODE_COLUMNS
    stats_columns = {f.name for f in episodes if f.name.startswith("stats/")}
    assert stats_columns == {f"stats/{k}/{s}" for k in features if k != "observation.images.ego" or True
                             for s in STATS}
    assert episodes.field("stats/observation.images.ego/mean").type == pa.list_(pa.list_(pa.list_(pa.float64())))
    tasks = pq.read_table(dataset / "meta" / "tasks.parquet")
    assert tasks.column("__index_level_0__").to_pylist() == [TASK] and tasks.column("task_index").to_pylist() == [0]
    assert json.loads(tasks.schema.metadata[b"pandas"])["index_columns"] == ["__index_level_0__"]


def test_rows_timestamps_and_video_frames_line_up(dataset):
    data = _rows(dataset)
    frame_index = np.asarray(data.column("frame_index"))
    assert np.array_equal(frame_index, np.tile(np.arange(16), 2))
    assert np.array_equal(np.asarray(data.column("episode_index")), np.repeat([0, 1], 16))
    assert np.array_equal(np.asarray(data.column("index")), np.arange(32))
    assert not np.asarray(data.column("task_index")).any()
    timestamps = np.asarray(data.column("timestamp"))
    assert timestamps.dtype == np.float32 and np.array_equal(timestamps, (frame_index / 16).astype(np.float32))
    episodes = _rows(dataset, "episodes").to_pylist()
    assert [(e["dataset_from_index"], e["dataset_to_index"], e["length"], e["tasks"]) for e in episodes] == [
        (0, 16, 16, [TASK]), (16, 32, 16, [TASK])]
    key = "videos/observation.images.ego"
    assert [(e[f"{key}/from_timestamp"], e[f"{key}/to_timestamp"]) for e in episodes] == [(0.0, 1.0), (1.0, 2.0)]
    times = _frame_times(dataset / "videos" / "observation.images.ego" / "chunk-000" / "file-000.mp4")
    assert len(times) == data.num_rows  # one video frame per parquet row
    for row, (t, key_frame) in enumerate(times):  # every query from_timestamp + frame_index / fps is exact
        episode = episodes[row // 16]
        assert t == Fraction(episode[f"{key}/from_timestamp"]) + Fraction(int(frame_index[row]), 16)
        assert key_frame == (row % 2 == 0)  # a keyframe every 2 frames, as LeRobot encodes


def test_stats_are_those_of_the_data(dataset, samples):
    stats = json.loads((dataset / "meta" / "stats.json").read_text())
    assert set(stats) == {"observation.state", "action", "observation.images.ego", "depth.ego", "timestamp",
                          "frame_index", "episode_index", "index", "task_index"}
    data = _rows(dataset)
    state = np.asarray(data.column("observation.state").to_pylist(), dtype=np.float64)
    assert np.allclose(stats["observation.state"]["mean"], state.mean(axis=0), rtol=0, atol=1e-12)
    assert np.allclose(stats["observation.state"]["std"], state.std(axis=0), rtol=0, atol=1e-12)
    assert stats["observation.state"]["min"] == state.min(axis=0).tolist()
    assert stats["observation.state"]["count"] == [32]
    assert np.allclose(stats["index"]["q50"], [(7.5 + 23.5) / 2], atol=1e-9)  # mean of the episodes' medians
    eps = [Episode.open(p) for p in samples]
    images = np.stack([ep.rgb(i) for ep in eps for i in range(16)]).astype(np.float64) / 255
    image = stats["observation.images.ego"]
    assert np.array(image["mean"]).shape == (3, 1, 1) and image["count"] == [32]
    assert np.allclose(np.array(image["mean"]).ravel(), images.mean(axis=(0, 1, 2)), atol=1e-12)
    assert np.array(image["max"]).ravel().tolist() == images.max(axis=(0, 1, 2)).tolist()
    per_episode = [e for e in _rows(dataset, "episodes").to_pylist()]
    for e, ep in zip(per_episode, eps):
        own = np.stack([ep.rgb(i) for i in range(16)]).astype(np.float64) / 255
        assert np.allclose(np.array(e["stats/observation.images.ego/std"]).ravel(), own.std(axis=(0, 1, 2)))
    depth = np.asarray(data.column("depth.ego").to_pylist(), dtype=np.float64)
    assert np.allclose(stats["depth.ego"]["mean"], [depth.mean()]) and stats["depth.ego"]["max"] == [depth.max()]


def test_vector_stats_and_sampling_follow_lerobot():
    values = np.arange(12.0).reshape(6, 2)
    s = vector_stats(values)
    assert s["count"].tolist() == [6] and s["min"].tolist() == [0, 1] and s["std"].tolist() == values.std(0).tolist()
    assert [f"q{round(q * 100):02d}" for q in QUANTILES] == ["q01", "q10", "q50", "q90", "q99"]
    one = vector_stats(np.array([[2.0, 3.0]]))
    assert one["q01"].tolist() == [2.0, 3.0] and one["std"].tolist() == [0.0, 0.0]
    assert stats_sample_indices(40).tolist() == list(range(40))
    assert len(stats_sample_indices(1000)) == 177 and len(stats_sample_indices(20000)) == 1681


def test_float64_round_trip_is_bit_exact_and_images_within_codec_loss(samples, tmp_path):
    out = tmp_path / "ds"
    export_lerobot(samples, out, task=TASK, dtype="float64", crf=20)
    for n, path in enumerate(samples):
        ep = Episode.open(path)
        back = import_lerobot(out, tmp_path / f"back{n}", episode=n, camera="ego", K=ep.camera)
        assert np.array_equal(back.frames.q, ep.frames.q) and np.array_equal(back.frames.gripper, ep.frames.gripper)
        assert np.array_equal(back.frames.actions, ep.frames.actions)
        assert np.array_equal(back.frames.t, np.arange(16) / 16)
        assert back.meta.source == "import:lerobot" and back.meta.extra["task"] == TASK
        assert back.meta.extra["import"]["episode_index"] == n
        assert back.chroma_subsampling() == StoredChroma("4:2:0", False)  # the video's yuv420p, kept as PNG
        psnrs = [_psnr(back.rgb(i), ep.rgb(i)) for i in range(16)]
        # yuv420p alone gives 36.4-37.5 dB on these 64x48 renders; AV1 at CRF 20 measured 30.3-36.5
        assert min(psnrs) > 29.0 and np.mean(psnrs) > 34.0, psnrs
        for i in range(16):
            expected = np.round(np.nan_to_num(ep.depth(i)) * 1000) / 1000
            assert np.allclose(back.depth(i), expected, rtol=0, atol=1e-9)


@pytest.mark.parametrize("pixel_format, keys", [
    ("yuv420p", {"chroma_subsampling": "4:2:0", "chroma_red_blue_swapped": False}),
    ("yuv422p", {"chroma_subsampling": "4:2:2", "chroma_red_blue_swapped": False}),
    ("yuv411p", {"chroma_subsampling": "4:1:1", "chroma_red_blue_swapped": False}),
    ("yuv444p", {"chroma_subsampling": "4:4:4", "chroma_red_blue_swapped": False}),
    ("bgr0", {"chroma_subsampling": "4:4:4", "chroma_red_blue_swapped": False}),
    ("gray", {}),
])
def test_a_videos_pixel_format_says_how_its_colour_was_kept(tmp_path, pixel_format, keys):
    path = tmp_path / "v.mkv"
    with av.open(str(path), "w") as container:
        stream = container.add_stream("ffv1", rate=10)
        stream.width, stream.height, stream.pix_fmt = 32, 24, pixel_format
        frame = av.VideoFrame.from_ndarray(np.zeros((24, 32, 3), np.uint8), format="rgb24").reformat(format=pixel_format)
        for packet in [*stream.encode(frame), *stream.encode()]:
            container.mux(packet)
    assert stored_colour_keys(path, "png") == keys
    assert stored_colour_keys(path, "jpg") == {}  # JPEG files say it in their header


def test_frames_stored_as_jpeg_are_read_by_their_header(samples, tmp_path):
    export_lerobot(samples[:1], tmp_path / "ds", task=TASK, codec="h264")
    camera = Episode.open(samples[0]).camera
    camera = replace(camera, extra={**camera.extra, "chroma_subsampling": "4:2:2", "chroma_red_blue_swapped": True})
    back = import_lerobot(tmp_path / "ds", tmp_path / "back", episode=0, camera="ego", K=camera, image_format="jpg")
    assert "chroma_subsampling" not in back.camera.extra and back.chroma_subsampling() == StoredChroma("4:2:0")


def test_float32_default_round_trips_to_float32(tmp_path):
    src = write_episode(tmp_path / "ep", frames=6, masks=False)  # full float64 precision joints, 10 fps
    ep = Episode.open(src)
    export_lerobot([src], tmp_path / "ds", codec="h264")
    back = import_lerobot(tmp_path / "ds", tmp_path / "back", episode=0, camera="observation.images.test",
                          K=ep.camera)
    assert np.array_equal(back.frames.q, ep.frames.q.astype(np.float32).astype(np.float64))
    assert np.array_equal(back.frames.actions, ep.frames.actions.astype(np.float32).astype(np.float64))
    assert not np.array_equal(back.frames.q, ep.frames.q)  # float32 does lose bits: --float64 matters
    assert back.meta.extra["task"] == "test"  # the episode's own task without --task


def test_without_actions_the_action_is_the_next_state(tmp_path):
    src = tmp_path / "ep"
    with open_writer(src, extra_frame_columns=(), joint_columns=()) as writer:
        for i in range(5):
            frame = frame_data(i, masks=False)
            frame.pop("extra")
            writer.add_frame(**frame)
    export_lerobot([src], tmp_path / "ds", dtype="float64", depth=False)
    data = _rows(tmp_path / "ds")
    state = np.asarray(data.column("observation.state").to_pylist())
    assert np.array_equal(np.asarray(data.column("action").to_pylist()), np.concatenate([state[1:], state[-1:]]))
    assert "depth.test" not in data.column_names
    record = json.loads((tmp_path / "ds" / "meta" / "augmentation.json").read_text())
    assert record["episodes"][0]["action"] == "next_state" and record["depth"] is False


def test_files_split_at_the_size_limits(samples, tmp_path):
    eps = [*samples, *samples, *samples]
    out = tmp_path / "ds"
    result = export_lerobot(eps, out, task=TASK, dtype="float64", data_file_size_mb=0.15, video_file_size_mb=0.02)
    assert result.data_files > 1 and result.video_files > 1
    rows = _rows(out, "episodes").to_pylist()
    key = "videos/observation.images.ego"
    assert [r["dataset_from_index"] for r in rows] == [16 * n for n in range(6)]
    for r in rows:  # each row points at its own data rows and video frames
        data = pq.read_table(out / f"data/chunk-000/file-{r['data/file_index']:03d}.parquet")
        mine = np.asarray(data.column("episode_index")) == r["episode_index"]
        assert mine.sum() == 16 and np.asarray(data.column("index"))[mine][0] == r["dataset_from_index"]
        video = out / f"videos/observation.images.ego/chunk-000/file-{r[f'{key}/file_index']:03d}.mp4"
        starts = [t for t, _ in _frame_times(video)]
        assert Fraction(r[f"{key}/from_timestamp"]) in starts and r[f"{key}/to_timestamp"] <= float(starts[-1]) + 1 / 16
    assert any(r[f"{key}/from_timestamp"] == 0.0 for r in rows[1:])  # a new video file starts at 0
    last = import_lerobot(out, tmp_path / "back", episode=5, camera="ego", K=Episode.open(samples[1]).camera)
    assert np.array_equal(last.frames.q, Episode.open(samples[1]).frames.q)


def test_fps_resamples_to_the_nearest_frames(samples, tmp_path):
    ep = Episode.open(samples[0])
    assert main(["export", str(samples[0]), "--format", "lerobot", "--out", str(tmp_path / "ds"), "--fps", "8",
                 "--float64", "--task", TASK]) == 0
    info = json.loads((tmp_path / "ds" / "meta" / "info.json").read_text())
    assert info["fps"] == 8 and info["total_frames"] == 8
    state = np.asarray(_rows(tmp_path / "ds").column("observation.state").to_pylist())
    assert np.array_equal(state[:, :6], ep.frames.q[::2])
    with pytest.raises(EpisodeFormatError, match="recorded at 16 fps, below the export's 20 fps"):
        export_lerobot(samples, tmp_path / "ds20", task=TASK, fps=20)
    odd = _copy(samples[0], tmp_path / "odd_fps", fps=15.5)
    with pytest.raises(EpisodeFormatError, match="whole-number fps.*--fps 15"):
        export_lerobot([odd], tmp_path / "ds_odd", task=TASK)
    assert not (tmp_path / "ds20").exists() and not (tmp_path / "ds_odd").exists()


def test_provenance_marks_augmented_episodes(samples, tmp_path):
    aug = _copy(samples[0], tmp_path / "episode_0003", source="augmentation", parent="demo0")
    (aug / "augmentation.json").write_text(json.dumps({"parent": "demo0", "seed": 7, "segments": []}))
    result = export_lerobot([samples[1], aug], tmp_path / "ds", task=TASK)
    record = json.loads((tmp_path / "ds" / "meta" / "augmentation.json").read_text())
    assert result.augmented == 1 and record["format"] == "manisplat-lerobot-export"
    assert [(e["episode_index"], e["augmented"], e["parent"], e["seed"]) for e in record["episodes"]] == [
        (0, False, None, None), (1, True, "demo0", 7)]
    assert record["episodes"][1]["episode"] == str(aug.resolve())


def test_bad_input_refused_before_anything_is_written(samples, tmp_path):
    out = tmp_path / "ds"
    small = write_episode(tmp_path / "small", frames=4, masks=False)  # 32x24, 10 fps
    with pytest.raises(EpisodeFormatError, match="different image sizes"):
        export_lerobot([samples[0], _copy(small, tmp_path / "small16", fps=16.0)], out, task=TASK)
    with pytest.raises(EpisodeFormatError, match="different fps.*without --fps"):
        export_lerobot([samples[0], samples[1], _copy(samples[0], tmp_path / "at8", fps=8.0)], out, task=TASK)
    with pytest.raises(EpisodeFormatError, match="no camera 'cam_high'; the episode's camera is 'ego'"):
        export_lerobot(samples, out, camera="cam_high", task=TASK)
    untitled = _copy(samples[0], tmp_path / "untitled")
    meta = json.loads((untitled / "episode.json").read_text())
    meta.pop("task", None)
    (untitled / "episode.json").write_text(json.dumps(meta))
    with pytest.raises(EpisodeFormatError, match="no task description.*--task"):
        export_lerobot([untitled], out)
    gap = _copy(samples[0], tmp_path / "gap")
    (gap / "depth" / "000003.png").unlink()
    with pytest.raises(EpisodeFormatError, match="no depth for 1 of 16 frames.*--no-depth"):
        export_lerobot([samples[1], gap], out, task=TASK)
    crashed = _copy(samples[0], tmp_path / "crashed")
    mark_incomplete(crashed)
    with pytest.raises(EpisodeFormatError, match="incomplete episode"):
        export_lerobot([crashed], out, task=TASK)
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_out_holding_anything_but_an_earlier_dataset_is_refused(samples, dataset, tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    for extra in ([], ["--overwrite"]):
        assert main(["export", str(samples[0]), "--format", "lerobot", "--out", str(mine), *extra]) == 2
        assert "holds no LeRobot dataset" in capsys.readouterr().err
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]
    earlier = tmp_path / "earlier"
    shutil.copytree(dataset, earlier)
    with pytest.raises(ExportDestinationError, match="already holds a LeRobot dataset; pass --overwrite"):
        export_lerobot(samples[:1], earlier, task=TASK)
    assert json.loads((earlier / "meta" / "info.json").read_text())["total_episodes"] == 2
    export_lerobot(samples[:1], earlier, task=TASK, overwrite=True)
    assert json.loads((earlier / "meta" / "info.json").read_text())["total_episodes"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["earlier", "mine"]  # nothing left beside it
    empty = tmp_path / "empty"
    empty.mkdir()
    export_lerobot(samples[:1], empty, task=TASK)
    assert (empty / "meta" / "info.json").is_file()


def test_an_interrupted_export_leaves_no_dataset(samples, dataset, tmp_path):
    broken = _copy(samples[1], tmp_path / "broken")
    data = (broken / "rgb" / "000011.png").read_bytes()
    (broken / "rgb" / "000011.png").write_bytes(data[: len(data) // 2])  # truncated: fails mid-episode
    with pytest.raises(EpisodeFormatError, match="000011.png"):
        export_lerobot([samples[0], broken], tmp_path / "ds", task=TASK)
    earlier = tmp_path / "earlier"
    shutil.copytree(dataset, earlier)
    with pytest.raises(EpisodeFormatError, match="000011.png"):
        export_lerobot([samples[0], broken], earlier, task=TASK, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken", "earlier"]  # no partial folder left
    assert json.loads((earlier / "meta" / "info.json").read_text())["total_episodes"] == 2  # kept whole


def test_options_of_the_other_format_are_usage_errors(samples, tmp_path, capsys):
    assert main(["export", str(samples[0]), "--format", "lerobot", "--out", str(tmp_path / "a"), "--compress"]) == 2
    assert "--compress do not apply to --format lerobot" in capsys.readouterr().err
    assert main(["export", str(samples[0]), "--format", "act-hdf5", "--out", str(tmp_path / "b"), "--task", "x",
                 "--no-depth"]) == 2
    assert "--task, --no-depth do not apply to --format act-hdf5" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_import_names_what_is_missing(dataset, tmp_path, capsys):
    base = ["import-lerobot", str(dataset), "--K", "60,60,31.5,23.5", "--out", str(tmp_path / "ep")]
    assert main([*base, "--episode", "5", "--camera", "ego"]) == 2
    assert "no episode 5 (episodes 0..1)" in capsys.readouterr().err
    assert main([*base, "--episode", "0", "--camera", "cam_high"]) == 2
    assert "no video camera 'cam_high' in the dataset; it has: observation.images.ego" in capsys.readouterr().err
    assert main([*base, "--episode", "0", "--camera", "ego", "--arm", "left"]) == 2
    assert "has shape [7]; expected [14]" in capsys.readouterr().err
    assert main([*base, "--episode", "1", "--camera", "ego"]) == 0
    assert len(Episode.open(tmp_path / "ep")) == 16
    old = tmp_path / "old"
    shutil.copytree(dataset, old)
    info = json.loads((old / "meta" / "info.json").read_text())
    (old / "meta" / "info.json").write_text(json.dumps({**info, "codebase_version": "v2.1"}))
    with pytest.raises(EpisodeFormatError, match="codebase_version 'v2.1'; only v3.0"):
        import_lerobot(old, tmp_path / "ep2", episode=0, camera="ego", K=K)
    (old / "videos" / "observation.images.ego" / "chunk-000" / "file-000.mp4").unlink()
    (old / "meta" / "info.json").write_text(json.dumps(info))
    with pytest.raises(EpisodeFormatError, match="file-000.mp4, which is missing"):
        import_lerobot(old, tmp_path / "ep3", episode=0, camera="ego", K=K)


def test_a_killed_exports_leftover_is_named_not_used(samples, tmp_path, caplog):
    leftover = tmp_path / ".ds.partial-deadbeef"
    (leftover / "meta").mkdir(parents=True)
    export_lerobot(samples[:1], tmp_path / "ds", task=TASK)
    assert "safe to delete" in caplog.text and str(leftover) in caplog.text
    assert leftover.is_dir() and json.loads((tmp_path / "ds" / "meta" / "info.json").read_text())["total_episodes"] == 1
