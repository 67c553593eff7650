"""manisplat-record as a user runs it: flags, exit codes, a clean stop by SIGTERM, recovery
after kill -9 (explicit and at the next start), and a full disk."""

from __future__ import annotations

import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from manisplat.episode import Episode, validate
from manisplat.episode.images import find_image
from manisplat.recorder.cli import main
from tests.recorder.helpers import source_frame, write_source

RECORD = [sys.executable, "-m", "manisplat.recorder.cli"]


@pytest.fixture(scope="module")
def depth_source(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Like ``source`` with depth: frame i is 1 m + i mm everywhere."""
    return write_source(tmp_path_factory.mktemp("depth") / "source", depth=True)


def record_args(source: Path, out: Path, duration: float = 60.0) -> list[str]:
    return ["--sim", "--camera", f"replay:{source}", "--loop", "--out", str(out), "--duration", str(duration),
            "--start", "now"]


def wait_for_rows(frames_csv: Path, rows: int, proc: subprocess.Popen, timeout: float = 90.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise AssertionError(f"the recorder exited early ({proc.returncode}): {proc.communicate()}")
        if frames_csv.is_file() and frames_csv.read_text().count("\n") > rows:
            return
        time.sleep(0.05)
    raise AssertionError(f"{frames_csv} did not reach {rows} rows in {timeout} s")


def complete_frames(path: Path) -> dict[int, str]:
    """Index -> frames.csv line of every frame whose row is whole and whose rgb image exists."""
    lines = (path / "frames.csv").read_text().split("\n")
    rows = {}
    for line in lines[1:-1]:  # the last element is after the last line break (a torn row or "")
        index = int(line.split(",")[0])
        if find_image(path / "rgb", index) is not None:
            rows[index] = line
    return rows


def assert_intact(path: Path, expected: dict[int, str]) -> None:
    """The recovered episode keeps exactly those frames, rows unchanged, images the camera's."""
    report = validate(path)
    assert report.ok, report
    ep = Episode.open(path)
    assert len(ep) == len(expected) > 0
    lines = (path / "frames.csv").read_text().split("\n")[1:-1]
    assert lines == [expected[i] for i in range(len(expected))]
    for i in range(len(ep)):
        np.testing.assert_array_equal(ep.rgb(i), source_frame(int(ep.frames.extra["seq"][i]) % 60))


def test_help_explains_every_flag_and_the_exit_codes(capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for flag in ("--can", "--interface", "--camera", "--sim", "--out", "--duration", "--episodes", "--fps", "--size",
                 "--depth", "--image-format", "--task", "--latency-ms", "--recover", "--start", "--actions"):
        assert flag in text
    for code in ("0  every episode", "1  an episode ended", "2  bad arguments", "3  the arm or the camera",
                 "docs/exit-codes.md"):
        assert code in text


@pytest.mark.parametrize("argv", [["--size", "640"], ["--camera", "usb"], ["--duration", "-1"],
                                  ["--recover", "/nonexistent/folder"], ["--episodes", "0"]])
def test_bad_arguments_exit_2(argv: list[str], capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2 and "error" in capsys.readouterr().err


def test_an_out_folder_that_cannot_be_made_is_a_usage_error(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    (tmp_path / "file").write_text("x")
    with pytest.raises(SystemExit) as exc:
        main(["--sim", "--out", str(tmp_path / "file" / "eps")])
    assert exc.value.code == 2 and "cannot create the folder" in capsys.readouterr().err


def test_devices_that_cannot_be_opened_exit_3(tmp_path: Path, source: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["--interface", "virtual", "--can", f"silent-{os.getpid()}-bus", "--camera", f"replay:{source}",
                 "--out", str(tmp_path / "o"), "--start", "now", "--duration", "1"]) == 3
    assert "no PiPER joint feedback" in capsys.readouterr().err


def test_a_replay_source_that_does_not_fit_is_bad_input_exit_2(tmp_path: Path, source: Path,
                                                               capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--sim", "--camera", f"replay:{tmp_path / 'none'}", "--out", str(tmp_path / "o")])
    assert exc.value.code == 2 and "does not exist" in capsys.readouterr().err
    (tmp_path / "notes.txt").write_text("x")
    assert main(["--sim", "--camera", f"replay:{tmp_path / 'notes.txt'}", "--out", str(tmp_path / "o"),
                 "--start", "now", "--duration", "1"]) == 2
    assert "neither an episode folder" in capsys.readouterr().err
    assert main(["--sim", "--camera", f"replay:{source}", "--size", "320x240", "--out", str(tmp_path / "o"),
                 "--start", "now"]) == 2
    assert "does not match" in capsys.readouterr().err


def test_the_readme_command_records_the_depth_of_a_replayed_episode(tmp_path: Path, depth_source: Path) -> None:
    out = tmp_path / "out"
    assert main(["--sim", "--sim-motion", "teleop", "--camera", f"replay:{depth_source}", "--loop", "--start", "now",
                 "--duration", "1", "--out", str(out)]) == 0
    ep = Episode.open(out / "episode_0000")
    assert ep.meta.complete and len(ep) >= 10 and ep.has_depth and validate(ep.path).ok
    for i in (0, len(ep) - 1):
        seq = int(ep.frames.extra["seq"][i]) % 60
        np.testing.assert_allclose(ep.depth(i), 1.0 + seq * 1e-3, atol=1e-6)


def test_no_depth_records_a_replayed_episode_without_its_depth(tmp_path: Path, depth_source: Path) -> None:
    out = tmp_path / "out"
    assert main(["--sim", "--camera", f"replay:{depth_source}", "--no-depth", "--start", "now", "--duration", "0.5",
                 "--out", str(out)]) == 0
    ep = Episode.open(out / "episode_0000")
    assert ep.meta.complete and len(ep) > 0 and not ep.has_depth and ep.meta.depth_scale is None
    assert validate(ep.path).ok


def test_depth_from_a_replay_without_depth_is_refused_before_anything_is_written(
        tmp_path: Path, source: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "out"
    assert main(["--sim", "--camera", f"replay:{source}", "--depth", "--start", "now", "--duration", "1",
                 "--out", str(out)]) == 2  # bad input, not a device fault
    assert "--depth" in capsys.readouterr().err
    assert not out.exists()


def test_a_failed_start_leaves_no_empty_out_folder(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "new" / "episodes"
    (tmp_path / "notes.txt").write_text("not a recording")
    assert main(["--sim", "--camera", f"replay:{tmp_path / 'notes.txt'}", "--out", str(out), "--start", "now",
                 "--duration", "1"]) == 2
    assert "neither an episode folder" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()


def test_an_episode_that_fails_before_its_first_frame_is_removed_and_reported(tmp_path: Path, source: Path) -> None:
    def limit() -> None:  # in the child: episode.json (2 kB) fits, no 9 kB image and no CAN log beyond 5 kB
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (5_000, 5_000))

    out = tmp_path / "out"
    done = subprocess.run(RECORD + record_args(source, out), capture_output=True, text=True, timeout=180,
                          preexec_fn=limit)
    assert done.returncode == 1, done.stderr
    assert "a file reached the size limit" in done.stderr
    assert "no frame was recorded: removed" in done.stderr and "--recover" not in done.stderr
    assert "removed" in done.stdout  # the summary table
    assert not out.exists()


def test_sigterm_ends_the_episode_cleanly(tmp_path: Path, source: Path) -> None:
    proc = subprocess.Popen(RECORD + record_args(source, tmp_path / "out") + ["--task", "pick", "--image-format", "jpg"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wait_for_rows(tmp_path / "out" / "episode_0000" / "frames.csv", 15, proc)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "episode_0000" in out and "valid" in out
    ep = Episode.open(tmp_path / "out" / "episode_0000")
    assert ep.meta.complete and len(ep) >= 15 and ep.meta.extra["task"] == "pick"
    assert ep.meta.extra["stats"]["stop_reason"] == "stopped"
    assert validate(ep.path).ok and (ep.path / "rgb" / "000000.jpg").is_file()


def test_kill_9_then_recover_keeps_every_written_frame(tmp_path: Path, source: Path,
                                                      capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "out"
    proc = subprocess.Popen(RECORD + record_args(source, out), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    crashed = out / "episode_0000"
    wait_for_rows(crashed / "frames.csv", 20, proc)
    proc.kill()
    proc.communicate(timeout=30)
    assert not Episode.open(crashed).meta.complete
    expected = complete_frames(crashed)
    copy = tmp_path / "copy"
    shutil.copytree(crashed, copy)

    assert main(["--recover", str(copy)]) == 0
    assert "recovered" in capsys.readouterr().out
    assert_intact(copy, expected)

    # the next start recovers it by itself, then records the next episode
    assert main(record_args(source, out, duration=0.5)) == 0
    assert_intact(crashed, expected)
    assert Episode.open(out / "episode_0001").meta.complete


def _disk_full_checks(tmp_path: Path, rc: int, err: str, episode: Path, why: str, advice: str) -> None:
    assert rc == 1, err
    assert why in err and advice in err
    assert not Episode.open(episode).meta.complete
    expected = complete_frames(episode)
    assert main(["--recover", str(episode)]) == 0
    assert_intact(episode, expected)


def _unshare_works() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "true"], capture_output=True)
    return probe.returncode == 0


@pytest.mark.skipif(not _unshare_works(), reason="cannot mount a tmpfs here (no user/mount namespaces)")
def test_a_full_disk_stops_recording_and_keeps_what_was_written(tmp_path: Path, source: Path) -> None:
    disk, saved = tmp_path / "disk", tmp_path / "saved"
    disk.mkdir()
    command = " ".join(RECORD + record_args(source, disk / "out")) + " 2>" + str(tmp_path / "err.txt")
    script = (f'mount -t tmpfs -o size=1m tmpfs {disk} && {command}; echo "rc=$?"; '
              f"cp -a {disk / 'out'} {saved}")  # the tmpfs ends with its namespace: keep a copy
    done = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "sh", "-c", script],
                          capture_output=True, text=True, timeout=180)
    rc = int(done.stdout.strip().splitlines()[-1].removeprefix("rc="))
    _disk_full_checks(tmp_path, rc, (tmp_path / "err.txt").read_text(), saved / "episode_0000", "the disk is full",
                      "free space, then run `manisplat-record --recover")


def test_a_file_size_limit_stops_recording_the_same_way(tmp_path: Path, source: Path) -> None:
    def limit() -> None:  # in the child: writes past 400 kB fail with EFBIG
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (400_000, 400_000))

    done = subprocess.run(RECORD + record_args(source, tmp_path / "out"), capture_output=True, text=True,
                          timeout=180, preexec_fn=limit)
    _disk_full_checks(tmp_path, done.returncode, done.stderr, tmp_path / "out" / "episode_0000",
                      "a file reached the size limit", "run `manisplat-record --recover")
    assert "free space" not in done.stderr
