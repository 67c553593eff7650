"""Per-frame files stay consistent: gt.npz is cut with frames.csv on recovery and checked by
validate, and an episode without a frame is never called valid."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from episode_factory import frame_data, mark_incomplete, open_writer

from manisplat.episode import DamagedEpisodeError, Episode, recover, validate
from manisplat.episode.cli import main

LINKS = np.array([f"link{i}" for i in range(9)])


def write_gt(path: Path, frames: int = 8, **override: np.ndarray) -> dict[str, np.ndarray]:
    """A gt.npz for the factory episode (objects ["box"]): per-frame arrays whose rows identify
    their frame, per-episode K, T_cam_base and link_names (9 entries, as long as 9 frames)."""
    rows = np.arange(frames, dtype=np.float64)
    T = np.repeat(np.eye(4)[None], frames, axis=0)
    T[:, 0, 3] = rows
    arrays = {"t": np.array([frame_data(i)["t"] for i in range(frames)]), "q": np.repeat(rows[:, None], 6, axis=1),
              "gripper": rows / 100, "T_base_tcp": T, "T_base_box": T + 1,
              "phase": np.array([f"p{i}" for i in range(frames)]), "finger_contact": rows > 3,
              "K": np.eye(3), "T_cam_base": np.eye(4), "link_names": LINKS, "info": np.array("free text")}
    arrays.update(override)
    np.savez(path / "gt.npz", **arrays)
    return arrays


def truncate(png: Path) -> None:
    png.write_bytes(png.read_bytes()[:100])


PER_FRAME = ("t", "q", "gripper", "T_base_tcp", "T_base_box", "phase", "finger_contact")


def test_drop_damaged_cuts_gt_to_the_kept_frames(episode):
    original = write_gt(episode)
    before = (episode / "gt.npz").read_bytes()
    truncate(episode / "rgb" / "000003.png")
    report = recover(episode, drop_damaged=True)
    assert report.frames_kept == 7 and report.validation.ok, str(report)
    assert "gt.npz" in report.saved and "gt.npz" in str(report)
    gt = Episode.open(episode).gt()
    kept = [0, 1, 2, 4, 5, 6, 7]
    for name in PER_FRAME:
        assert np.array_equal(gt[name], original[name][kept]), name
    for name in ("K", "T_cam_base", "link_names", "info"):
        assert np.array_equal(gt[name], original[name]), name
    assert np.array_equal(gt["t"], Episode.open(episode).frames.t)
    assert (report.backup_dir / "gt.npz").read_bytes() == before  # the original is kept, not deleted


def test_crash_tail_cuts_gt(episode):
    original = write_gt(episode)
    mark_incomplete(episode)
    (episode / "masks" / "000007.png").unlink()
    report = recover(episode)
    assert report.frames_kept == 7 and report.validation.ok, str(report)
    assert np.array_equal(Episode.open(episode).gt()["T_base_box"], original["T_base_box"][:7])


def test_validate_names_the_gt_array_that_does_not_fit(episode):
    write_gt(episode, T_base_box=np.repeat(np.eye(4)[None], 9, axis=0))
    report = validate(episode)
    assert not report.ok
    (problem,) = report.errors
    assert problem.file == "gt.npz" and "'T_base_box'" in problem.message and "9" in problem.message
    assert "8" in problem.message and "frames.csv" in problem.message
    assert str(problem).startswith("gt.npz: error:")


def test_validate_accepts_per_episode_gt_arrays(episode):
    """A calibration episode's gt.npz holds only per-episode 4x4 transforms."""
    np.savez(episode / "gt.npz", T_base_cam=np.eye(4), T_link6_board=np.eye(4), K=np.eye(3))
    assert validate(episode).ok


def test_validate_reports_an_unreadable_gt(episode):
    (episode / "gt.npz").write_bytes(b"not a zip")
    (problem,) = validate(episode).errors
    assert problem.file == "gt.npz" and "cannot read" in problem.message


def test_recover_realigns_gt_left_too_long_by_an_earlier_recovery(episode):
    """What the earlier recover --drop-damaged left: 7 frames, gt.npz still with 8 rows."""
    original = write_gt(episode)
    truncate(episode / "rgb" / "000003.png")
    recover(episode, drop_damaged=True)
    np.savez(episode / "gt.npz", **original)
    assert any(p.file == "gt.npz" for p in validate(episode).errors)
    report = recover(episode)
    assert report.changed and report.validation.ok, str(report)
    assert np.array_equal(Episode.open(episode).gt()["q"], original["q"][[0, 1, 2, 4, 5, 6, 7]])


def test_recover_refuses_gt_that_does_not_cover_the_frames(episode):
    write_gt(episode, 6)
    mark_incomplete(episode)
    before = sorted(p.relative_to(episode) for p in episode.rglob("*"))
    with pytest.raises(DamagedEpisodeError, match="gt.npz"):
        recover(episode)
    assert sorted(p.relative_to(episode) for p in episode.rglob("*")) == before


def test_sample_episode_drop_damaged_then_validate(tmp_path, capsys):
    """The issue's steps: sample, a damaged frame, recover --drop-damaged, validate, then use gt."""
    ep = tmp_path / "ep"
    assert main(["sample", str(ep), "--frames", "12", "--width", "48", "--height", "36"]) == 0
    truncate(ep / "rgb" / "000005.png")
    assert main(["recover", "--drop-damaged", str(ep)]) == 0
    assert main(["validate", str(ep)]) == 0
    assert "OK (11 frames" in capsys.readouterr().out
    episode = Episode.open(ep)
    gt = episode.gt()
    assert all(len(gt[k]) == 11 for k in ("t", "q", "gripper", "T_base_tcp", "T_base_box", "phase", "T_base_links"))
    assert np.array_equal(gt["t"], episode.frames.t)


def test_episode_without_a_frame_is_invalid(tmp_path, capsys, caplog):
    with open_writer(tmp_path / "ep"):
        pass
    assert "closed without a frame" in caplog.text
    report = validate(tmp_path / "ep")
    (problem,) = report.errors
    assert problem.file == "frames.csv" and "at least one frame" in problem.message
    assert main(["validate", str(tmp_path / "ep")]) == 1


def test_recovery_without_a_complete_frame_says_nothing_could_be_kept(tmp_path, capsys):
    path = tmp_path / "ep"
    writer = open_writer(path)
    writer.add_frame(**frame_data(0))
    writer.sync()  # then killed: no close
    truncate(path / "rgb" / "000000.png")
    assert main(["recover", str(path)]) == 1
    out = capsys.readouterr().out
    assert "nothing could be kept" in out and str(path / ".recovered") in out
    (backup,) = (path / ".recovered").iterdir()
    assert (backup / "rgb" / "000000.png").exists() and (backup / "frames.csv").exists()  # debris kept
    assert not validate(path).ok
