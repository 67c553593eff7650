"""Streaming onto a simulated PiPER (real threads, real python-can virtual bus, real time): the
replay ends where it should, and every stop leaves the arm holding without reset or disable."""

from __future__ import annotations

import math
import threading
import time
from typing import Iterator

import numpy as np
import pytest

from manisplat.drivers.piper.streamer import StreamConfig, replay
from manisplat.drivers.piper.trajectory import Trajectory
from manisplat.drivers.replay_cli import SimArm
from tests.replay.helpers import smooth_motion

# generous where the test is not about it: a loaded CI machine must not trip these
RELAXED = dict(feedback_timeout_s=0.5, max_tracking_error_deg=20.0, settle_tol_deg=0.5)


def motion(duration: float = 1.5, amplitude_deg: float = 8.0) -> Trajectory:
    t, q, g = smooth_motion(duration, amplitude_deg=amplitude_deg)
    return Trajectory(t, q, g, "joints", 1.0)


@pytest.fixture
def sim() -> Iterator[SimArm]:
    traj = motion()
    arm = SimArm(traj.q[0] + math.radians(2.0), 0.05)  # 2 deg away: the approach runs
    yield arm
    arm.close()


def assert_never_dropped(sim: SimArm) -> None:
    assert sim.audit.resets == 0 and sim.audit.disables == 0 and sim.audit.estops == 0


