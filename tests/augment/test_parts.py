"""The pieces under augmentation: the Pinocchio copy of the robot, target sampling, timing."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from manisplat.augment.collision import SceneCollision
from manisplat.augment.kinematics import PinRobot
from manisplat.augment.sampling import sample_targets
from manisplat.augment.skills import finite_difference_ratios
from manisplat.augment.source import source_demo
from manisplat.augment.timing import time_motion
from manisplat.robot import builtin_piper


def test_pinocchio_model_matches_the_robot_model():
    robot = builtin_piper()
    kin = PinRobot(robot)
    q = robot.sample_configurations(20, generator=torch.Generator().manual_seed(0)).numpy()
    width = np.linspace(0, 0.07, 20)
    assert np.abs(kin.tcp_batch(q) - robot.tcp_pose(torch.as_tensor(q)).numpy()).max() < 1e-9
    links = robot.forward_kinematics(torch.as_tensor(q), torch.as_tensor(width)).numpy()
    for i in range(20):
        ours = kin.link_poses(q[i], width[i])
        for name in robot.link_names:
            assert np.abs(ours[name] - links[i, robot.link_index(name)]).max() < 1e-9
    # IK from a nearby start reaches the target far below the tolerance
    T = kin.tcp(q[3])
    sol = kin.ik(T, q[3] + 0.05, tol_pos=1e-4, tol_rot=1.75e-4)
    assert sol.ok(1e-6, 1e-6)


def test_targets_stay_in_their_ranges_and_follow_the_seed(twin):
    box = source_demo(twin).objects["box"]
    ranges, place = (0.08, 0.08, math.radians(45)), (0.05, 0.05, math.radians(45))
    draws = [sample_targets(twin, np.random.default_rng(s), ranges, place)["box"] for s in range(40)]
    for tgt in draws:
        for T, T0, r in ((tgt.T_start, box.T_rest, ranges), (tgt.T_place, box.T_placed, place)):
            d = T[:3, 3] - T0[:3, 3]
            assert abs(d[0]) <= r[0] and abs(d[1]) <= r[1] and abs(d[2]) < 1e-12
            R = T[:3, :3] @ T0[:3, :3].T  # a turn about the vertical only
            assert np.allclose(R[2], [0, 0, 1], atol=1e-9)
            assert abs(math.atan2(R[1, 0], R[0, 0])) <= r[2] + 1e-12
    spread = np.array([t.T_start[:2, 3] - box.T_rest[:2, 3] for t in draws])
    assert spread.std(axis=0).min() > 0.03  # actually uses the range
    again = sample_targets(twin, np.random.default_rng(7), ranges, place)["box"]
    assert np.array_equal(again.T_start, draws[7].T_start) and np.array_equal(again.T_place, draws[7].T_place)


@pytest.mark.parametrize("profile", ["time-optimal", "smooth"])
def test_timed_motions_keep_the_limits_and_the_boundary_velocities(profile):
    robot = builtin_piper()
    vlim, alim, dt = robot.velocity_limits * 0.95, robot.acceleration_limits * 0.95, 1 / 16
    a = np.array([0.0, 1.0, -1.0, 0.0, 0.3, 0.0])
    b = np.array([0.6, 1.4, -0.8, 0.2, 0.0, 0.3])
    v0 = np.array([0.3, 0.2, -0.1, 0.0, 0.0, 0.0])
    v1 = np.array([0.0, -0.3, 0.1, 0.0, 0.1, 0.0])
    timed = time_motion(np.stack([a, b]), v0, v1, vlim=vlim, alim=alim, dt=dt, profile=profile)
    q = timed.q
    assert np.allclose(q[0], a) and np.allclose(q[-1], b)
    assert timed.duration == (len(q) - 1) * dt and timed.duration >= timed.optimal - 1e-9
    # with a frame before at v0 and one after at v1, finite differences stay within the limits
    padded = np.concatenate([[a - v0 * dt], q, [b + v1 * dt]])
    rv, ra = finite_difference_ratios(padded, dt, robot.velocity_limits, robot.acceleration_limits)
    assert rv <= 1 and ra <= 1
    # and the leaving velocity is v0 (to first order in dt)
    assert np.abs((q[1] - q[0]) / dt - v0).max() < 0.6 * dt * robot.acceleration_limits.max()


def test_the_centre_frame_follows_the_objects_gaussians(twin):
    """augmentation.json's object frame: the reconstructed axes, the origin at the centre of the
    object's Gaussians (moving them moves it by as much), and the two frames convert both ways."""
    from manisplat.augment.frames import centre_offset, from_centre_frame, to_centre_frame

    means = twin.graph.objects["box"].params["means"]
    before = centre_offset(twin, "box")
    shift = torch.tensor([0.02, -0.01, 0.005])
    with torch.no_grad():
        means += shift
    try:
        after = centre_offset(twin, "box")
    finally:
        with torch.no_grad():
            means -= shift
    np.testing.assert_allclose(after[:3, 3] - before[:3, 3], shift.numpy(), atol=1e-6)
    np.testing.assert_array_equal(after[:3, :3], np.eye(3))
    pose = twin.object_poses["box"][0]
    np.testing.assert_allclose(from_centre_frame(twin, "box", to_centre_frame(twin, "box", pose)), pose, atol=1e-12)


