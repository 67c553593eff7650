"""New demonstrations from a small twin: skills moved rigidly with their object, motions within
the limits the replay enforces, unreachable targets and obstacles handled, deterministic."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.interpolate import CubicSpline

from manisplat.augment.collision import BoxObstacle
from manisplat.augment.sampling import perturb
from manisplat.augment.source import source_demo
from manisplat.augment.trajectory import (AugmentConfig, ObjectTarget, Rejected, augment_trajectory, augmenter_for,
                                          sample_targets)
from manisplat.drivers.piper.trajectory import ReplayLimits, Trajectory, check_trajectory, trajectory_figures
from manisplat.robot import builtin_piper
from manisplat.twin.commands import CommandRelation

TOL_M, TOL_RAD = 1e-4, math.radians(0.01)


def _pose_errors(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and rotation (rad, the atan2 form: accurate for tiny angles) differences."""
    dp = np.linalg.norm(A[..., :3, 3] - B[..., :3, 3], axis=-1)
    R = np.swapaxes(A[..., :3, :3], -1, -2) @ B[..., :3, :3]
    skew = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    return dp, np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1))


def _source_tcp_at(twin, first: int, last: int, n: int) -> np.ndarray:
    """The source TCP at n source times evenly from ``first`` to ``last`` (the skill's frames, or
    the slowed skill's: a C2 spline through the source joints, as documented)."""
    s = np.linspace(first, last, n)
    q = CubicSpline(np.arange(len(twin.q)), twin.q, axis=0)(s)
    exact = np.isclose(s, np.round(s))
    q[exact] = twin.q[np.round(s[exact]).astype(int)]
    return twin.robot.tcp_pose(torch.as_tensor(q)).numpy()


def _tcp(twin, q: np.ndarray) -> np.ndarray:
    return twin.robot.tcp_pose(torch.as_tensor(q)).numpy()


def _source_targets(twin) -> dict[str, ObjectTarget]:
    src = source_demo(twin)
    return {k: ObjectTarget(o.T_rest, o.T_placed) for k, o in src.objects.items() if o.manipulated}


def _replay_problems(traj) -> tuple[list[str], dict]:
    robot = builtin_piper(with_geometry=False)
    out = []
    figures = {}
    for q, g in ((traj.action_q, traj.action_gripper), (traj.q, traj.gripper)):
        t = Trajectory(traj.t.copy(), q, g, "actions", 1.0)
        out += check_trajectory(t, robot, ReplayLimits())
        figures = trajectory_figures(t, robot, ReplayLimits())
    return out, figures


def test_zero_perturbation_reproduces_the_source_skills(twin):
    traj = augment_trajectory(twin, _source_targets(twin), AugmentConfig())
    skills = [s for s in traj.segments if s["kind"] == "skill"]
    assert [s["name"] for s in skills] == ["S_pick", "S_place"]
    for seg in skills:
        f0, f1 = seg["frames"]
        s0, s1 = seg["source_frames"]
        new = _tcp(twin, traj.q[f0:f1 + 1])
        src = _source_tcp_at(twin, s0, s1, f1 - f0 + 1)
        dp, dr = _pose_errors(new, src)
        assert dp.max() <= TOL_M and dr.max() <= TOL_RAD, (seg["name"], dp.max(), dr.max())
        assert np.allclose(np.array(seg["T"]), np.eye(4), atol=1e-12)
        # the gripper signal is the source's (at its ends, exactly), and so are its commands
        assert traj.gripper[f0] == pytest.approx(twin.gripper[s0], abs=1e-9)
        assert traj.gripper[f1] == pytest.approx(twin.gripper[s1], abs=1e-9)
        played = np.linspace(s0, s1, f1 - f0 + 1)  # source frames, slowed uniformly where a limit asked
        np.testing.assert_allclose(traj.action_gripper[f0:f1 + 1],
                                   np.interp(played, np.arange(len(twin.t)), twin.commands.gripper[:, 0]), atol=1e-9)
    # starts and ends where the source does
    assert np.allclose(traj.q[0], twin.q[0]) and traj.t[0] == 0
    assert np.allclose(np.diff(traj.t), 1 / twin.fps)
    assert traj.validation["skill_error_mm"] <= 0.1 and traj.validation["skill_error_deg"] <= 0.01


