"""Rotations: SO(3) exp/log, quaternions (w, x, y, z), geodesic angles, Euler RPY.

All functions are batched over leading dimensions (``...``) and keep the input dtype
(float64 is the project default; float32 is allowed). Exp/log and quaternion-to-matrix call
kornia, whose implementations pass our stress tests (exact at 0, 1e-12, pi - 1e-9 and pi,
finite gradients there, float32 included); we add arbitrary batch shapes, a canonical
quaternion sign and clear errors on inputs kornia silently maps to identity (a zero quaternion).
Matrix-to-quaternion is Shepperd's method as one matrix product: it runs in every training
iteration, where kornia's per-case branches cost about a hundred small kernels (with backward).
The geodesic angle uses atan2 (kornia has no such function; acos loses all precision near 0
and pi).
"""

from __future__ import annotations

import torch
from kornia.geometry import conversions as _kc

from manisplat.compilation import constant_tensor
from manisplat.geometry.errors import GeometryError

DEFAULT_DTYPE = torch.float64


def _flat(x: torch.Tensor, tail: int) -> tuple[torch.Tensor, torch.Size]:
    """Reshape ``[..., *tail_shape]`` to ``[B, *tail_shape]``; return it and the batch shape."""
    batch = x.shape[: x.ndim - tail]
    return x.reshape(-1, *x.shape[x.ndim - tail :]), batch


#: hat(w) flattened row-major as a linear map of w: [3][9]
HAT_MAP = ((0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0),
           (0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0),
           (0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0))


def hat(w: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrix of ``w`` [..., 3] -> [..., 3, 3], so that ``hat(w) @ v = w x v``
    (one matrix product: it runs in every training iteration, in the pose corrections)."""
    return (w @ constant_tensor(HAT_MAP, w.dtype, w.device)).reshape(*w.shape[:-1], 3, 3)


def vee(W: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`hat` on the skew part: [..., 3, 3] -> [..., 3]."""
    return 0.5 * torch.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]], dim=-1
    )


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of the axis-angle vector ``w`` [..., 3] (rad) -> [..., 3, 3]."""
    flat, batch = _flat(w, 1)
    return _kc.axis_angle_to_rotation_matrix(flat).reshape(*batch, 3, 3)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Axis-angle vector [..., 3] of rotation matrices [..., 3, 3]; angle in [0, pi].

    At exactly pi the axis sign is arbitrary (both are correct).
    """
    flat, batch = _flat(R, 2)
    return _kc.rotation_matrix_to_axis_angle(flat).reshape(*batch, 3)


def quat_canonical(q: torch.Tensor) -> torch.Tensor:
    """The representative of ``q`` [..., 4] (w, x, y, z) with w >= 0.

    When w == 0, the first non-zero of (x, y, z) is made positive, so every rotation has one
    canonical quaternion. A fixed handful of tensor ops, no branches (it runs inside training).
    """
    first_nonzero = (q != 0).to(torch.uint8).argmax(dim=-1, keepdim=True)  # 0 when all are zero
    sign = torch.where(q.gather(-1, first_nonzero) < 0, -1.0, 1.0).to(q.dtype)
    return q * sign


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix [..., 3, 3] of quaternions [..., 4] (w, x, y, z); ``q`` need not be unit.

    Raises:
        GeometryError: a quaternion has (near) zero norm, so it names no rotation.
    """
    norm = q.norm(dim=-1)
    tiny = norm <= torch.finfo(q.dtype).tiny ** 0.5
    if bool(tiny.any()):
        idx = tiny.nonzero()[0].tolist()
        raise GeometryError(f"quaternion at index {idx} has zero norm; it names no rotation")
    flat, batch = _flat(q / norm[..., None], 1)
    return _kc.quaternion_to_rotation_matrix(flat).reshape(*batch, 3, 3)


def _shepperd_map() -> tuple[tuple[float, ...], ...]:
    """[10][16] the linear map from (R00..R22, 1) to the flattened symmetric matrix ``K = 4 q q^T``
    of Shepperd's method (entries like ``1 + R00 + R11 + R22 = 4 w^2`` and ``R21 - R12 = 4 w x``)."""
    A = [[0.0] * 16 for _ in range(10)]
    diagonal_signs = ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1))
    for k, signs in enumerate(diagonal_signs):
        A[9][5 * k] = 1.0
        for i, s in enumerate(signs):
            A[4 * i][5 * k] = float(s)
    # off-diagonal (k, l): R[a] + sign * R[b], R indexed row-major (R01 = 1, R10 = 3, ...)
    off = {(0, 1): (7, 5, -1), (0, 2): (2, 6, -1), (0, 3): (3, 1, -1),
           (1, 2): (1, 3, 1), (1, 3): (2, 6, 1), (2, 3): (5, 7, 1)}
    for (k, l), (a, b, s) in off.items():
        for entry in (4 * k + l, 4 * l + k):
            A[a][entry], A[b][entry] = 1.0, float(s)
    return tuple(tuple(row) for row in A)


