"""manisplat-replay as a user runs it: refusals before anything moves, the dry run, a replay of an
episode in the AgileX URDF convention, and Ctrl-C."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from manisplat.drivers.piper.convention import AGILEX_URDF_OLD
from manisplat.drivers.replay_cli import main
from tests.replay.helpers import OLD_URDF, smooth_motion, write_episode, write_urdf

NO_TARGETS = "0 resets (0x150 B0=2), 0 disables (0x471 01), 0 e-stops, 0 joint targets"


@pytest.fixture
def episode(tmp_path: Path) -> Path:
    t, q, g = smooth_motion(1.0)
    return write_episode(tmp_path / "ep", t, q, g)


def test_help_explains_the_checks_and_exit_codes(capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    for flag in ("--can", "--sim", "--speed", "--dry-run", "--max-tracking-error-deg", "--max-start-distance-deg"):
        assert flag in text
    for code in ("0    replayed", "1    stopped", "2    bad", "3    the arm", "4    refused", "130  interrupted"):
        assert code in text


def test_a_start_far_from_the_arm_is_refused_before_anything_moves(episode: Path,
                                                                   capsys: pytest.CaptureFixture) -> None:
    assert main([str(episode), "--sim", "--sim-start", "40,60,-60,0,0,0"]) == 4
    out, err = capsys.readouterr()
    assert "from the arm's current state" in err and "nothing was sent" in err and NO_TARGETS in out


def test_targets_outside_the_limits_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    t, q, g = smooth_motion(1.0)
    q[:, 0] += np.linspace(0, math.radians(155), len(t))  # J1 limit 150 deg
    assert main([str(write_episode(tmp_path / "ep", t, q, g)), "--sim", "--speed", "0.05"]) == 4
    assert "joint1 leaves its limits" in capsys.readouterr().err


def test_an_unmappable_convention_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    write_urdf(tmp_path / "odd.urdf", [((0, 0, 0.1), (0, 0, 0), (0, 0, 1), -3, 3)] * 6)
    t, q, g = smooth_motion(1.0)
    assert main([str(write_episode(tmp_path / "ep", t, q, g, description="../odd.urdf")), "--sim"]) == 4
    assert "cannot map the joint angles" in capsys.readouterr().err


def test_dry_run_checks_and_sends_nothing(episode: Path, capsys: pytest.CaptureFixture) -> None:
    assert main([str(episode), "--sim", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "all checks pass" in out and "nothing was sent" in out and NO_TARGETS in out


def test_an_agilex_urdf_episode_is_converted_and_replayed(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    write_urdf(tmp_path / "piper_description.urdf", OLD_URDF)
    t, q_arm, g = smooth_motion(1.0)
    q_urdf = AGILEX_URDF_OLD.from_arm(q_arm)  # recorded in the URDF convention
    actions = np.concatenate([q_urdf, g[:, None]], axis=1)
    ep = write_episode(tmp_path / "ep", t, q_urdf, g, description="../piper_description.urdf", actions=actions)
    assert main([str(ep), "--sim", "--feedback-timeout-ms", "500"]) == 0
    out = capsys.readouterr().out
    assert "AgileX piper_description (Piper_ros ros-noetic-no-aloha @4f22c61) -> piper_sdk" in out
    assert "targets: actions" in out and "outcome: completed" in out and "tracking error" in out
    final = [float(v) for v in out.split("final error, deg:")[1].split("\n")[0].split()]
    assert max(final) <= 0.5  # measured against the converted targets: the sim ended there
    assert "0 resets (0x150 B0=2), 0 disables (0x471 01), 0 e-stops" in out


def test_ctrl_c_stops_a_replay_with_the_arm_holding(tmp_path: Path) -> None:
    t, q, g = smooth_motion(6.0)
    ep = write_episode(tmp_path / "ep", t, q, g)
    proc = subprocess.Popen([sys.executable, "-m", "manisplat.drivers.replay_cli", str(ep), "--sim",
                             "--feedback-timeout-ms", "500"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:  # wait until the checks passed and the replay runs
        line = proc.stdout.readline()
        lines.append(line)
        if "all checks pass" in line or not line:
            break
    time.sleep(2.0)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    out = "".join(lines) + out
    assert proc.returncode == 130, out + err
    assert "outcome: interrupted" in out and "holding its measured position" in out
    assert "0 resets (0x150 B0=2), 0 disables (0x471 01), 0 e-stops" in out