def test_a_shifted_object_moves_the_skills_by_exactly_its_transform(twin):
    src = source_demo(twin)
    box = src.objects["box"]
    T_start = perturb(box.T_rest, 0.03, -0.04, math.radians(20))
    T_place = perturb(box.T_placed, -0.02, 0.03, math.radians(-15))
    traj = augment_trajectory(twin, {"box": ObjectTarget(T_start, T_place)}, AugmentConfig())
    for seg in (s for s in traj.segments if s["kind"] == "skill"):
        f0, f1 = seg["frames"]
        s0, s1 = seg["source_frames"]
        T_new, T_src = (T_start, box.T_rest) if seg["name"] == "S_pick" else (T_place, box.T_placed)
        D = T_new @ np.linalg.inv(T_src)
        assert np.allclose(np.array(seg["T"]), D, atol=1e-12)
        new = _tcp(twin, traj.q[f0:f1 + 1])
        src_tcp = _source_tcp_at(twin, s0, s1, f1 - f0 + 1)
        dp, dr = _pose_errors(new, D @ src_tcp)
        assert dp.max() <= TOL_M and dr.max() <= TOL_RAD
        # relative to the object, the TCP is where it was in the source
        dp, dr = _pose_errors(np.linalg.inv(T_new) @ new, np.linalg.inv(T_src) @ src_tcp)
        assert dp.max() <= TOL_M and dr.max() <= TOL_RAD
    # the object starts at T_start, ends at T_place, and is carried at the source's grasp offset
    poses = traj.object_poses["box"]
    assert np.allclose(poses[0], T_start) and np.allclose(poses[-1], T_place, atol=1e-9)
    transfer = next(s for s in traj.segments if s["name"] == "M_transfer")
    tcp = _tcp(twin, traj.q[transfer["frames"][0]:transfer["frames"][1] + 1])
    grasp = np.linalg.inv(tcp) @ poses[transfer["frames"][0]:transfer["frames"][1] + 1]
    assert np.allclose(grasp, box.G, atol=1e-9)
    assert np.allclose(traj.objects["box"]["T_start"], T_start, atol=1e-12)


@pytest.mark.parametrize("profile", ["time-optimal", "smooth"])
def test_trajectories_pass_the_replay_checks_at_speed_one(twin, profile):
    for seed in range(4):
        targets = sample_targets(twin, np.random.default_rng(seed), (0.04, 0.04, math.radians(30)),
                                 (0.03, 0.03, math.radians(30)))
        try:
            traj = augment_trajectory(twin, targets, AugmentConfig(seed=seed, profile=profile))
        except Rejected as exc:
            assert exc.reason == "ik_unreachable", exc
            continue
        problems, figures = _replay_problems(traj)
        assert problems == []
        assert figures["peak_velocity_of_limit"] <= 1 and figures["peak_acceleration_of_limit"] <= 1
        assert ((traj.action_gripper >= 0.0) & (traj.action_gripper <= 0.07)).all()
        assert np.allclose(traj.action_q[:-1], traj.q[1:])
        assert traj.q.shape == (len(traj.t), 6) and traj.validation["collision_free"]
        assert traj.planner["profile"] == profile
        # frames inside the joint limits
        robot = builtin_piper(with_geometry=False)
        assert np.all(traj.q >= robot.lower - 1e-9) and np.all(traj.q <= robot.upper + 1e-9)


def test_slower_speed_gives_slower_motions(twin):
    fast = augment_trajectory(twin, _source_targets(twin), AugmentConfig(speed=1.0))
    slow = augment_trajectory(twin, _source_targets(twin), AugmentConfig(speed=0.5))
    frames = lambda tr: sum(s["frames"][1] - s["frames"][0] + 1 for s in tr.segments if s["kind"] == "motion")  # noqa: E731
    assert frames(slow) > 1.3 * frames(fast)


