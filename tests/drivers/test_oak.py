"""The OAK camera side: depthai's real record/replay path (RecordVideo + RecordMessage written
by a host-only pipeline, read back by ReplayVideo + ReplayMessage, no device), intrinsics from a
depthai calibration, episode replays, and the Camera / Arm interfaces."""

from __future__ import annotations

import time

import depthai as dai
import numpy as np
import pytest

from manisplat.drivers.base import Arm, Camera, DriverError, SequenceTracker
from manisplat.drivers.oak import DepthaiReplayCamera, OakCamera, OakConfig, intrinsics_at
from manisplat.drivers.replay import EpisodeArm, EpisodeCamera
from manisplat.episode import CameraInfo, EpisodeWriter, RobotInfo
from manisplat.episode.images import StoredChroma

from .depthai_recording import write_recording

H, W = 48, 64


def calibration(tmp_path) -> tuple[dai.CalibrationHandler, object]:
    """A 1920x1080 CAM_A calibration (f = 1000 px, centred), saved as depthai's JSON."""
    handler = dai.CalibrationHandler()
    handler.setCameraIntrinsics(dai.CameraBoardSocket.CAM_A, [[1000.0, 0, 960.0], [0, 1000.0, 540.0], [0, 0, 1]],
                                1920, 1080)
    handler.setDistortionCoefficients(dai.CameraBoardSocket.CAM_A, [0.1, -0.05, 0.001, 0.002, 0.01] + [0.0] * 9)
    path = tmp_path / "calib.json"
    handler.eepromToJsonFile(path)
    return handler, path


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """12 frames recorded through depthai's own nodes; sequence 8 missing (a drop)."""
    folder = tmp_path_factory.mktemp("depthai")
    rng = np.random.default_rng(0)
    seq = np.array([5, 6, 7, 9, 10, 11, 12, 13, 14, 15, 16, 17])
    t = 5000.0 + (seq - 5) / 30.0
    rgb = rng.integers(0, 256, (len(seq), H, W, 3), dtype=np.uint8)
    depth = rng.integers(0, 6000, (len(seq), H, W), dtype=np.uint16)
    files = write_recording(folder, rgb, t, seq, exposure_us=8000, depth_mm=depth)
    return files, rgb, t, seq, depth


def test_depthai_replay_gives_back_what_was_recorded(recording, tmp_path):
    (video, meta, depth_file), rgb, t, seq, depth = recording
    _, calib_json = calibration(tmp_path)
    with DepthaiReplayCamera(video, depth=depth_file, calibration=calib_json) as cam:
        assert isinstance(cam, Camera) and (cam.width, cam.height) == (W, H)
        assert cam.chroma_subsampling == StoredChroma("4:4:4")  # RecordVideo kept the BGR frames losslessly (ffv1)
        frames = list(iter(lambda: cam.read(timeout=5.0), None))
        assert cam.read() is None
    # RecordVideo loses the last frame when its pipeline stops (depthai behaviour)
    assert len(seq) - 1 <= len(frames) <= len(seq)
    for k, f in enumerate(frames):
        assert f.seq == seq[k]
        np.testing.assert_array_equal(f.rgb, rgb[k])  # lossless, RGB order
        assert f.exposure_s == pytest.approx(0.008)
        assert f.t == pytest.approx(t[k] - 0.004, abs=1e-6)  # middle of the 8 ms exposure
        np.testing.assert_array_equal(f.depth, depth[k].astype(np.float32) * np.float32(1e-3))
    assert [f.dropped for f in frames[:5]] == [0, 0, 0, 1, 0]  # sequence 8 was never recorded
    assert cam.tracker.dropped == 1


def test_a_slow_reader_loses_no_replayed_frame(recording):
    """depthai's replay runs at the recorded rate and stops its pipeline at the end; frames a
    slower reader has not taken yet must still come out."""
    (video, meta, depth_file), rgb, t, seq, depth = recording
    with DepthaiReplayCamera(video, depth=depth_file, K=np.eye(3)) as cam:
        frames = []
        while (f := cam.read(timeout=5.0)) is not None:
            frames.append(f)
            time.sleep(0.06)  # twice the recorded frame interval
    assert len(seq) - 1 <= len(frames) and [f.seq for f in frames] == list(seq[: len(frames)])
    assert all(f.depth is not None for f in frames) and cam.frames_without_depth == 0


