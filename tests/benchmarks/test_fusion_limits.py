"""benchmarks.bench_fusion_limits: the box region's error split into its outline and its inside,
the image shift that explains a misplaced render, and what a shift alone costs."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.bench_fusion_limits import (SHIFTS, face_kinds, outline_split, phases_of, psnr_of, shift_errors,
                                         shift_price, shifted)


def _textured_square(offset: float = 0.0, size: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A smooth textured square (image [size, size, 3] float32 on a grey ground) drawn 4x finer and
    averaged down, moved right by ``offset`` px, and its region [size, size] bool (unmoved)."""
    fine = 4 * size
    y, x = np.mgrid[0:fine, 0:fine] / 4.0
    inside = (x - offset >= 12) & (x - offset < 28) & (y >= 12) & (y < 28)
    texture = 0.7 + 0.1 * np.sin(0.3 * (x - offset)) * np.cos(0.2 * y)
    image = np.where(inside, texture, 0.3).astype(np.float32)
    image = image.reshape(size, 4, size, 4).mean((1, 3))
    region = np.zeros((size, size), bool)
    region[12:28, 12:28] = True
    return np.repeat(image[..., None], 3, axis=-1), region


def test_a_misplaced_render_errs_on_the_outline_and_the_best_shift_finds_it():
    target, region = _textured_square()
    pred, _ = _textured_square(offset=0.5)
    parts = outline_split(pred, target, region)
    assert parts["n"] == 256 and parts["outline_n"] + parts["inside_n"] == 256 and parts["inside_n"] == 144
    outline = parts["outline_sum"] / parts["outline_n"]
    inside = parts["inside_sum"] / parts["inside_n"]
    assert outline > 3 * inside  # the square's edges carry the misplacement
    errors = shift_errors(pred, target, region)
    a, b = np.unravel_index(errors.argmin(), errors.shape)
    assert (SHIFTS[a], SHIFTS[b]) == (-0.5, 0.0)  # moved back by what it was moved
    centre = len(SHIFTS) // 2
    assert psnr_of(errors[a, b]) > psnr_of(errors[centre, centre]) + 3


def test_the_price_of_a_shift_grows_with_the_shift_and_is_nothing_without_one():
    target, region = _textured_square()
    assert shift_price(target, region, 0.0) == pytest.approx(0.0, abs=1e-12)
    assert 0 < shift_price(target, region, 0.25) < shift_price(target, region, 0.5)
    np.testing.assert_allclose(shifted(target, 0.0, 0.0), target)


def _camera_looking(from_: np.ndarray, at: np.ndarray) -> np.ndarray:
    """T_base_cam [4, 4] (OpenCV axes: z forward, y down) of a camera at ``from_`` looking at ``at``."""
    z = (at - from_) / np.linalg.norm(at - from_)
    x = np.cross(z, [0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T[:3, 3] = from_
    return T


def test_each_pixel_is_given_the_face_its_ray_hits_by_where_that_face_points():
    K = np.array([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]])
    half = np.array([0.02, 0.02, 0.025])
    region = np.zeros((64, 64), bool)
    region[30:35, 30:35] = True  # the image's centre, on the box from every camera below
    standing = np.eye(4)
    above = _camera_looking(np.array([0.0, 0.0, 0.5]), np.zeros(3))
    beside = _camera_looking(np.array([0.5, 0.0, 0.0]), np.zeros(3))
    below = _camera_looking(np.array([0.0, 0.0, -0.5]), np.zeros(3))
    assert (face_kinds(K, above, standing, half, region) == 0).all()
    assert (face_kinds(K, beside, standing, half, region) == 1).all()
    assert (face_kinds(K, below, standing, half, region) == 2).all()
    lying = np.eye(4)
    lying[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]  # turned 90 deg about x: its +y face points up
    assert (face_kinds(K, above, lying, half, region) == 0).all()
    assert (face_kinds(K, beside, lying, half, region) == 1).all()
    away = np.eye(4)
    away[:3, 3] = [0.3, 0.3, 0.0]  # nowhere near the rays
    assert (face_kinds(K, above, away, half, region) == -1).all()
    looking_up = _camera_looking(np.array([0.0, 0.0, 0.5]), np.array([0.0, 0.0, 1.0]))
    assert (face_kinds(K, looking_up, standing, half, region) == -1).all()  # the box behind the camera
    corner = np.zeros((64, 64), bool)
    corner[0, 0] = True  # 0.32 rad off the axis: misses a box 4 cm wide at 0.5 m
    assert face_kinds(K, above, standing, half, corner).tolist() == [-1]


def test_the_phases_follow_where_the_drawn_object_is():
    poses = np.repeat(np.eye(4)[None], 7, axis=0)
    poses[3:, 0, 3] = [0.05, 0.10, 0.15, 0.15]  # lifted away, carried, placed
    poses[3, 2, 3] = 0.03
    assert phases_of(poses) == ["start"] * 3 + ["carried"] * 2 + ["placed"] * 2
