"""The checks a trajectory passes before anything moves: each problem found and named, all of them."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from manisplat.drivers.piper.convention import AGILEX_URDF_OLD, IDENTITY
from manisplat.drivers.piper.trajectory import (ReplayLimits, Trajectory, approach, check_trajectory, sample,
                                                trajectory_figures, trajectory_from_episode)
from manisplat.episode import Episode
from manisplat.robot import builtin_piper
from tests.replay.helpers import smooth_motion, write_episode

ROBOT = builtin_piper(with_geometry=False)
LIMITS = ReplayLimits()


def traj(t: np.ndarray, q: np.ndarray, g: np.ndarray | None = None, speed: float = 1.0) -> Trajectory:
    return Trajectory(t / speed, q, np.full(len(t), 0.03) if g is None else g, "joints", speed)


def test_actions_are_preferred_and_time_scales_with_speed(tmp_path: Path) -> None:
    t, q, g = smooth_motion()
    actions = np.concatenate([q + 0.01, g[:, None]], axis=1)
    ep = Episode.open(write_episode(tmp_path / "ep", t, q, g, actions=actions))
    tr = trajectory_from_episode(ep, IDENTITY, speed=2.0)
    assert tr.source == "actions" and tr.duration == pytest.approx(t[-1] / 2)
    np.testing.assert_allclose(tr.q, q + 0.01)
    tr = trajectory_from_episode(ep, AGILEX_URDF_OLD, source="joints")
    np.testing.assert_allclose(tr.q, AGILEX_URDF_OLD.to_arm(q))
    with pytest.raises(ValueError, match="speed"):
        trajectory_from_episode(ep, IDENTITY, speed=0.0)
    plain = Episode.open(write_episode(tmp_path / "plain", t, q, g))
    with pytest.raises(ValueError, match="no action columns"):
        trajectory_from_episode(plain, IDENTITY, source="actions")


def test_a_smooth_motion_passes_and_sampling_interpolates() -> None:
    t, q, g = smooth_motion()
    tr = traj(t, q, g)
    assert check_trajectory(tr, ROBOT, LIMITS, current_q=q[0]) == []
    qs, gs = sample(tr, 0.5 * (t[3] + t[4]))
    np.testing.assert_allclose(qs, 0.5 * (q[3] + q[4]))
    assert gs == pytest.approx(0.5 * (g[3] + g[4]))


def test_positions_outside_the_limits_are_named() -> None:
    t, q, g = smooth_motion()
    q = q.copy()
    q[5:8, 4] = math.radians(75)  # J5 limit is 70 deg
    g = g.copy()
    g[2] = 0.09
    problems = check_trajectory(traj(t, q, g), ROBOT, ReplayLimits(max_step_deg=180))
    assert any("joint5 leaves its limits" in p and "first frame 5 at 75.00 deg" in p for p in problems)
    assert any("gripper leaves" in p and "frame 2" in p for p in problems)


def test_velocity_and_acceleration_say_which_speed_passes() -> None:
    t = np.linspace(0, 1.0, 51)
    q = np.zeros((51, 6)) + np.radians([0, 60, -60, 0, 0, 0])
    q[:, 0] = 0.8 * np.sin(2 * np.pi * t)  # J1 peak 5.0 rad/s > 3.14 limit; 31.6 rad/s^2 > 5
    problems = check_trajectory(traj(t, q), ROBOT, ReplayLimits(max_step_deg=90))
    velocity = next(p for p in problems if p.startswith("velocity"))
    accel = next(p for p in problems if p.startswith("acceleration"))
    speed = min(float(velocity.split("--speed ")[1].split()[0]), float(accel.split("--speed ")[1].split()[0]))
    assert speed < 0.6
    assert check_trajectory(traj(t, q, speed=speed * 0.999), ROBOT, ReplayLimits(max_step_deg=90)) == []
    slow_arm = ReplayLimits(arm_speed_pct=10, max_step_deg=90)
    assert any("x 10 %" in p for p in check_trajectory(traj(t, q, speed=speed * 0.999), ROBOT, slow_arm))


def test_jumps_far_starts_and_bad_numbers_are_refused_all_at_once() -> None:
    t, q, g = smooth_motion()
    q = q.copy()
    q[10:, 1] += math.radians(12)  # a 12 deg jump between frames 9 and 10
    far = q[0] + math.radians(40)
    problems = check_trajectory(traj(t, q, g, speed=0.01), ROBOT, LIMITS, current_q=far)
    assert any("a jump of 12.7" in p and "joint2 between frames 9 and 10" in p for p in problems)
    assert any("the start is 40.0 deg from the arm's current state" in p for p in problems)
    q[3, 2] = np.nan
    assert check_trajectory(traj(t, q, g), ROBOT, LIMITS) == ["the trajectory holds NaN or infinite values"]
    t2 = t.copy()
    t2[4] = t2[3]
    assert "not after" in check_trajectory(traj(t2, np.nan_to_num(q), g), ROBOT, LIMITS)[0]


def test_the_approach_is_slow_and_ends_at_the_start() -> None:
    a, b = np.zeros(6), np.radians([30, 10, 0, 0, 0, 0])
    duration, at = approach(a, b, ROBOT, fraction=0.1)
    assert duration == pytest.approx(math.pi / 2 * math.radians(30) / (ROBOT.velocity_limits[0] * 0.1))
    np.testing.assert_allclose(at(0.0), a)
    np.testing.assert_allclose(at(duration), b)
    s = np.linspace(0, duration, 2001)
    speed = np.abs(np.diff([at(x) for x in s], axis=0)).max(axis=0) / (s[1] - s[0])
    assert np.all(speed <= ROBOT.velocity_limits * 0.1 * 1.001)


def test_the_built_in_sample_passes_the_replays_checks_at_speed_1(tmp_path: Path) -> None:
    """The sample a newcomer is told to try must replay as recorded (at 16 fps its wrist reached
    15 rad/s^2 against the 5 allowed)."""
    from manisplat.drivers.piper.convention import convention_for
    from manisplat.episode.synthetic import write_sample_episode

    episode = Episode.open(write_sample_episode(tmp_path / "sample", width=32, height=24))
    traj = trajectory_from_episode(episode, convention_for(episode.meta.robot.description, episode.path), 1.0)
    robot = builtin_piper(with_geometry=False)
    assert check_trajectory(traj, robot, ReplayLimits()) == []
    assert trajectory_figures(traj, robot, ReplayLimits())["peak_acceleration_of_limit"] < 0.9