def test_replay_intrinsics_from_a_depthai_calibration(recording, tmp_path):
    (video, meta, _), *_ = recording
    handler, calib_json = calibration(tmp_path)
    with DepthaiReplayCamera(video, meta, calibration=calib_json) as cam:
        expected = np.array(handler.getCameraIntrinsics(dai.CameraBoardSocket.CAM_A, W, H))
        np.testing.assert_allclose(cam.K, expected)
        np.testing.assert_allclose(cam.dist, [0.1, -0.05, 0.001, 0.002, 0.01], rtol=1e-6)
        assert cam.read().depth is None
    # by hand: 1920x1080 -> 640x360 is a 1/3 scale; 640x480 crops (f kept) or stretches (fy 4/3 larger)
    K, _ = intrinsics_at(handler, "CAM_A", 640, 360)
    np.testing.assert_allclose(K, [[1000 / 3, 0, 320], [0, 1000 / 3, 180], [0, 0, 1]], rtol=1e-6)
    K, _ = intrinsics_at(handler, "CAM_A", 640, 480, "crop")
    np.testing.assert_allclose(K, [[1000 / 3, 0, 320], [0, 1000 / 3, 240], [0, 0, 1]], rtol=1e-6)
    K, _ = intrinsics_at(handler, "CAM_A", 640, 480, "stretch")
    np.testing.assert_allclose(K, [[1000 / 3, 0, 320], [0, 4000 / 9, 240], [0, 0, 1]], rtol=1e-6)


def test_replay_refuses_what_it_cannot_play(recording, tmp_path):
    (video, meta, _), *_ = recording
    with pytest.raises(DriverError, match="video .*none.mkv not found"):
        DepthaiReplayCamera(tmp_path / "none.mkv", meta, K=np.eye(3))
    with pytest.raises(DriverError, match="exactly one"):
        DepthaiReplayCamera(video, meta)
    with pytest.raises(DriverError, match="metadata .*missing.mcap not found"):
        DepthaiReplayCamera(video, tmp_path / "missing.mcap", K=np.eye(3))


def test_a_missing_device_is_a_clear_error_fast():
    if dai.Device.getAllAvailableDevices():
        pytest.skip("an OAK device is attached")
    t0 = time.monotonic()
    with pytest.raises(DriverError, match="no OAK device found"):
        OakCamera(OakConfig(width=640, height=400, depth=True))
    assert time.monotonic() - t0 < 5.0
    with pytest.raises(ValueError, match="resize"):
        OakConfig(resize="letterbox")
    with pytest.raises(ValueError, match="socket"):
        OakConfig(socket="CAM_Z")


def write_episode(path, n: int = 6):
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    cam = CameraInfo(name="ego", width=W, height=H, K=K, dist=np.zeros(5))
    rng = np.random.default_rng(1)
    with EpisodeWriter(path, cam, RobotInfo(), 10.0, depth_scale=1e-3, extra_frame_columns=("seq",)) as writer:
        for k in range(4 * n):
            writer.add_joint_sample(0.025 * k, rng.uniform(-1, 1, 6), 0.01 * (k % 7))
        for i in range(n):
            writer.add_frame(0.1 * i, rng.uniform(-1, 1, 6), 0.02, rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
                             depth=np.full((H, W), 0.5 + 0.1 * i), extra={"seq": float(100 + i + (i >= 3))})
    return path


def test_episode_camera_and_arm(tmp_path):
    path = write_episode(tmp_path / "ep")
    cam = EpisodeCamera(path)
    assert isinstance(cam, Camera) and cam.chroma_subsampling is None  # PNG files of unknown origin
    frames = list(iter(cam.read, None))
    assert [f.seq for f in frames] == [100, 101, 102, 104, 105, 106] and cam.tracker.dropped == 1
    assert [f.t for f in frames] == pytest.approx([0.1 * i for i in range(6)])
    assert frames[3].dropped == 1 and frames[2].depth[0, 0] == pytest.approx(0.7)
    np.testing.assert_array_equal(cam.K, [[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])

    arm = EpisodeArm(path)
    assert isinstance(arm, Arm) and len(arm) == 24
    states = [arm.wait_for_joint_state(k - 1) for k in range(24)]
    assert [s.seq for s in states] == list(range(24)) and states[5].t == pytest.approx(0.125)
    np.testing.assert_array_equal(states[7].q, arm.q[7])
    assert arm.health().state == "ended"
    with pytest.raises(TimeoutError, match="24 joint samples"):
        arm.wait_for_joint_state(23)


def test_episode_replays_in_real_time(tmp_path):
    path = write_episode(tmp_path / "ep", n=4)
    t0 = time.monotonic()
    with EpisodeCamera(path, realtime=True) as cam:
        frames = list(iter(cam.read, None))
    assert len(frames) == 4 and 0.28 < time.monotonic() - t0 < 2.0  # 0.3 s of frames
    arm = EpisodeArm(path, realtime=True)
    t0 = time.monotonic()
    state = arm.wait_for_joint_state(7)  # sample 8, due 0.2 s in
    assert state.seq >= 8 and 0.18 < time.monotonic() - t0 < 1.5


def test_sequence_tracker():
    tracker = SequenceTracker()
    assert [tracker.update(s) for s in (3, 4, 7, 8, 2, 3)] == [0, 0, 2, 0, 0, 0]
    assert tracker.dropped == 2 and tracker.frames == 6