def test_an_unreachable_target_is_rejected(twin):
    box = source_demo(twin).objects["box"]
    far = perturb(box.T_rest, 1.5, 0.0, 0.0)
    with pytest.raises(Rejected) as info:
        augment_trajectory(twin, {"box": ObjectTarget(far, box.T_placed)}, AugmentConfig())
    assert info.value.reason == "ik_unreachable"


def _spread_targets(twin) -> dict[str, ObjectTarget]:
    """The box picked 6 cm to one side and placed 5 cm to the other: a long transfer."""
    box = source_demo(twin).objects["box"]
    return {"box": ObjectTarget(perturb(box.T_rest, 0.0, -0.06, 0.0), perturb(box.T_placed, 0.0, 0.05, 0.0))}


def _obstacle_on_transfer(twin) -> BoxObstacle:
    """A 3 cm cube where the TCP passes in the middle of the straight transfer."""
    traj = augment_trajectory(twin, _spread_targets(twin), AugmentConfig())
    seg = next(s for s in traj.segments if s["name"] == "M_transfer")
    assert next(r for r in traj.planner["segments"] if r["segment"] == "M_transfer")["method"] == "straight"
    f0, f1 = seg["frames"]
    T = np.eye(4)
    T[:3, 3] = _tcp(twin, traj.q[(f0 + f1) // 2])[:3, 3]
    return BoxObstacle((0.03, 0.03, 0.03), T)


def test_an_obstacle_on_the_straight_path_forces_a_collision_free_detour(twin):
    obstacle = _obstacle_on_transfer(twin)
    config = AugmentConfig(obstacles=(obstacle,), planner_timeout_s=5.0, seed=1)
    traj = augment_trajectory(twin, _spread_targets(twin), config)
    transfer = next(r for r in traj.planner["segments"] if r["segment"] == "M_transfer")
    assert transfer["method"] == "rrtconnect"
    # independently of the planner: the TCP stays out of the cube, densely between frames
    seg = next(s for s in traj.segments if s["name"] == "M_transfer")
    f0, f1 = seg["frames"][0] - 1, seg["frames"][1] + 1
    q = traj.q[f0:f1 + 1]
    dense = np.concatenate([a + np.linspace(0, 1, 20, endpoint=False)[:, None] * (b - a) for a, b in zip(q[:-1], q[1:])])
    centre = obstacle.T[:3, 3]
    tcp = _tcp(twin, dense)[:, :3, 3]
    assert np.abs(tcp - centre).max(axis=1).min() > 0.015 + 0.005
    assert traj.validation["collision_free"]
    problems, _ = _replay_problems(traj)
    assert problems == []


@pytest.mark.parametrize("speed, back", [(0.6, 0.02), (1.5, 0.1)])
def test_a_motion_that_must_reverse_the_skills_velocity_brakes_to_rest_first(twin, speed, back):
    """The motion after a skill that ends moving at ``speed`` rad/s (joint 1) goes ``back`` rad
    the other way: no spline leaves at that speed and turns within the limits, so the arm brakes
    along its velocity to rest, goes back, and the joins keep the replay's limits."""
    augmenter, config = augmenter_for(twin), AugmentConfig()
    q_a = source_demo(twin).q[0].copy()
    v_a = np.zeros(6)
    v_a[0] = speed
    q_b = q_a - back * np.eye(6)[0]
    records: list[dict] = []
    piece = augmenter._motion("M_test", q_a, q_b, v_a, np.zeros(6), 0.07, augmenter._object_plan(_source_targets(twin)),
                              0.0, augmenter.vlim * config.headroom, augmenter.alim * config.headroom, config, seed=0,
                              timings={"planning_s": 0.0, "timing_s": 0.0}, attempts=records)
    q = piece["q"]
    assert records[-1]["joined"] == "at rest"
    assert np.array_equal(q[0], q_a) and np.array_equal(q[-1], q_b)
    # it keeps going the skill's way while it brakes (a stop distance of v^2 / alim at half the
    # acceleration limit, within 1 %) and is at rest before it turns
    stop = speed ** 2 / augmenter.alim[0]
    assert (q[:, 0] - q_a[0]).max() == pytest.approx(stop, rel=0.01)
    # the skill's last frames moving at v_a, then the motion: the replay's checks pass across the join
    dt = augmenter.dt
    joined = np.concatenate([q_a - np.outer([3, 2, 1], v_a) * dt, q])
    t = np.arange(len(joined)) * dt
    robot = builtin_piper(with_geometry=False)
    assert check_trajectory(Trajectory(t, joined, np.full(len(t), 0.07), "actions", 1.0), robot, ReplayLimits()) == []
    v = np.diff(joined, axis=0) / dt
    assert np.abs(np.diff(v, axis=0) / dt).max() <= augmenter.alim.max() * 1.001


def test_a_timed_motion_that_leaves_the_joint_limits_is_not_taken(twin):
    """The timed spline can bulge past a planner's waypoint: a frame beyond a limit (the
    validation's tolerance) sends the motion back to be followed more closely or re-planned."""
    augmenter = augmenter_for(twin)
    q = source_demo(twin).q[:3].copy()
    assert augmenter._departure(q, 0.07) != "limits"
    q[1, 4] = augmenter.kin.upper[4]  # on the limit is inside
    assert augmenter._departure(q, 0.07) != "limits"
    q[1, 4] = augmenter.kin.upper[4] + 2e-9
    assert augmenter._departure(q, 0.07) == "limits"
    q[1, 4] = augmenter.kin.lower[4] - 2e-9
    assert augmenter._departure(q, 0.07) == "limits"


def test_an_obstacle_that_blocks_everything_is_rejected(twin):
    box = source_demo(twin).objects["box"]
    T = np.eye(4)
    T[:3, 3] = box.T_rest[:3, 3] + [0, 0, 0.15]
    wall = BoxObstacle((0.3, 0.3, 0.1), T)  # over the object: the approach and the pick cannot pass
    with pytest.raises(Rejected) as info:
        augment_trajectory(twin, _source_targets(twin), AugmentConfig(obstacles=(wall,), planner_timeout_s=0.3))
    assert info.value.reason in ("collision", "planner_timeout")


def test_deterministic_for_a_seed(twin):
    again = sample_targets(twin, np.random.default_rng(5))
    assert np.array_equal(sample_targets(twin, np.random.default_rng(5))["box"].T_start, again["box"].T_start)
    # with the planner in play (OMPL re-seeded from the seed); whether a seed's straight path
    # passes the cube depends on the twin to the last bit (the IK's seeded solutions), so the
    # first seed that needs the planner is taken
    obstacle = _obstacle_on_transfer(twin)
    for seed in range(11, 31):
        config = AugmentConfig(obstacles=(obstacle,), planner_timeout_s=5.0, seed=seed)
        a = augment_trajectory(twin, _spread_targets(twin), config)
        if next(r for r in a.planner["segments"] if r["segment"] == "M_transfer")["method"] == "rrtconnect":
            break
    else:
        pytest.fail("no seed of 11-30 needed the planner for the transfer past the cube")
    b = augment_trajectory(twin, _spread_targets(twin), config)
    assert np.array_equal(a.q, b.q) and np.array_equal(a.gripper, b.gripper)
    assert [s["frames"] for s in a.segments] == [s["frames"] for s in b.segments]


def test_an_object_set_down_across_a_step_is_rejected(twin):
    """A 4 mm step in the measured support right under the source's place pose (the box would rest
    on an edge): the same targets that augment fine on a flat table are discarded as unstable; a
    step 10 cm away changes nothing."""
    from manisplat.twin.support import SupportMap

    place = source_demo(twin).objects["box"].T_placed[:2, 3]
    flat = twin.support
    try:
        for offset, rejected in ((0.0, True), (0.10, False)):
            heights = np.zeros((400, 400), np.float32)
            origin = (-1.0, -1.0)
            xs = origin[0] + np.arange(400) * 0.005
            heights[:, xs >= place[0] + offset] = 0.004
            twin.support = SupportMap(heights, origin, 0.005)
            if rejected:
                with pytest.raises(Rejected) as info:
                    augment_trajectory(twin, _source_targets(twin), AugmentConfig())
                assert info.value.reason == "unstable_support" and "falls away 4.0 mm" in info.value.detail
            else:
                augment_trajectory(twin, _source_targets(twin), AugmentConfig())
    finally:
        twin.support = flat


def test_the_gripper_commands_are_the_sources_where_recorded_else_open_or_closed(twin):
    """The sample's recorded gripper commands close over several frames, ahead of its fingers; a
    twin without them commands open (0.07) or closed (0) from the grasp to the release."""
    recorded = augment_trajectory(twin, _source_targets(twin), AugmentConfig())
    ramp = (recorded.action_gripper > 1e-6) & (recorded.action_gripper < 0.07 - 1e-6)
    assert ramp.sum() >= 3
    demo = twin.demonstration
    without = twin.with_demonstration(replace(demo, commands=CommandRelation(demo.commands.lead, demo.commands.press)))
    binary = augment_trajectory(without, _source_targets(without), AugmentConfig())
    assert set(np.unique(binary.action_gripper)) == {0.0, 0.07}
    closing = np.flatnonzero(binary.action_gripper == 0.0)[0]
    assert recorded.action_gripper[closing - 1] < 0.07  # the recorded commands start closing earlier


def test_a_new_start_is_where_the_demonstration_begins_and_the_skills_stay_where_they_were(twin):
    """start_q: frame 0 is the given start, the first motion is planned from it (within the limits
    the replay enforces), the skills are the same as from the source's start, and the planner
    record says how far the start moved; a start of the wrong size is refused."""
    targets = _source_targets(twin)
    aug = augmenter_for(twin)
    start = np.clip(aug.src.q[0] + np.radians([6.0, -4.0, 5.0, -8.0, 3.0, 10.0]), aug.kin.lower, aug.kin.upper)
    own = augment_trajectory(twin, targets, AugmentConfig())
    moved = augment_trajectory(twin, targets, AugmentConfig(), start_q=start)
    np.testing.assert_allclose(moved.q[0], start, atol=1e-12)
    assert np.abs(own.q[0] - start).max() > np.radians(5)
    np.testing.assert_allclose(moved.planner["start_offset_deg"], np.degrees(start - aug.src.q[0]), atol=1e-3)
    assert own.planner["start_offset_deg"] == [0.0] * aug.kin.dof
    skills = lambda tr: [tr.q[s["frames"][0]:s["frames"][1] + 1] for s in tr.segments if s["kind"] == "skill"]  # noqa: E731
    for a, b in zip(skills(own), skills(moved), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-9)
    assert moved.segments[0]["name"] == "M_approach"
    problems, _ = _replay_problems(moved)
    assert problems == []
    with pytest.raises(ValueError, match="start_q must be"):
        augment_trajectory(twin, targets, AugmentConfig(), start_q=start[:5])


def test_sampled_starts_stay_within_their_range_and_the_joint_limits():
    from manisplat.augment.sampling import sample_start
    rng = np.random.default_rng(0)
    q0 = np.array([0.0, 1.5, -1.3, 0.0, -1.2, 0.0])
    lower, upper = np.full(6, -1.25), np.full(6, 1.6)
    starts = np.stack([sample_start(rng, q0, 0.2, lower, upper) for _ in range(200)])
    assert (starts >= lower).all() and (starts <= upper).all()
    assert (np.abs(starts - np.clip(q0, lower, upper)) <= 0.2 + 1e-12).all()
    assert (starts[:, 0].max() - starts[:, 0].min()) > 0.3  # spread over the range, not stuck at the source
    assert np.allclose(sample_start(rng, q0, 0.0, lower, upper), np.clip(q0, lower, upper))
    with pytest.raises(ValueError, match="half-range"):
        sample_start(rng, q0, -0.1, lower, upper)
