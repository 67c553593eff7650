import numpy as np
import pytest

from manisplat.calib.cli import main
from manisplat.calib.errors import NotEnoughDataError
from manisplat.calib.latency import RobotMotion, estimate_latency, fit_latency, robot_motion
from manisplat.calib.synth import Q_NOMINAL, _camera_info, default_truth, write_latency_episode
from manisplat.episode import Episode, EpisodeWriter, RobotInfo


def standing_episode(path, spec, duration_s: float, gripper, frame_times) -> Episode:
    """The arm standing at Q_NOMINAL: 200 Hz joints.csv with ``gripper(t)`` (m), and uniform
    grey 320x240 frames at ``frame_times``."""
    truth = default_truth(spec, width=320, height=240, f=260.0)
    with EpisodeWriter(path, _camera_info(truth), RobotInfo(), fps=30.0, source="simulation") as w:
        for t in np.arange(0.0, duration_s, 0.005):
            w.add_joint_sample(float(t), Q_NOMINAL, gripper(t))
        for t in frame_times:
            w.add_frame(float(t), Q_NOMINAL, gripper(t), np.full((240, 320, 3), 90, np.uint8))
    return Episode.open(path)


@pytest.mark.parametrize("latency, calibrated, seed", [(0.047, False, 3), (-0.012, True, 6)])
def test_latency_recovered_within_2ms(tmp_path, spec, latency, calibrated, seed):
    """10 s of bursty motion at 30 fps, rendered at the true exposure times, stamped late."""
    truth = default_truth(spec, width=320, height=240, f=260.0, latency_s=latency)
    write_latency_episode(tmp_path / "ep", spec, truth, rng=np.random.default_rng(seed), duration_s=10.0,
                          calibrated=calibrated)
    est = estimate_latency(tmp_path / "ep", bootstrap=40)
    assert est.signal == ("pixels" if calibrated else "metres")
    assert abs(est.latency_s - latency) < 0.002
    assert 0 < est.std_s < 0.004 and est.correlation > 0.9


def test_no_motion_is_refused():
    robot = RobotMotion(np.linspace(0, 5, 1001), np.zeros((1001, 3, 3)))
    with pytest.raises(NotEnoughDataError, match="no motion"):
        fit_latency(np.arange(0.5, 4.5, 0.1), np.zeros(39), robot)
    with pytest.raises(NotEnoughDataError, match="does not move"):
        fit_latency(np.arange(0.5, 4.5, 0.1), np.random.default_rng(0).random(39), robot)
    with pytest.raises(NotEnoughDataError, match="at least 9"):
        fit_latency(np.arange(5) * 0.1, np.ones(4), robot)


def test_the_robot_signal_sees_the_gripper_open_while_the_arm_stands(tmp_path, spec):
    """Finger motion shows in the image, so the robot signal must show it too."""
    ep = standing_episode(tmp_path / "ep", spec, 1.0, lambda t: 0.07 * t, [0.5])  # opens 7 cm/s, joints still
    motion, signal = robot_motion(ep)
    moved = motion.displacement(np.array([0.2]), np.array([0.8]))[0]  # (M,) metres
    assert signal == "metres" and moved.max() == pytest.approx(0.6 * 0.07 / 2, rel=0.05)  # one finger: half


def test_latency_command(tmp_path, spec, capsys):
    truth = default_truth(spec, width=320, height=240, f=260.0, latency_s=0.04)
    write_latency_episode(tmp_path / "ep", spec, truth, rng=np.random.default_rng(2), duration_s=5.0)
    assert main(["latency", str(tmp_path / "ep"), "--json", str(tmp_path / "l.json")]) == 0
    assert "latency " in capsys.readouterr().out
    import json
    est = json.loads((tmp_path / "l.json").read_text())
    assert abs(est["latency_s"] - 0.04) < max(0.01, 3 * est["latency_std_s"])


def test_latency_command_exit_codes(tmp_path, spec, capsys):
    """A still episode exits 3 (not enough data) and a non-positive search range exits 2."""
    standing_episode(tmp_path / "still", spec, 2.0, lambda t: 0.0, 0.5 + np.arange(30) / 30)
    assert main(["latency", str(tmp_path / "still")]) == 5
    assert "no motion" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["latency", str(tmp_path / "still"), "--max-offset", "0"])
    assert exc.value.code == 2 and "--max-offset: must be > 0" in capsys.readouterr().err


def test_a_long_episode_is_analysed_over_its_busiest_stretch():
    """40 s of frames, the robot moves only from 25 to 32 s: a 10 s window must cover that, and
    exact image motion gives the offset to a fraction of a millisecond."""
    t = np.arange(0.0, 40.0, 0.005)
    phase = np.clip((t - 25.0) / 7.0, 0.0, 1.0)
    x = 0.3 * (phase - np.sin(6 * np.pi * phase) / (6 * np.pi))  # three bursts, still elsewhere  [m]
    robot = RobotMotion(t, np.stack([x, 0.2 * x ** 2, np.zeros_like(x)], axis=1)[:, None, :])
    latency = 0.0213
    t_frames = np.arange(1.0, 39.0, 1 / 30)
    signals = {step: robot.displacement(t_frames[:-step] - latency, t_frames[step:] - latency)[:, 0]
               for step in (1, 2)}
    est = fit_latency(t_frames, signals, robot, bootstrap=10, max_span_s=10.0)
    assert est.window_s[1] - est.window_s[0] == pytest.approx(10.0)
    assert est.window_s[0] <= 25.0 and est.window_s[1] >= 32.0
    assert est.intervals <= 10.0 * 30 + 1
    assert abs(est.latency_s - latency) < 2e-4
