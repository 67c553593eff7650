"""recover(): crash artefacts are moved aside, complete frames are kept, other damage is refused."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from episode_factory import frame_data, joint_data, mark_incomplete, open_writer

from manisplat.episode import DamagedEpisodeError, Episode, recover, validate

CHILD = """
import sys
sys.path.insert(0, {helpers!r})
from episode_factory import frame_data, joint_data, mark_incomplete, open_writer
writer = open_writer({path!r}, fsync_every=5)
i = 0
while True:
    writer.add_frame(**frame_data(i))
    for k in range(4 * i, 4 * i + 4):
        writer.add_joint_sample(**joint_data(k))
    print(i, flush=True)
    i += 1
"""


def assert_frames_intact(path: Path, count: int) -> None:
    ep = Episode.open(path)
    assert len(ep) == count and ep.meta.complete and ep.meta.frame_count == count
    for i in range(count):
        d = frame_data(i)
        assert ep.frames.t[i] == d["t"] and np.array_equal(ep.frames.q[i], d["q"])
        assert np.array_equal(ep.rgb(i), d["rgb"]) and np.array_equal(ep.mask(i), d["mask"])


@pytest.mark.parametrize("frames_before_kill", [3, 12])
def test_sigkill_mid_episode(tmp_path, frames_before_kill):
    path = tmp_path / "ep"
    script = CHILD.format(helpers=str(Path(__file__).parent), path=str(path))
    child = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        reported = [int(child.stdout.readline()) for _ in range(frames_before_kill)]
    finally:
        os.kill(child.pid, signal.SIGKILL)
        child.wait()
        child.stdout.close()
    assert reported == list(range(frames_before_kill))
    assert not validate(path).ok  # complete: false at least

    report = recover(path)
    assert report.changed and report.validation.ok, str(report)
    assert report.frames_kept >= frames_before_kill  # every frame the writer finished is kept
    assert_frames_intact(path, report.frames_kept)
    assert validate(path).ok
    joints = Episode.open(path).joints()
    assert len(joints) >= 4 * frames_before_kill
    assert joints.t[-1] == joint_data(len(joints) - 1)["t"]
    for rel in report.moved:  # nothing deleted
        assert (report.backup_dir / rel).exists()


def test_simulated_crash_artefacts(tmp_path):
    path = tmp_path / "ep"
    writer = open_writer(path)
    for i in range(6):
        writer.add_frame(**frame_data(i))
    for k in range(10):
        writer.add_joint_sample(**joint_data(k))
    writer.sync()
    original_frames = (path / "frames.csv").read_bytes()
    with open(path / "frames.csv", "a") as f:
        f.write("6,0.6,0.1,0.2,0.3")  # torn last row
    with open(path / "joints.csv", "a") as f:
        f.write("0.25,0.1,")  # torn last sample
    (path / "rgb" / "000006.png").write_bytes((path / "rgb" / "000000.png").read_bytes())  # row never written
    (path / "depth" / "000006.png").write_bytes((path / "depth" / "000000.png").read_bytes())
    (path / "rgb" / "000007.png.tmp").write_bytes(b"\x89PNG partial")  # image being written
    (path / "episode.json.tmp").write_text("{")

    report = recover(path)
    assert report.frames_kept == 6 and report.dropped == [8]
    assert sorted(report.moved) == ["depth/000006.png", "episode.json.tmp", "rgb/000006.png", "rgb/000007.png.tmp"]
    assert sorted(report.saved) == ["frames.csv", "joints.csv"]
    assert report.validation.ok, str(report)
    assert_frames_intact(path, 6)
    assert (path / "frames.csv").read_bytes() == original_frames
    assert len(Episode.open(path).joints()) == 10
    backup = report.backup_dir
    assert backup.parent == path / ".recovered"
    assert (backup / "frames.csv").read_bytes().endswith(b"6,0.6,0.1,0.2,0.3")
    assert (backup / "rgb" / "000007.png.tmp").exists() and (backup / "recovery.json").exists()
    entry = json.loads((path / "episode.json").read_text())["recovery"][0]
    assert entry["frames_kept"] == 6 and entry["backup"] == str(backup.relative_to(path))
    assert "rgb/000006.png" in entry["moved"]


def test_tail_row_with_truncated_image(episode):
    mark_incomplete(episode)
    png = episode / "rgb" / "000007.png"
    png.write_bytes(png.read_bytes()[:100])
    report = recover(episode)
    assert report.frames_kept == 7 and report.dropped == [9] and report.validation.ok
    assert_frames_intact(episode, 7)
    assert not (episode / "depth" / "000007.png").exists()
    assert (report.backup_dir / "masks" / "000007.png").exists()


def test_incomplete_but_whole_episode_is_only_marked_complete(episode):
    mark_incomplete(episode)
    report = recover(episode)
    assert report.changed and report.frames_kept == 8 and report.moved == [] and report.backup_dir is None
    assert validate(episode).ok and not (episode / ".recovered").exists()


def test_complete_valid_episode_is_a_no_op(episode):
    before = (episode / "episode.json").read_bytes()
    report = recover(episode)
    assert not report.changed and report.frames_kept == 8
    assert "nothing to do" in str(report)
    assert (episode / "episode.json").read_bytes() == before and not (episode / ".recovered").exists()


def test_damage_in_the_middle_is_refused_then_dropped(episode):
    mark_incomplete(episode)
    png = episode / "rgb" / "000003.png"
    png.write_bytes(png.read_bytes()[:200])
    before = sorted(p.relative_to(episode) for p in episode.rglob("*"))
    with pytest.raises(DamagedEpisodeError, match=r"line 5 is damaged .*rgb/000003.png.*4 good frame"):
        recover(episode)
    assert sorted(p.relative_to(episode) for p in episode.rglob("*")) == before  # untouched

    report = recover(episode, drop_damaged=True)
    assert report.frames_kept == 7 and report.dropped == [5] and report.validation.ok, str(report)
    assert ("rgb/000004.png", "rgb/000003.png") in report.renamed
    ep = Episode.open(episode)
    for new, old in enumerate([0, 1, 2, 4, 5, 6, 7]):
        d = frame_data(old)
        assert ep.frames.index[new] == new and ep.frames.t[new] == d["t"]
        assert np.array_equal(ep.rgb(new), d["rgb"]) and np.array_equal(ep.mask(new), d["mask"])
    assert (report.backup_dir / "rgb" / "000003.png").exists()


def test_nan_row_in_the_middle_is_refused(episode):
    mark_incomplete(episode)
    lines = (episode / "frames.csv").read_text().splitlines(keepends=True)
    lines[2] = lines[2].replace(lines[2].split(",")[3], "nan", 1)
    (episode / "frames.csv").write_text("".join(lines))
    with pytest.raises(DamagedEpisodeError, match="line 3"):
        recover(episode)
    assert recover(episode, drop_damaged=True).frames_kept == 7


def test_damaged_joints_in_the_middle_are_refused(episode):
    mark_incomplete(episode)
    lines = (episode / "joints.csv").read_text().splitlines(keepends=True)
    lines[5] = "oops\n"
    (episode / "joints.csv").write_text("".join(lines))
    with pytest.raises(DamagedEpisodeError, match="joints.csv: line 6"):
        recover(episode)
    report = recover(episode, drop_damaged=True)
    assert report.validation.ok and len(Episode.open(episode).joints()) == 31


def test_damage_in_a_complete_episode_is_refused(episode):
    png = episode / "rgb" / "000007.png"
    png.write_bytes(png.read_bytes()[:100])
    with pytest.raises(DamagedEpisodeError, match="closed as complete"):
        recover(episode)
    report = recover(episode, drop_damaged=True)
    assert report.frames_kept == 7 and report.validation.ok


def test_drop_damaged_skips_rows_out_of_order(episode):
    mark_incomplete(episode)
    lines = (episode / "frames.csv").read_text().splitlines(keepends=True)
    lines[3], lines[4] = lines[4], lines[3]  # frames 2 and 3 swapped: t goes back
    (episode / "frames.csv").write_text("".join(lines))
    with pytest.raises(DamagedEpisodeError, match="line 4: index 3, expected 2"):
        recover(episode)
    report = recover(episode, drop_damaged=True)  # keeps frame 3 (line 4), drops frame 2 (line 5)
    assert report.frames_kept == 7 and report.dropped == [5] and report.validation.ok
    ep = Episode.open(episode)
    for new, old in enumerate([0, 1, 3, 4, 5, 6, 7]):
        assert np.array_equal(ep.rgb(new), frame_data(old)["rgb"]) and ep.frames.t[new] == frame_data(old)["t"]
