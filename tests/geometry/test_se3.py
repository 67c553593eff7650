"""SE(3): build/invert/compose/apply, exp/log against the matrix exponential, pose errors."""

from __future__ import annotations

import math

import torch
from hypothesis import given
from hypothesis import strategies as st

from manisplat.geometry import (
    hat,
    invert_transform,
    is_transform,
    make_transform,
    pose_error,
    se3_exp,
    se3_log,
    so3_exp,
    transform_points,
    translation_error,
)
from tests.geometry.strategies import rotation_vectors, transforms


def twist_matrix(xi: torch.Tensor) -> torch.Tensor:
    M = torch.zeros(4, 4, dtype=xi.dtype)
    M[:3, :3] = hat(xi[3:])
    M[:3, 3] = xi[:3]
    return M


@given(rotation_vectors(), st.lists(st.floats(-1, 1), min_size=3, max_size=3))
def test_se3_exp_matches_matrix_exponential_and_log_inverts(w, v):
    xi = torch.cat([torch.tensor(v, dtype=torch.float64), w])
    T = se3_exp(xi)
    assert torch.allclose(T, torch.linalg.matrix_exp(twist_matrix(xi)), atol=1e-13, rtol=0)
    back = se3_exp(se3_log(T))
    assert torch.isfinite(back).all()
    assert torch.allclose(back, T, atol=1e-12, rtol=0)


@given(transforms(), transforms())
def test_inverse_and_composition(T_ab, T_bc):
    eye = torch.eye(4, dtype=torch.float64)
    assert torch.allclose(invert_transform(T_ab) @ T_ab, eye, atol=1e-14)
    assert torch.allclose(invert_transform(T_ab @ T_bc), invert_transform(T_bc) @ invert_transform(T_ab), atol=1e-13)
    p = torch.randn(7, 3, dtype=torch.float64)
    assert torch.allclose(transform_points(T_ab @ T_bc, p), transform_points(T_ab, transform_points(T_bc, p)), atol=1e-13)


def test_shapes_broadcast_and_float32():
    R = so3_exp(torch.randn(2, 5, 3, dtype=torch.float64))
    T = make_transform(R, torch.zeros(3, dtype=torch.float64))
    assert T.shape == (2, 5, 4, 4) and bool(is_transform(T).all())
    pts = torch.randn(2, 5, 11, 3, dtype=torch.float64)
    assert transform_points(T, pts).shape == (2, 5, 11, 3)
    T32 = T.float()
    assert se3_log(T32).dtype == torch.float32
    assert torch.allclose(se3_exp(se3_log(T32)), T32, atol=2e-6)


def test_pose_error_reports_distance_and_angle():
    T_a = make_transform(so3_exp(torch.tensor([0.0, 0.0, 0.1], dtype=torch.float64)), torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    T_b = make_transform(so3_exp(torch.tensor([0.0, 0.0, 0.1 + 1e-9], dtype=torch.float64)), torch.tensor([1.0, 2.0, 3.003], dtype=torch.float64))
    dt, dr = pose_error(T_a, T_b)
    assert abs(float(dt) - 0.003) < 1e-12
    assert abs(float(dr) - 1e-9) < 1e-15
    assert float(translation_error(T_a, T_a)) == 0.0


def test_is_transform_rejects_bad_matrices():
    T = make_transform(so3_exp(torch.tensor([0.2, 0.1, -0.3], dtype=torch.float64)), torch.ones(3, dtype=torch.float64))
    assert bool(is_transform(T))
    bad_row = T.clone()
    bad_row[3, 0] = 0.1
    scaled = T.clone()
    scaled[:3, :3] *= 1.01
    nan = T.clone()
    nan[0, 3] = math.nan
    for bad in (bad_row, scaled, nan):
        assert not bool(is_transform(bad))


def test_exp_log_need_no_grad_for_plain_inputs_and_pass_gradcheck():
    xi = torch.tensor([0.1, -0.2, 0.3, 0.4, 0.5, -0.6], dtype=torch.float64)
    assert not se3_exp(xi).requires_grad and not se3_log(se3_exp(xi)).requires_grad
    se3_exp(xi).numpy()  # usable as plain data
    assert torch.autograd.gradcheck(se3_exp, (xi.clone().requires_grad_(True),))
    T = se3_exp(xi).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda M: se3_log(M), (T,))
