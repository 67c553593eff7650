"""Interpolation: joints and poses at arbitrary times, no extrapolation, gaps reported."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from manisplat.geometry import (
    axis_rotation,
    bracket_times,
    interpolate_joints,
    interpolate_poses,
    make_transform,
    rotation_angle,
    rotation_error,
    slerp,
    so3_exp,
)

f64 = torch.float64


def test_joints_exact_at_samples_and_linear_between():
    t = torch.tensor([0.0, 0.005, 0.010, 0.020], dtype=f64)
    q = torch.tensor([[0.0, 1.0], [0.1, 1.5], [0.3, 2.0], [0.3, 1.0]], dtype=f64)
    out = interpolate_joints(t, q, torch.tensor([0.0, 0.0025, 0.010, 0.015, 0.020], dtype=f64))
    assert torch.equal(out.values[[0, 2, 4]], q[[0, 2, 3]])
    assert torch.allclose(out.values[1], torch.tensor([0.05, 1.25], dtype=f64))
    assert torch.allclose(out.values[3], torch.tensor([0.3, 1.5], dtype=f64))
    assert torch.allclose(out.gap, torch.tensor([0.005, 0.005, 0.010, 0.010, 0.010], dtype=f64))


@given(st.lists(st.floats(0.0, 1.0), min_size=1, max_size=30))
def test_queries_inside_range_never_leave_the_sample_hull(fractions):
    t = torch.cumsum(torch.rand(50, dtype=f64, generator=torch.Generator().manual_seed(0)) + 1e-3, 0)
    q = torch.randn(50, 6, dtype=f64, generator=torch.Generator().manual_seed(1))
    query = t[0] + torch.tensor(fractions, dtype=f64) * (t[-1] - t[0])
    out = interpolate_joints(t, q, query)
    assert torch.isfinite(out.values).all()
    assert bool((out.values >= q.min(0).values - 1e-12).all() and (out.values <= q.max(0).values + 1e-12).all())


@pytest.mark.parametrize(
    "times, query, message",
    [
        ([0.0, 1.0], [1.5], "refusing to extrapolate"),
        ([0.0, 1.0], [-1e-9], "refusing to extrapolate"),
        ([0.0, 1.0, 1.0], [0.5], "strictly increasing"),
        ([0.0, math.nan], [0.5], "NaN"),
        ([], [0.5], "non-empty"),
    ],
)
def test_bad_times_raise(times, query, message):
    with pytest.raises(ValueError, match=message):
        bracket_times(torch.tensor(times, dtype=f64), torch.tensor(query, dtype=f64))


def test_joint_values_checked():
    t = torch.tensor([0.0, 1.0], dtype=f64)
    with pytest.raises(ValueError, match="NaN"):
        interpolate_joints(t, torch.tensor([[0.0], [math.nan]], dtype=f64), torch.tensor([0.5], dtype=f64))
    with pytest.raises(ValueError, match=r"\[T, D\]"):
        interpolate_joints(t, torch.zeros(3, 2, dtype=f64), torch.tensor([0.5], dtype=f64))


def test_single_sample_answers_only_its_own_time():
    out = interpolate_joints([0.5], [[1.0, 2.0]], [0.5])
    assert torch.equal(out.values, torch.tensor([[1.0, 2.0]], dtype=f64)) and float(out.gap[0]) == 0.0


def test_slerp_follows_the_geodesic_and_is_stable_for_equal_rotations():
    R0 = so3_exp(torch.tensor([0.1, 0.2, 0.3], dtype=f64))
    R1 = R0 @ axis_rotation("z", 1.2)
    for s in (0.0, 0.25, 0.5, 1.0):
        assert torch.allclose(slerp(R0, R1, s), R0 @ axis_rotation("z", 1.2 * s), atol=1e-15)
    same = slerp(R0, R0 @ axis_rotation("x", 1e-14), 0.5)
    assert torch.isfinite(same).all() and float(rotation_error(same, R0)) < 1e-14
    half_turn = slerp(R0, R0 @ axis_rotation("y", math.pi), 0.5)
    assert abs(float(rotation_angle(R0.T @ half_turn)) - math.pi / 2) < 1e-12


def test_pose_interpolation_is_slerp_plus_lerp():
    t = torch.tensor([0.0, 1.0, 3.0], dtype=f64)
    R = torch.stack([axis_rotation("z", a) for a in (0.0, 0.5, 1.5)])
    p = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [1.0, 2.0, 0]], dtype=f64)
    poses = make_transform(R, p)
    out = interpolate_poses(t, poses, torch.tensor([0.0, 0.5, 2.0, 3.0], dtype=f64))
    assert torch.equal(out[[0, 3]], poses[[0, 2]])
    assert torch.allclose(out[1], make_transform(axis_rotation("z", 0.25), torch.tensor([0.5, 0.0, 0.0], dtype=f64)), atol=1e-15)
    assert torch.allclose(out[2], make_transform(axis_rotation("z", 1.0), torch.tensor([1.0, 1.0, 0.0], dtype=f64)), atol=1e-15)
    with pytest.raises(ValueError, match="extrapolate"):
        interpolate_poses(t, poses, torch.tensor([3.5], dtype=f64))