def wait_for(predicate, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_a_replay_runs_to_the_end_and_reports_the_tracking(sim: SimArm) -> None:
    traj = motion()
    report = replay(sim.arm, traj, StreamConfig(**RELAXED))
    assert report.outcome == "completed", report
    assert report.streamed_s == pytest.approx(traj.duration) and report.ticks > 20
    assert report.final_error_deg.max() <= 0.5
    sim.sim.wait_cycles(5)  # the last commands reach the simulated arm
    np.testing.assert_allclose(sim.sim.state()["q"], traj.q[-1], atol=math.radians(0.5))
    tr = report.tracking
    assert tr.samples > 20 and 0 < tr.max_deg.max() < 5 and np.all(tr.lag_rms_deg <= tr.rms_deg + 1e-12)
    assert sim.sim.state()["gripper_target"] == pytest.approx(traj.gripper[-1], abs=1e-5)
    assert "holding its measured position" in report.left and "tracking error" in str(report)
    assert_never_dropped(sim)
    assert sim.audit.enables >= 1  # the simulated arm started disabled: enabled, never reset


def test_an_arm_resting_at_a_joint_limit_is_moved_to_the_start() -> None:
    """Its measured position may read a wire step beyond the limit; the approach must not command it."""
    traj = motion()
    robot_upper = SimArm(traj.q[0], 0.05)
    upper = robot_upper.arm.robot.upper.copy()
    robot_upper.close()
    start = traj.q[0].copy()
    start[4] = upper[4]  # joint5 at its limit, as the simulated arm starts when clipped there
    arm = SimArm(start, 0.05)
    try:
        report = replay(arm.arm, traj, StreamConfig(**RELAXED))
        assert report.outcome == "completed", report
        assert_never_dropped(arm)
    finally:
        arm.close()


def test_a_tracking_error_stops_the_stream_and_the_arm_holds(sim: SimArm) -> None:
    traj = motion(duration=1.0, amplitude_deg=20.0)  # ~1.1 rad/s: the arm lags by more than 1 deg
    report = replay(sim.arm, traj, StreamConfig(**{**RELAXED, "max_tracking_error_deg": 1.0}))
    assert report.outcome == "tracking_error" and "deg from its target" in report.detail
    assert report.streamed_s < traj.duration and "holding its measured position" in report.left
    sim.sim.wait_cycles(40)
    held = sim.sim.state()
    np.testing.assert_allclose(held["target"], held["q"], atol=math.radians(0.5))
    sim.sim.wait_cycles(40)
    np.testing.assert_allclose(sim.sim.state()["q"], held["q"], atol=math.radians(0.05))  # still
    assert_never_dropped(sim)


def test_lost_feedback_stops_the_stream_and_leaves_the_last_target(sim: SimArm) -> None:
    traj = motion(duration=3.0)
    config = StreamConfig(**{**RELAXED, "feedback_timeout_s": 0.1})
    result: dict = {}
    thread = threading.Thread(target=lambda: result.setdefault("r", replay(sim.arm, traj, config)), daemon=True)
    thread.start()
    wait_for(lambda: sim.audit.joint_targets > 350)  # well into the stream (the approach takes ~1 s)
    sim.sim.stop()  # the arm goes silent
    thread.join(20.0)
    returned = time.time()  # the virtual bus stamps each frame with time.time() when it is sent
    report = result["r"]
    assert report.outcome == "feedback_lost" and "no joint feedback within 0.1 s" in report.detail
    assert "last target sent (no fresh feedback" in report.left
    time.sleep(0.5)
    assert sim.audit.last_joint_target_stamp < returned  # nothing streamed after replay() returned
    sim.sim.start()  # the arm comes back: it holds the last streamed target
    sim.sim.wait_cycles(80)
    last = sim.arm._last_target[0]  # what PiperArm sent last
    np.testing.assert_allclose(sim.sim.state()["target"], last, atol=math.radians(0.001))
    assert report.streamed_s < traj.duration - 0.5
    assert_never_dropped(sim)


def test_a_stop_request_ends_the_stream_with_the_arm_holding(sim: SimArm) -> None:
    traj = motion(duration=3.0)
    stop = threading.Event()
    threading.Timer(2.0, stop.set).start()
    report = replay(sim.arm, traj, StreamConfig(**RELAXED), stop)
    assert report.outcome == "interrupted" and 0 < report.streamed_s < traj.duration
    assert "holding its measured position" in report.left
    sim.sim.wait_cycles(40)
    state = sim.sim.state()
    np.testing.assert_allclose(state["target"], state["q"], atol=math.radians(0.5))
    assert_never_dropped(sim)


def test_the_grippers_moves_and_grasps_are_not_reported_as_tracking_error() -> None:
    from manisplat.drivers.piper.streamer import GripperTracking

    sent_t = np.arange(0.0, 4.0, 0.005)
    sent_g = np.where(sent_t < 1.0, 0.07, 0.0)  # open, then told to close at 1 s
    fb_t = sent_t + 0.002
    closing = np.clip(0.07 - 0.1 * (fb_t - 1.0), 0.040, 0.07)  # 0.3 s of travel, then the box stops it at 40 mm
    fb_g = np.where(fb_t < 1.0, 0.0695, closing)
    fb_g[::50] = np.nan  # feedback without a gripper reading
    gripper = GripperTracking.of(sent_t, sent_g, fb_t, fb_g)
    assert gripper.settled_max_mm == pytest.approx(0.5)  # the open hold, 0.5 mm short
    assert gripper.held_mm == pytest.approx(40.0)
    assert "within 0.50 mm" in str(gripper) and "held something at 40.0 mm" in str(gripper)
    free = GripperTracking.of(sent_t, sent_g, fb_t, np.where(fb_t < 1.0, 0.07, np.clip(0.07 - 0.2 * (fb_t - 1.0), 0, 1)))
    assert free.held_mm is None and free.settled_max_mm < 1e-9


def test_targets_a_rounding_step_beyond_a_limit_are_streamed_inside_it(sim: SimArm) -> None:
    """The checks let 1e-9 beyond a limit pass (data like a gripper of 0.07000000000000006 m);
    the arm refuses any excess, so the streamer keeps the targets inside the limits."""
    traj = motion()
    at_limit = Trajectory(traj.t, traj.q, np.full(len(traj.t), 0.07000000000000006), "joints", 1.0)
    report = replay(sim.arm, at_limit, StreamConfig(**RELAXED))
    assert report.outcome == "completed", report
    assert sim.sim.state()["gripper_target"] == pytest.approx(0.07, abs=1e-5)
