"""The camera check benchmark's workspace error: what an extrinsic error moves the workspace by."""

import numpy as np
from scipy.spatial.transform import Rotation

from benchmarks._viewpoints import TARGET
from benchmarks.bench_camera_check import workspace_error_mm


def _camera_at(position) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [2.0, 0.3, -0.7]).as_matrix()
    T[:3, 3] = position
    return T


def test_the_same_pose_moves_nothing():
    T = _camera_at([0.75, -0.85, 0.8])
    assert np.allclose(workspace_error_mm(T, T), 0.0, atol=1e-9)


def test_a_shifted_camera_shifts_every_point_by_as_much():
    T = _camera_at([0.75, -0.85, 0.8])
    shifted = T.copy()
    shifted[:3, 3] += [0.0006, -0.0008, 0.0]  # 1 mm
    rms, worst = workspace_error_mm(T, shifted)
    assert np.isclose(rms, 1.0) and np.isclose(worst, 1.0)


def test_turning_about_the_workspace_moves_the_centre_more_than_the_workspace():
    """0.05 deg about the workspace's middle: the centre of a camera 1.2 m away moves about 1 mm,
    the workspace's points (within about 0.3 m of that middle) a fraction of it."""
    T = _camera_at([0.75, -0.85, 0.8])
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec(np.radians(0.05) * np.array([0.0, 0.6, 0.8])).as_matrix()
    pivot = np.eye(4)
    pivot[:3, 3] = TARGET
    turned = pivot @ turn @ np.linalg.inv(pivot) @ T
    centre_mm = 1e3 * np.linalg.norm(turned[:3, 3] - T[:3, 3])
    rms, worst = workspace_error_mm(T, turned)
    assert centre_mm > 0.9
    assert worst < 0.4 * centre_mm and rms < 0.25 * centre_mm