def _hamilton_map() -> tuple[tuple[float, ...], ...]:
    """[16][4] the linear map from the outer product ``a_j b_k`` (flattened j * 4 + k) to the
    Hamilton product ``a * b``."""
    terms = {0: ((0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, -1)),
             1: ((0, 1, 1), (1, 0, 1), (2, 3, 1), (3, 2, -1)),
             2: ((0, 2, 1), (1, 3, -1), (2, 0, 1), (3, 1, 1)),
             3: ((0, 3, 1), (1, 2, 1), (2, 1, -1), (3, 0, 1))}
    H = [[0.0] * 4 for _ in range(16)]
    for i, products in terms.items():
        for j, k, s in products:
            H[4 * j + k][i] = float(s)
    return tuple(tuple(row) for row in H)


SHEPPERD_MAP, HAMILTON_MAP = _shepperd_map(), _hamilton_map()


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternion [..., 4] (w, x, y, z), canonical sign (w >= 0), of rotations [..., 3, 3].

    Shepperd's method: ``K = 4 q q^T`` is linear in R; its row with the largest diagonal entry
    (``4 q_i q``, with ``|q_i| >= 1/2`` as the diagonal sums to 4), normalised, is ``q`` up to
    sign, accurate everywhere, angle pi included. One matrix product and a few gathers: a
    fixed dozen tensor ops (kernel launches on a GPU) rather than a branch per case, since it runs
    in every training iteration.
    """
    flat, batch = _flat(R, 2)
    rows = torch.cat([flat.reshape(-1, 9), torch.ones_like(flat[:, :1, 0])], dim=1)  # [B, 10]
    K = (rows @ constant_tensor(SHEPPERD_MAP, R.dtype, R.device)).reshape(-1, 4, 4)
    pivot = K.diagonal(dim1=-2, dim2=-1).argmax(dim=-1)  # [B]
    row = K.gather(1, pivot[:, None, None].expand(-1, 1, 4))[:, 0]  # [B, 4]
    q = row / row.norm(dim=-1, keepdim=True)
    return quat_canonical(q).reshape(*batch, 4)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a * b`` of quaternions [..., 4] (w, x, y, z): rotation ``a`` after ``b``
    (broadcast over the leading dimensions). An outer product and one matrix product: two
    kernels, for the Gaussians' rotations in every training iteration."""
    a, b = torch.broadcast_tensors(a, b)
    outer = a[..., :, None] * b[..., None, :]
    return outer.reshape(*outer.shape[:-2], 16) @ constant_tensor(HAMILTON_MAP, outer.dtype, outer.device)


def quat_left_multiplier(q: torch.Tensor) -> torch.Tensor:
    """The [..., 4, 4] matrix ``X`` of left multiplication by quaternions ``q`` [..., 4] for row
    vectors: ``b @ X == quat_multiply(q, b)`` for any ``b`` [N, 4]. One small product, so that
    turning many quaternions by one (a rigid node's Gaussians) costs one [N, 4] x [4, 4] product
    instead of :func:`quat_multiply`'s outer products (five times fewer operations)."""
    hamilton = constant_tensor(HAMILTON_MAP, q.dtype, q.device).reshape(4, 16)
    return (q @ hamilton).reshape(*q.shape[:-1], 4, 4)


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    """Conjugate (the inverse, for unit quaternions) of ``q`` [..., 4]."""
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype, device=q.device)


def rotation_angle(R: torch.Tensor) -> torch.Tensor:
    """Geodesic angle (rad, in [0, pi]) of rotations [..., 3, 3], via atan2(sin, cos).

    ``acos((tr R - 1) / 2)`` loses about half the digits near 0 and near pi; atan2 of the
    skew part's norm and the trace term keeps full relative precision at both ends.
    """
    trace = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    cos = 0.5 * (trace - 1.0)
    sin = vee(R).norm(dim=-1)
    return torch.atan2(sin, cos)


