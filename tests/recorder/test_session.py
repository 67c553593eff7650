"""End to end on simulated hardware: a simulated PiPER on a virtual bus (lock-step on a
ManualClock) and a replayed camera, recorded by the real Recorder into real files."""

from __future__ import annotations

import time
from pathlib import Path

import can
import numpy as np
import pytest

from manisplat.episode import Episode, validate
from manisplat.recorder.simrig import wave_gripper_effort
from manisplat.recorder.sync import FLAG_GAP, FLAG_HELD, FLAG_NAMES
from tests.recorder.helpers import FPS, lockstep_rig, source_frame, write_source

MAX_SYNC_ERROR_DEG = 0.05


def truth_error_deg(rig, ep: Episode) -> np.ndarray:
    """Per frame, the largest joint error (deg) against the simulated arm's true state at the
    frame's true mid-exposure time (what the replayed camera exposed, whatever its stamp said)."""
    exposure = dict(rig.camera.exposures)
    t_true = np.array([exposure[int(s)] for s in ep.frames.extra["seq"]])
    truth = rig.rig.truth(t_true)
    return np.degrees(np.abs(ep.frames.q - truth[:, :6])).max(axis=1)


def test_synced_joints_match_the_true_state_at_the_frame_times(tmp_path: Path, source: Path) -> None:
    rig = lockstep_rig(source, stamp_latency_s=0.020, latency_s=0.020)
    try:
        result = rig.recorder.record_episode(tmp_path / "ep", duration=3.0)
    finally:
        rig.close()
    assert result.error is None and result.valid
    assert validate(tmp_path / "ep").ok  # with full image decoding
    ep = Episode.open(tmp_path / "ep")
    err = truth_error_deg(rig, ep)
    assert len(ep) >= 85 and err.max() < MAX_SYNC_ERROR_DEG, f"max sync error {err.max():.4f} deg"
    exposure = dict(rig.camera.exposures)
    truth = rig.rig.truth(np.array([exposure[int(s)] for s in ep.frames.extra["seq"]]))
    assert np.abs(ep.frames.gripper - truth[:, 6]).max() < 1e-4  # 0.1 mm, from the gripper's own frames
    t_exposed = np.array([exposure[int(s)] for s in ep.frames.extra["seq"]]) - rig.rig.m0
    effort = ep.frames.extra["gripper_effort"]  # with the width, from the same frames (0.001 N*m steps)
    assert np.abs(effort - wave_gripper_effort(t_exposed)).max() < 3e-3 and np.ptp(effort) > 0.5
    assert not ep.frames.extra["sync_flags"].any()
    np.testing.assert_allclose(np.diff(ep.frames.t), 1 / FPS, atol=1e-6)
    exposure = dict(rig.camera.exposures)  # frames.csv t is the true exposure time: the latency was applied
    t0 = ep.meta.extra["clock"]["t0_monotonic"]
    np.testing.assert_allclose(ep.frames.t + t0, [exposure[int(s)] for s in ep.frames.extra["seq"]], atol=1e-9)
    # the images are the camera's, in order
    for i in (0, len(ep) // 2, len(ep) - 1):
        np.testing.assert_array_equal(ep.rgb(i), source_frame(int(ep.frames.extra["seq"][i]) % 60))
    # joints.csv: every sample at 200 Hz, on the same clock, matching the truth
    # (the rig's clock may lead the camera by up to 0.1 s, so the episode's end, not 3.0 s, is the reference)
    j = ep.joints()
    assert np.diff(j.t).max() < 0.0051 and j.t[0] < 0.0051  # no sample missing from the start
    assert ep.frames.t[-1] <= j.t[-1] < ep.frames.t[-1] + 0.2  # to the end, a few past the last frame
    jt = rig.rig.truth(j.t + ep.meta.extra["clock"]["t0_monotonic"])
    assert np.degrees(np.abs(j.q - jt[:, :6])).max() < MAX_SYNC_ERROR_DEG
    # the CAN log: every frame the arm sent during the episode, time 0 = the episode's start
    log = list(can.LogReader(tmp_path / "ep" / "can.asc"))
    assert len(log) == result.stats.can_frames_logged and result.stats.can_frames_dropped == 0
    assert 0.0 <= log[0].timestamp < 0.006 and log[-1].timestamp >= ep.frames.t[-1]
    assert len(log) == pytest.approx(3040 * (log[-1].timestamp - log[0].timestamp), rel=0.005)  # none missing
    meta = ep.meta.extra
    assert meta["clock"]["camera_latency_s"] == 0.020 and meta["clock"]["offset_uncertainty_s"] == 0.0
    assert meta["stats"]["frames"] == len(ep) and meta["stats"]["flagged"] == 0


def test_without_the_latency_correction_the_error_is_larger(tmp_path: Path, source: Path) -> None:
    rig = lockstep_rig(source, stamp_latency_s=0.020, latency_s=0.0)
    try:
        rig.recorder.record_episode(tmp_path / "ep", duration=2.0)
    finally:
        rig.close()
    assert truth_error_deg(rig, Episode.open(tmp_path / "ep")).max() > 0.3


def test_teleoperation_actions_are_the_leader_commands(tmp_path: Path, source: Path) -> None:
    rig = lockstep_rig(source, motion="teleop")
    try:
        deadline = time.monotonic() + 5.0  # the first command may still be on its way to the listener
        while not rig.recorder.feed.leader.seen and time.monotonic() < deadline:
            time.sleep(0.001)
        assert rig.recorder.feed.leader.seen
        result = rig.recorder.record_episode(tmp_path / "ep", duration=2.0)
    finally:
        rig.close()
    assert result.valid
    ep = Episode.open(tmp_path / "ep")
    t_mono = ep.frames.t + ep.meta.extra["clock"]["t0_monotonic"]
    expected = rig.rig.leader_command(t_mono)
    actions = ep.frames.actions
    assert actions is not None
    np.testing.assert_allclose(np.degrees(actions[:, :6]), np.degrees(expected[:, :6]), atol=0.001)
    np.testing.assert_allclose(actions[:, 6], expected[:, 6], atol=2e-6)
    assert truth_error_deg(rig, ep).max() < MAX_SYNC_ERROR_DEG  # the follower, which lags the leader
    assert np.degrees(np.abs(actions[:, :6] - ep.frames.q)).max() > 0.5
    assert ep.meta.extra["actions"]["gripper_from_state_frames"] == 0


def test_a_silent_bus_flags_the_frames_and_recording_goes_on(tmp_path: Path, source: Path) -> None:
    rig = lockstep_rig(source)
    start = rig.clock.monotonic()
    rig.rig.silence(start + 1.0, start + 1.6)
    try:
        result = rig.recorder.record_episode(tmp_path / "ep", duration=3.0)
    finally:
        rig.close()
    assert result.error is None and result.valid
    ep = Episode.open(tmp_path / "ep")
    j, t = ep.joints(), ep.frames.t
    k = int(np.argmax(np.diff(j.t)))
    lo, hi = j.t[k], j.t[k + 1]  # the last joint sample before the dropout and the first after
    assert hi - lo == pytest.approx(0.6, abs=0.006)
    assert lo + ep.meta.extra["clock"]["t0_monotonic"] - start == pytest.approx(1.0, abs=0.006)
    flags = ep.frames.extra["sync_flags"].astype(int)
    inside = (t > lo + 0.001) & (t < hi - 0.001)  # (the gripper's frames come 0.4 ms after the joints')
    outside = (t < lo - 0.001) | (t > hi + 0.001)
    assert inside.sum() >= 15 and np.all(flags[inside] & (FLAG_GAP | FLAG_HELD))
    assert not flags[outside].any() and len(ep) >= 85  # frames kept coming, all of them written
    # counted as written, flag by flag (held or interpolated across the gap: which, depends on
    # whether the samples after the dropout arrived before the frame was decided)
    named = {name: int(np.count_nonzero(flags & bit)) for bit, name in FLAG_NAMES.items() if np.any(flags & bit)}
    assert result.stats.flagged == np.count_nonzero(flags) and result.stats.flag_counts == named
    assert truth_error_deg(rig, ep)[outside].max() < MAX_SYNC_ERROR_DEG


def test_a_stalled_camera_is_counted_and_recording_goes_on(tmp_path: Path) -> None:
    stalling = write_source(tmp_path / "stalling", frames=90, missing=range(30, 60))  # 1 s without frames
    rig = lockstep_rig(stalling, loop=False)
    try:
        result = rig.recorder.record_episode(tmp_path / "ep", duration=10.0)
    finally:
        rig.close()
    assert result.valid and result.stats.stop_reason == "camera ended"
    s = result.stats
    assert (s.frames, s.dropped_camera, s.camera_stalls) == (60, 30, 1)
    assert s.longest_camera_gap_s == pytest.approx(31 / FPS, abs=1e-6)
    ep = Episode.open(tmp_path / "ep")
    seq = ep.frames.extra["seq"].astype(int)
    assert seq.tolist() == list(range(30)) + list(range(60, 90))
    assert np.diff(ep.joints().t).max() < 0.0051  # the joint stream did not stall
    assert truth_error_deg(rig, ep).max() < MAX_SYNC_ERROR_DEG


def test_depth_is_recorded_when_asked_and_refused_when_missing(tmp_path: Path, source: Path) -> None:
    with_depth = write_source(tmp_path / "with_depth", frames=20, depth=True)
    rig = lockstep_rig(with_depth, loop=False, depth=True)
    try:
        # the recording ends when the 20-frame source does; the duration only bounds it (a loaded
        # 2-core runner once took over 5 s for the 20 frames)
        result = rig.recorder.record_episode(tmp_path / "ep", duration=120.0)
    finally:
        rig.close()
    assert result.valid and result.stats.frames == 20
    ep = Episode.open(tmp_path / "ep")
    np.testing.assert_allclose(ep.depth(5), 1.005, atol=1e-3)
    rig = lockstep_rig(source, depth=True)
    try:
        result = rig.recorder.record_episode(tmp_path / "ep2", duration=1.0)
    finally:
        rig.close()
    assert result.stats.stop_reason == "camera error" and "without depth" in result.error


def test_can_stamps_off_the_wall_clock_fall_back_to_host_arrival_times(tmp_path: Path, source: Path) -> None:
    """An interface with its own time base (stamps far from the wall clock): real time, SystemClock."""
    from manisplat.drivers.piper import PiperArm
    from manisplat.drivers.replay import EpisodeCamera
    from manisplat.recorder.clock import SystemClock
    from manisplat.recorder.replaycam import ReplayCamera
    from manisplat.recorder.session import Recorder, RecorderConfig
    from manisplat.recorder.simrig import SimRig

    clock = SystemClock()
    rig = SimRig(clock, motion="wave", keep_states=False)
    rig.sim.t0 = rig.t0_wall = 5000.0  # stamps count from 5000 s, not the epoch
    rig.start()
    arm = PiperArm(rig.open_bus(), read_only=True, own_bus=True)
    camera = ReplayCamera(lambda: EpisodeCamera(source), clock, loop=True)
    try:
        recorder = Recorder(arm, camera, clock, RecorderConfig(), nominal_fps=FPS)
        recorder.wait_for_arm(timeout=10.0)
        result = recorder.record_episode(tmp_path / "ep", duration=1.5)
    finally:
        camera.close()
        rig.stop()
        arm.close()
    assert recorder.feed.can_stamps == "host" and result.valid
    ep = Episode.open(tmp_path / "ep")
    assert ep.meta.extra["clock"]["can_timestamps"] == "host arrival time (monotonic)"
    # host arrival times put the rows on the episode's timeline, within its 1.5 s (not 5000 s
    # away); how many arrive, and when the first does, depends on the machine's load (on a
    # saturated 2-core machine the first came 0.94 s in)
    joints = ep.joints()
    assert len(ep) >= 10 and len(joints) >= 30
    assert 0.0 <= joints.t[0] < joints.t[-1] < 2.0


@pytest.mark.parametrize("image_format", ["png", "jpg"])
def test_how_the_source_kept_its_colour_outlives_png_files(tmp_path: Path, image_format: str) -> None:
    from manisplat.episode.chroma import set_chroma_subsampling
    from manisplat.episode.images import StoredChroma

    source = write_source(tmp_path / "source", frames=10)
    set_chroma_subsampling(source, "4:2:2")  # e.g. frames of a 4:2:2 video, stored as PNG
    rig = lockstep_rig(source, loop=False, image_format=image_format)
    try:
        result = rig.recorder.record_episode(tmp_path / "ep", duration=120.0)
    finally:
        rig.close()
    assert result.valid
    ep = Episode.open(tmp_path / "ep")
    if image_format == "png":
        assert ep.chroma_subsampling() == StoredChroma("4:2:2") == rig.camera.chroma_subsampling
    else:  # the recorder's own JPEG files, 4:2:0, say it in their header
        assert "chroma_subsampling" not in ep.camera.extra and ep.chroma_subsampling() == StoredChroma("4:2:0")