def test_a_smooth_motion_between_rests_is_the_minimum_jerk_profile_over_the_fewest_frames():
    robot = builtin_piper()
    vlim, alim, dt = robot.velocity_limits * 0.95, robot.acceleration_limits * 0.95, 1 / 16
    a = np.array([0.0, 1.0, -1.0, 0.0, 0.3, 0.0])
    b = np.array([0.9, 1.6, -0.4, 0.5, -0.2, 1.2])
    zero = np.zeros(6)
    smooth = time_motion(np.stack([a, b]), zero, zero, vlim=vlim, alim=alim, dt=dt, profile="smooth")
    fast = time_motion(np.stack([a, b]), zero, zero, vlim=vlim, alim=alim, dt=dt)
    n = len(smooth.q) - 1
    tau = np.arange(n + 1) / n
    minimum_jerk = 10 * tau ** 3 - 15 * tau ** 4 + 6 * tau ** 5
    assert np.abs(smooth.q - (a + minimum_jerk[:, None] * (b - a))).max() < 1e-6
    # the fewest frames: peak speed 1.875 and peak acceleration 5.77 x (distance / duration)
    def within(frames: int) -> bool:
        duration = frames * dt
        return bool((1.875 * np.abs(b - a) / duration <= vlim).all()
                    and (10 / np.sqrt(3) * np.abs(b - a) / duration ** 2 <= alim).all())
    assert within(n) and not within(n - 1)
    # it starts gently where the time-optimal profile leaves at full acceleration, and takes longer
    first_step = lambda q: np.abs(q[1] - q[0]).max()  # noqa: E731
    assert first_step(smooth.q) < 0.2 * first_step(fast.q)
    assert n > len(fast.q) - 1


def test_an_unknown_timing_profile_is_refused():
    with pytest.raises(ValueError, match="profile"):
        time_motion(np.stack([np.zeros(6), np.ones(6)]), np.zeros(6), np.zeros(6), vlim=np.ones(6), alim=np.ones(6),
                    dt=0.1, profile="fast")


def test_the_table_is_the_surface_the_recordings_depth_measures_under_the_objects(twin):
    # the sample's table is the plane z = 0; the box's underside is never seen, so its lowest
    # Gaussians are a poor ruler (4 mm off here; 7.7 and 14 mm on the Cobot Magic sample)
    scene = SceneCollision(twin, PinRobot(twin.robot), source_demo(twin))
    assert scene.table_estimates.keys() >= {"support", "objects"}
    assert scene.table_z == scene.table_estimates["support"]
    assert abs(scene.table_z) < 5e-4
    without_map = copy.copy(twin)
    without_map.support = None
    scene = SceneCollision(without_map, PinRobot(twin.robot), source_demo(without_map))
    assert "support" not in scene.table_estimates
    assert scene.table_z == scene.table_estimates["objects"]