def rotation_error(R_a: torch.Tensor, R_b: torch.Tensor) -> torch.Tensor:
    """Geodesic angle (rad) between rotations [..., 3, 3]: the angle of ``R_a^T R_b``."""
    return rotation_angle(R_a.transpose(-1, -2) @ R_b)


def orthonormalize(R: torch.Tensor) -> torch.Tensor:
    """Nearest rotation (Frobenius norm) to each [..., 3, 3] matrix, via SVD (polar factor).

    Use it to remove the drift of long products of rotations. Any reflection is removed by
    flipping the singular vector of the smallest singular value.
    """
    U, _, Vh = torch.linalg.svd(R)
    det = torch.linalg.det(U @ Vh)
    fix = torch.ones_like(U[..., 0, :])
    fix[..., 2] = torch.sign(det) + (det == 0).to(det.dtype)
    return (U * fix[..., None, :]) @ Vh


def is_rotation(R: torch.Tensor, atol: float = 1e-6) -> torch.Tensor:
    """Bool [...]: finite, ``R^T R = I`` and ``det R = +1`` within ``atol``."""
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    finite = torch.isfinite(R).all(dim=-1).all(dim=-1)
    ortho = (R.transpose(-1, -2) @ R - eye).abs().amax(dim=(-1, -2)) <= atol
    det = (torch.linalg.det(R) - 1.0).abs() <= atol
    return finite & ortho & det


def axis_rotation(axis: str, angle: torch.Tensor | float, dtype: torch.dtype = DEFAULT_DTYPE) -> torch.Tensor:
    """Rotation [..., 3, 3] by ``angle`` (rad) about the principal axis ``"x"``, ``"y"`` or ``"z"``."""
    a = torch.as_tensor(angle, dtype=dtype)
    c, s = torch.cos(a), torch.sin(a)
    one, zero = torch.ones_like(a), torch.zeros_like(a)
    rows = {
        "x": [one, zero, zero, zero, c, -s, zero, s, c],
        "y": [c, zero, s, zero, one, zero, -s, zero, c],
        "z": [c, -s, zero, s, c, zero, zero, zero, one],
    }
    if axis not in rows:
        raise ValueError(f"axis must be 'x', 'y' or 'z', got {axis!r}")
    return torch.stack(rows[axis], dim=-1).reshape(*a.shape, 3, 3)


def rpy_to_matrix(rpy: torch.Tensor) -> torch.Tensor:
    """Rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` of ``rpy`` [..., 3] = (roll, pitch, yaw) in rad.

    This is the URDF ``rpy`` convention (fixed axes X, then Y, then Z).
    """
    roll, pitch, yaw = rpy.unbind(-1)
    return axis_rotation("z", yaw, rpy.dtype) @ axis_rotation("y", pitch, rpy.dtype) @ axis_rotation("x", roll, rpy.dtype)


def matrix_to_rpy(R: torch.Tensor) -> torch.Tensor:
    """(roll, pitch, yaw) [..., 3] in rad with ``R = Rz(yaw) Ry(pitch) Rx(roll)``; pitch in [-pi/2, pi/2].

    At gimbal lock (|pitch| = pi/2) roll and yaw are not separable; as piper_sdk does, yaw is
    then 0 and roll carries the whole rotation (a documented convention, not an error).
    """
    cos_pitch = torch.hypot(R[..., 0, 0], R[..., 1, 0])
    pitch = torch.atan2(-R[..., 2, 0], cos_pitch)
    locked = cos_pitch <= 1e3 * torch.finfo(R.dtype).eps
    sign = torch.where(R[..., 2, 0] < 0, 1.0, -1.0).to(R.dtype)
    roll = torch.where(
        locked, torch.atan2(sign * R[..., 0, 1], R[..., 1, 1]), torch.atan2(R[..., 2, 1], R[..., 2, 2])
    )
    yaw = torch.where(locked, torch.zeros_like(pitch), torch.atan2(R[..., 1, 0], R[..., 0, 0]))
    return torch.stack([roll, pitch, yaw], dim=-1)


def random_rotations(n: int, *, generator: torch.Generator | None = None, dtype: torch.dtype = DEFAULT_DTYPE) -> torch.Tensor:
    """``n`` rotations [n, 3, 3] drawn uniformly (Haar measure) via normalised Gaussian quaternions."""
    q = torch.randn(n, 4, generator=generator, dtype=dtype)
    return quat_to_matrix(q)


