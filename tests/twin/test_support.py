"""The support height map: measured from depth frames, robust to what moves through them, and
the step under an object's footprint that decides whether it can be set down there."""

from __future__ import annotations

import numpy as np
import pytest

from manisplat.twin.support import MAX_STEP, SupportMap, support_map

W, H = 160, 120
K = np.array([[150.0, 0, (W - 1) / 2], [0, 150.0, (H - 1) / 2], [0, 0, 1]])
PLATE = (0.30, 0.05, 0.06, 0.004)  # centre x, y (m), radius (m), height (m)


def camera_above(x=0.3, y=0.0, z=0.6) -> np.ndarray:
    """T_base_cam [4, 4] of a camera looking straight down (OpenCV axes: z down, x along base x)."""
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]
    T[:3, 3] = [x, y, z]
    return T


def table_with_plate(T_base_cam: np.ndarray) -> np.ndarray:
    """Exact z-depth [H, W] (m) of a table at z = 0 carrying a raised disc (``PLATE``)."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1)
    R, c = T_base_cam[:3, :3], T_base_cam[:3, 3]
    d_base = rays @ R.T
    depth = np.zeros((H, W))
    for height, inside in ((PLATE[3], True), (0.0, False)):
        z = (height - c[2]) / d_base[..., 2]
        hit = c[:2] + z[..., None] * d_base[..., :2]
        on_plate = np.hypot(hit[..., 0] - PLATE[0], hit[..., 1] - PLATE[1]) <= PLATE[2]
        take = (on_plate if inside else ~on_plate) & (depth == 0)
        depth[take] = z[take]
    return depth


def square(centre_xy, half=0.02, n=9) -> np.ndarray:
    """Footprint points [n*n, 2] of a square object."""
    a = np.linspace(-half, half, n)
    return np.stack(np.meshgrid(a, a), -1).reshape(-1, 2) + np.asarray(centre_xy)


@pytest.fixture(scope="module")
def measured() -> SupportMap:
    T = camera_above()
    depth = table_with_plate(T)
    frames = np.repeat(depth[None], 5, axis=0)
    background = np.ones_like(frames, dtype=bool)
    rng = np.random.default_rng(0)
    for k in range(5):  # something passes through each frame (masked out), and a bogus reading
        y0, x0 = rng.integers(0, H - 30), rng.integers(0, W - 30)
        background[k, y0:y0 + 30, x0:x0 + 30] = False
        frames[k, y0:y0 + 30, x0:x0 + 30] = 0.3
    frames[0, 10:20, 10:20] = 0.1  # a wrong reading in one frame only: the median ignores it
    return support_map(frames, background, K, T)


def test_heights_are_measured_where_seen_and_unknown_elsewhere(measured):
    assert abs(measured.height_at(np.array([[PLATE[0], PLATE[1]]]))[0] - PLATE[3]) < 1e-6
    assert abs(measured.height_at(np.array([[PLATE[0], -0.15]]))[0]) < 1e-6
    assert np.isnan(measured.height_at(np.array([[2.0, 2.0]]))[0])  # outside the view
    assert np.nanmax(measured.heights) < PLATE[3] + 1e-6  # the wrong reading did not survive


def test_an_object_is_supported_only_with_its_centre_well_inside_the_surface(measured):
    """A 4 cm square footprint: on the plate or the table, or overhanging the rim with its centre
    1.7 cm inside, it rests; with its centre 1 cm inside the rim, on the rim, or on the table with a
    corner on the plate, it rests on an edge (the plate's 4 mm height)."""
    cx, cy, radius, height = PLATE

    def drop(inside: float) -> float:  # the footprint's centre ``inside`` m within the rim (negative: outside)
        return measured.edge_drop(square((cx, cy - radius + inside)))

    assert drop(radius) < 1e-6  # the plate's centre
    assert measured.edge_drop(square((cx, cy - 0.15))) < 1e-6  # the table, far from the plate
    assert drop(0.017) < 1e-6  # it overhangs the rim by 3 mm, its centre 1.7 cm inside: it rests
    for inside in (0.01, 0.0, -0.015):
        assert abs(drop(inside) - height) < 1e-6 and drop(inside) > MAX_STEP, inside
    assert measured.edge_drop(square((3.0, 3.0))) is None  # never seen: no judgement


def test_no_background_gives_no_map():
    T = camera_above()
    depth = table_with_plate(T)[None]
    assert support_map(depth, np.zeros_like(depth, dtype=bool), K, T) is None


def test_stereo_noise_that_every_frame_shares_is_not_taken_for_edges():
    """Depth scattered by 2 mm per pixel, the same in every frame (a stereo camera's): open table
    and plate are judged flat, an object on the plate's rim still on an edge. Unsmoothed, most spots of the open
    table would measure as an edge (the cells' 5th to 95th percentile)."""
    T = camera_above()
    noisy = table_with_plate(T) + np.random.default_rng(1).normal(0, 0.002, (H, W))
    frames = np.repeat(noisy[None], 5, axis=0)
    noisy_map = support_map(frames, np.ones_like(frames, dtype=bool), K, T)
    cx, cy, radius, height = PLATE
    table = [noisy_map.edge_drop(square((x, y))) for x in (0.20, 0.25, 0.30, 0.35, 0.40) for y in (-0.10, -0.05)]
    assert max(table) < MAX_STEP, table
    assert noisy_map.edge_drop(square((cx, cy))) < MAX_STEP
    for inside in (0.01, 0.0):  # a corner just on the plate (centre 1.5 cm outside) may be missed now
        assert noisy_map.edge_drop(square((cx, cy - radius + inside))) > MAX_STEP, inside


def test_depth_in_steps_sets_the_smallest_edge_and_continuous_depth_does_not():
    """A stereo camera's depth in 1/8 pixel disparity steps (4 mm at 0.6 m here): a flat
    table then measures as terraces one step apart, which are not taken for edges; the same scene
    in exact depth keeps the 2.5 mm threshold and finds the plate's rim. (The camera leans 10
    deg: a table exactly square to it would take one depth value, the plate another, and nothing
    would tell those two from two steps of the depth.)"""
    T = camera_above()
    lean = np.eye(4)
    lean[1:3, 1:3] = [[np.cos(0.17), -np.sin(0.17)], [np.sin(0.17), np.cos(0.17)]]
    T = T @ lean
    exact = table_with_plate(T)
    f_b = 150.0 * 0.075  # focal length (px) x baseline (m): steps of z^2 / (f b) / 8
    stepped = f_b / (np.round(f_b / exact * 8) / 8)
    frames = np.repeat(stepped[None], 3, axis=0)
    stepped_map = support_map(frames, np.ones_like(frames, dtype=bool), K, T)
    expected = 0.6 ** 2 / f_b / 8
    assert stepped_map.resolution == pytest.approx(expected, rel=0.15)
    assert stepped_map.smallest_edge() == pytest.approx(1.5 * stepped_map.resolution)
    table = [stepped_map.edge_drop(square((x, y))) for x in (0.20, 0.30, 0.40) for y in (-0.12, -0.08)]
    assert max(table) < stepped_map.smallest_edge(), table
    exact_map = support_map(np.repeat(exact[None], 3, axis=0), np.ones((3, H, W), dtype=bool), K, T)
    assert exact_map.smallest_edge() == MAX_STEP
    cx, cy, radius, _ = PLATE
    assert exact_map.edge_drop(square((cx, cy - radius))) > exact_map.smallest_edge()
