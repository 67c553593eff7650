"""SO(3): exp/log, quaternions, geodesic angle, RPY, orthonormalisation, float32 bounds."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from manisplat.geometry import (
    GeometryError,
    axis_rotation,
    hat,
    is_rotation,
    matrix_to_quat,
    matrix_to_rpy,
    orthonormalize,
    quat_canonical,
    quat_conjugate,
    quat_left_multiplier,
    quat_multiply,
    quat_to_matrix,
    random_rotations,
    rotation_angle,
    rotation_error,
    rpy_to_matrix,
    so3_exp,
    so3_log,
    vee,
)
from tests.geometry.strategies import SPECIAL_ANGLES, rotation_vectors, unit_axes

EPS64 = torch.finfo(torch.float64).eps
EPS32 = torch.finfo(torch.float32).eps


def rodrigues_oracle(w: torch.Tensor) -> torch.Tensor:
    """Exact rotation of an axis-angle vector via the matrix exponential of its skew matrix."""
    return torch.linalg.matrix_exp(hat(w))


@given(rotation_vectors())
def test_exp_matches_matrix_exponential(w):
    R = so3_exp(w)
    assert torch.allclose(R, rodrigues_oracle(w), atol=10 * EPS64, rtol=0)
    assert bool(is_rotation(R, atol=1e-14))


@given(rotation_vectors())
def test_log_inverts_exp_at_every_angle(w):
    w_back = so3_log(so3_exp(w))
    angle = float(w.norm())
    assert torch.isfinite(w_back).all()
    assert abs(float(w_back.norm()) - angle) <= 1e-9 * max(angle, 1e-300) + 4 * EPS64
    if angle < math.pi - 1e-6:
        assert torch.allclose(w_back, w, atol=4 * EPS64 + 1e-12 * angle, rtol=0)
    else:  # at (or within rounding of) pi the axis sign is arbitrary; the rotation is not
        assert torch.allclose(so3_exp(w_back), so3_exp(w), atol=1e-14, rtol=0)


@pytest.mark.parametrize("angle", SPECIAL_ANGLES)
def test_log_is_exact_at_special_angles_about_every_axis(angle):
    axes = torch.randn(2000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    axes = axes / axes.norm(dim=-1, keepdim=True)
    R = rodrigues_oracle(axes * angle)
    w = so3_log(R)
    assert torch.isfinite(w).all()
    assert torch.allclose(rodrigues_oracle(w), R, atol=1e-14, rtol=0)
    assert (w.norm(dim=-1) - angle).abs().max() <= 1e-14 + 1e-12 * angle


@pytest.mark.parametrize("angle", [0.0, 1e-12, math.pi - 1e-9, math.pi])
def test_exp_log_gradients_are_finite_at_zero_and_pi(angle):
    w = (torch.tensor([0.3, -0.5, 0.81], dtype=torch.float64) / 1.0)
    w = (w / w.norm() * angle).requires_grad_(True)
    so3_exp(w)[1, 0].backward()
    assert torch.isfinite(w.grad).all()
    R = rodrigues_oracle(w.detach()).requires_grad_(True)
    so3_log(R).sum().backward()
    assert torch.isfinite(R.grad).all()


def test_exp_gradient_at_zero_is_the_generator():
    w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    so3_exp(w)[1, 0].backward()  # R ~ I + hat(w): dR10/dw = (0, 0, 1)
    assert torch.allclose(w.grad, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def test_hat_vee_and_batch_shapes():
    w = torch.randn(4, 5, 3, dtype=torch.float64)
    v = torch.randn(4, 5, 3, dtype=torch.float64)
    assert torch.allclose((hat(w) @ v[..., None])[..., 0], torch.linalg.cross(w, v, dim=-1))
    assert torch.equal(vee(hat(w)), w)
    assert so3_exp(w).shape == (4, 5, 3, 3)
    assert so3_log(so3_exp(w)).shape == (4, 5, 3)
    assert matrix_to_quat(so3_exp(w)).shape == (4, 5, 4)


# ---------------------------------------------------------------- quaternions
@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: sum(x * x for x in q) > 1e-6))
def test_quaternion_sign_ambiguity(qlist):
    q = torch.tensor(qlist, dtype=torch.float64)
    R = quat_to_matrix(q)
    assert torch.allclose(quat_to_matrix(-q), R, atol=1e-15, rtol=0)
    assert torch.allclose(quat_to_matrix(3.7 * q), R, atol=1e-15, rtol=0)  # need not be unit
    back = matrix_to_quat(R)
    assert float(back[0]) >= 0.0
    unit = q / q.norm()
    # Up to sign: where w is within rounding of 0 no rule can pick the sign continuously.
    assert min(float((back - unit).abs().max()), float((back + unit).abs().max())) <= 1e-12
    if abs(float(unit[0])) > 1e-9:
        assert torch.allclose(back, quat_canonical(unit), atol=1e-12, rtol=0)


def test_canonical_sign_when_w_is_zero():
    q = torch.tensor([[0.0, -0.6, 0.8, 0.0], [0.0, 0.0, -1.0, 0.0], [-0.0, 0.0, 0.0, -1.0]], dtype=torch.float64)
    c = quat_canonical(q)
    assert torch.equal(c, torch.tensor([[0.0, 0.6, -0.8, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]], dtype=torch.float64))
    assert torch.allclose(matrix_to_quat(quat_to_matrix(q)), c, atol=1e-15)


def test_zero_quaternion_is_an_error_not_identity():
    with pytest.raises(GeometryError, match="zero norm"):
        quat_to_matrix(torch.tensor([[1.0, 0, 0, 0], [0.0, 0, 0, 0]], dtype=torch.float64))


def test_quaternion_product_composes_rotations():
    R = random_rotations(100, generator=torch.Generator().manual_seed(0))
    qa, qb = matrix_to_quat(R[:50]), matrix_to_quat(R[50:])
    assert torch.allclose(quat_to_matrix(quat_multiply(qa, qb)), R[:50] @ R[50:], atol=1e-14)
    assert torch.allclose(quat_to_matrix(quat_conjugate(qa)), R[:50].transpose(-1, -2), atol=1e-14)


def test_one_quaternion_turns_many_as_the_product_does():
    """``b @ quat_left_multiplier(q)`` is ``q * b`` for every row of ``b``, for one ``q`` and for a
    batch of them (float64 to the last digits, float32 as its own product)."""
    R = random_rotations(41, generator=torch.Generator().manual_seed(1))
    q, b = matrix_to_quat(R[0]), matrix_to_quat(R[1:])
    assert torch.allclose(b @ quat_left_multiplier(q), quat_multiply(q.expand_as(b), b), atol=1e-15)
    qs = matrix_to_quat(R[1:5])
    assert torch.allclose(b[:4, None, :] @ quat_left_multiplier(qs), quat_multiply(qs, b[:4])[:, None, :], atol=1e-15)
    q32, b32 = q.float(), b.float()
    assert torch.allclose(b32 @ quat_left_multiplier(q32), quat_multiply(q32.expand_as(b32), b32), atol=1e-6)


# ---------------------------------------------------------------- angles
@pytest.mark.parametrize("angle", SPECIAL_ANGLES)
def test_geodesic_angle_has_full_relative_precision(angle):
    R = axis_rotation("x", angle)
    got = float(rotation_angle(R))
    assert abs(got - angle) <= 2 * EPS64 * angle


@given(rotation_vectors(), rotation_vectors())
def test_rotation_error_is_symmetric_and_matches_log(w1, w2):
    R1, R2 = so3_exp(w1), so3_exp(w2)
    e12, e21 = rotation_error(R1, R2), rotation_error(R2, R1)
    assert abs(float(e12) - float(e21)) <= 1e-12
    assert abs(float(e12) - float(so3_log(R1.T @ R2).norm())) <= 1e-9
    assert 0.0 <= float(e12) <= math.pi


# ---------------------------------------------------------------- RPY
@given(
    st.floats(-math.pi, math.pi), st.floats(-math.pi / 2, math.pi / 2), st.floats(-math.pi, math.pi)
)
def test_rpy_round_trip(roll, pitch, yaw):
    rpy = torch.tensor([roll, pitch, yaw], dtype=torch.float64)
    R = rpy_to_matrix(rpy)
    assert torch.allclose(R, axis_rotation("z", yaw) @ axis_rotation("y", pitch) @ axis_rotation("x", roll))
    assert torch.allclose(rpy_to_matrix(matrix_to_rpy(R)), R, atol=1e-12, rtol=0)


@pytest.mark.parametrize("pitch", [math.pi / 2, -math.pi / 2])
def test_rpy_gimbal_lock_follows_piper_sdk(pitch):
    R = rpy_to_matrix(torch.tensor([0.4, pitch, -0.3], dtype=torch.float64))
    roll, p, yaw = matrix_to_rpy(R).tolist()
    assert yaw == 0.0 and abs(p - pitch) < 1e-7
    assert torch.allclose(rpy_to_matrix(torch.tensor([roll, p, yaw], dtype=torch.float64)), R, atol=1e-12)


# ---------------------------------------------------------------- orthonormalisation and drift
def test_orthonormalize_projects_onto_rotations():
    R = random_rotations(200, generator=torch.Generator().manual_seed(1))
    noisy = R + 1e-3 * torch.randn(R.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    fixed = orthonormalize(noisy)
    assert bool(is_rotation(fixed, atol=1e-14).all())
    assert float(rotation_error(fixed, R).max()) < 5e-3
    reflected = R.clone()
    reflected[:, :, 2] *= -1  # det = -1
    assert bool(is_rotation(orthonormalize(reflected), atol=1e-14).all())


@pytest.mark.slow
@pytest.mark.parametrize("dtype, bound", [(torch.float64, 1e-9), (torch.float32, 2e-4)])
def test_drift_after_a_million_compositions(dtype, bound):
    """1e6 products of one small rotation, re-orthonormalised every 1000 steps.

    The exact result is the rotation by n * (angle of the step actually used). Measured here:
    7e-11 rad in float64 and 2.5e-5 rad in float32 (a random walk of float32 rounding); the
    bounds leave about 10x margin.
    """
    axis = torch.tensor([0.48, -0.6, 0.64], dtype=torch.float64)
    step = so3_exp(axis / axis.norm() * 0.0123456789).to(dtype)
    step64 = step.double()
    step_angle = float(rotation_angle(orthonormalize(step64)))
    n = 1_000_000
    R = torch.eye(3, dtype=dtype)
    for i in range(1, n + 1):
        R = R @ step
        if i % 1000 == 0:
            R = orthonormalize(R)
    exact = so3_exp(so3_log(orthonormalize(step64)) / step_angle * math.fmod(n * step_angle, 2 * math.pi))
    assert bool(is_rotation(R.double(), atol=10 * float(torch.finfo(dtype).eps)))
    assert float(rotation_error(R.double(), exact)) <= bound


def test_float32_error_bounds_against_float64():
    """float32 exp/log/quaternion ops stay within a few float32 ulps of the float64 results."""
    w = torch.randn(5000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    w = w / w.norm(dim=-1, keepdim=True) * torch.rand(5000, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(5)) * math.pi
    R64 = so3_exp(w)
    R32 = so3_exp(w.float())
    assert float((R32.double() - R64).abs().max()) <= 8 * EPS32
    assert float(rotation_error(so3_exp(so3_log(R64.float())).double(), R64).max()) <= 16 * EPS32
    q32 = matrix_to_quat(R64.float())
    assert float((quat_to_matrix(q32).double() - R64).abs().max()) <= 8 * EPS32
    assert torch.isfinite(so3_log(R32)).all()


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_axis_rotation_rejects_unknown_axis_and_matches_exp(axis):
    e = torch.zeros(3, dtype=torch.float64)
    e["xyz".index(axis)] = 0.7
    assert torch.allclose(axis_rotation(axis, 0.7), so3_exp(e), atol=1e-15)
    with pytest.raises(ValueError, match="axis"):
        axis_rotation("w", 0.1)


@given(unit_axes())
def test_is_rotation_rejects_non_rotations(axis):
    R = so3_exp(axis * 0.3)
    assert bool(is_rotation(R))
    assert not bool(is_rotation(2 * R))
    assert not bool(is_rotation(-R))  # det -1
    bad = R.clone()
    bad[0, 0] = float("nan")
    assert not bool(is_rotation(bad))
