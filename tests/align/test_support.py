"""The support under a footprint, read from depth: a camera above a table with a 5 mm mat."""

from __future__ import annotations

import numpy as np

from manisplat.align.support import footprint, support_height

W, H = 160, 120
K = np.array([[150.0, 0.0, W / 2 - 0.5], [0.0, 150.0, H / 2 - 0.5], [0.0, 0.0, 1.0]])
MAT_CENTRE, MAT_RADIUS, MAT_TOP = np.array([0.32, 0.06]), 0.06, 0.005


def camera_pose() -> np.ndarray:
    """T_base_cam: 0.6 m above (0.3, 0.0), looking straight down."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [0.3, 0.0, 0.6]
    return T


def table_depth(T_base_cam: np.ndarray) -> np.ndarray:
    """[H, W] z-depth (m) of the table (height 0) with the mat (5 mm) on it."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ T_base_cam[:3, :3].T
    centre = T_base_cam[:3, 3]
    z_mat = (MAT_TOP - centre[2]) / rays[..., 2]
    on_mat = np.linalg.norm(centre[:2] + z_mat[..., None] * rays[..., :2] - MAT_CENTRE, axis=-1) < MAT_RADIUS
    return np.where(on_mat, z_mat, (0.0 - centre[2]) / rays[..., 2]).astype(np.float32)


def box_at(x: float, y: float, yaw_deg: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    """Surface points [M, 3] of a 4 x 4 x 5 cm box (object frame) and its pose standing at (x, y)."""
    axes = [np.linspace(-s / 2, s / 2, 9) for s in (0.04, 0.04, 0.05)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    points = grid[(np.abs(np.abs(grid) - [0.02, 0.02, 0.025]) < 1e-9).any(-1)]
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = [x, y, 0.025]
    return points, T


def test_the_footprint_is_the_hull_seen_from_above_and_its_lowest_height():
    points, T = box_at(0.3, -0.1)
    hull, low = footprint(points, T)
    assert abs(low) < 1e-12
    assert len(hull) == 4 and np.allclose(np.sort(np.linalg.norm(hull - [0.3, -0.1], axis=1)), np.hypot(0.02, 0.02))


def test_the_support_under_a_footprint_is_the_mat_or_the_table():
    T_base_cam = camera_pose()
    depth = table_depth(T_base_cam)
    free = np.ones((H, W), bool)
    on_mat = footprint(*box_at(*MAT_CENTRE))
    on_table = footprint(*box_at(0.3, -0.12))
    assert abs(support_height(*on_mat, [(depth, free)] * 3, K, T_base_cam) - MAT_TOP) < 2e-4
    assert abs(support_height(*on_table, [(depth, free)], K, T_base_cam)) < 2e-4


def test_a_spot_covered_in_every_frame_or_behind_the_camera_has_no_support():
    T_base_cam = camera_pose()
    depth = table_depth(T_base_cam)
    covered = np.zeros((H, W), bool)  # the robot or an object over every pixel
    hull, low = footprint(*box_at(*MAT_CENTRE))
    assert support_height(hull, low, [(depth, covered)] * 3, K, T_base_cam) is None
    assert support_height(hull, 0.7, [(depth, np.ones((H, W), bool))], K, T_base_cam) is None  # above the camera


def test_the_support_from_stereo_depth_in_disparity_steps_is_not_stuck_to_a_step():
    """Stereo depth from disparity with 0.08 px of noise in steps of 1/8 px (4 mm at this range):
    a median of the heights sticks to one step; the support is found within 0.4 mm."""
    T_base_cam = camera_pose()
    exact = table_depth(T_base_cam).astype(np.float64)
    focal_baseline = K[0, 0] * 0.075
    rng = np.random.default_rng(3)
    views = []
    for _ in range(10):
        disparity = np.round((focal_baseline / exact + rng.normal(0.0, 0.08, exact.shape)) * 8) / 8
        views.append(((focal_baseline / disparity).astype(np.float32), np.ones((H, W), bool)))
    height = support_height(*footprint(*box_at(*MAT_CENTRE)), views, K, T_base_cam)
    assert abs(height - MAT_TOP) < 4e-4  # the median: 1.0 mm off
