"""The gripper's recorded effort on its way from frames.csv to the releases the pseudo ground truth uses."""

from __future__ import annotations

import numpy as np

from manisplat.episode import CameraInfo, EpisodeWriter, RobotInfo
from manisplat.reconstruct.data import load_episode_data, retime
from manisplat.reconstruct.masks import object_carrier

FPS, T = 10.0, 12
K = np.array([[30.0, 0.0, 15.5], [0.0, 30.0, 11.5], [0.0, 0.0, 1.0]])


def write(path, effort: np.ndarray | None) -> None:
    """A 32x24 one-arm episode whose gripper closes at frame 3 and opens from frame 8 (6 mm a frame)."""
    width = np.array([0.07, 0.07, 0.07, 0.05, 0.04, 0.04, 0.04, 0.04, 0.04, 0.046, 0.052, 0.058])
    columns = ("gripper_effort",) if effort is not None else ()
    camera = CameraInfo(name="cam", width=32, height=24, K=K, mount="base", T_mount_cam=np.eye(4))
    with EpisodeWriter(path, camera, RobotInfo(), FPS, extra_frame_columns=columns) as writer:
        for i in range(T):
            writer.add_frame(i / FPS, np.zeros(6), width[i], np.zeros((24, 32, 3), np.uint8),
                             extra=None if effort is None else {"gripper_effort": float(effort[i])})


def test_the_recorded_effort_dates_the_release_and_follows_a_retiming(tmp_path):
    effort = np.array([0.0, 0.0, 0.0, -0.5, -1.0, -1.0, -1.0, -1.0, -0.1, 0.0, 0.0, 0.0])
    write(tmp_path / "ep", effort)
    data = load_episode_data(tmp_path / "ep", load_meshes=False)
    np.testing.assert_array_equal(data.arm_gripper_effort("arm"), effort)
    carrier = object_carrier(data, np.zeros(3))
    np.testing.assert_array_equal(carrier.effort, effort)
    (event,) = carrier.events()
    assert event.release == 8, "the pads stopped squeezing at frame 8; the opening shows it at 9"
    retime(data, 0.05)  # half a frame later: each frame's effort is read between its own and the next
    np.testing.assert_allclose(data.arm_gripper_effort("arm")[:-1], (effort[:-1] + effort[1:]) / 2)

    write(tmp_path / "without", None)
    data = load_episode_data(tmp_path / "without", load_meshes=False)
    assert data.arm_gripper_effort("arm") is None and object_carrier(data, np.zeros(3)).events()[0].release == 9
