"""Geometry on torch tensors: rotations, rigid transforms, point-set alignment, interpolation.

Batched over leading dimensions, float64 by default (float32 allowed), no NaN/Inf out of any
function: degenerate inputs raise :class:`GeometryError` or follow a documented convention.

Conventions: quaternions are (w, x, y, z); ``T_a_b`` maps frame-b coordinates to frame a;
twists are (v, w); angles in radians.

Where kornia is used and where not (each choice backed by ``tests/geometry``):
* kornia: SO(3)/SE(3) exp and log, quaternion <-> matrix. They pass our stress tests at 0,
  1e-12, pi - 1e-9 and pi in float64 and float32, with finite gradients.
* own: the geodesic angle (kornia has no atan2 form; acos is imprecise near 0 and pi),
  Kabsch/Umeyama and RANSAC (none in kornia), slerp via exp/log (exact at the ends), Euler RPY
  with piper_sdk's gimbal-lock convention, and checks kornia skips (a zero quaternion becomes
  identity there; it is an error here).
"""

from manisplat.geometry.align import RansacFit, RigidFit, kabsch, kabsch_ransac, umeyama
from manisplat.geometry.errors import GeometryError
from manisplat.geometry.interpolate import (
    Bracket,
    JointInterpolation,
    bracket_times,
    interpolate_joints,
    interpolate_poses,
    slerp,
)
from manisplat.geometry.rotation import (
    DEFAULT_DTYPE,
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
from manisplat.geometry.se3 import (
    invert_transform,
    is_transform,
    make_transform,
    pose_error,
    se3_exp,
    se3_log,
    transform_points,
    translation_error,
)

__all__ = [
    "DEFAULT_DTYPE",
    "Bracket",
    "GeometryError",
    "JointInterpolation",
    "RansacFit",
    "RigidFit",
    "axis_rotation",
    "bracket_times",
    "hat",
    "interpolate_joints",
    "interpolate_poses",
    "invert_transform",
    "is_rotation",
    "is_transform",
    "kabsch",
    "kabsch_ransac",
    "make_transform",
    "matrix_to_quat",
    "matrix_to_rpy",
    "orthonormalize",
    "pose_error",
    "quat_canonical",
    "quat_conjugate",
    "quat_left_multiplier",
    "quat_multiply",
    "quat_to_matrix",
    "random_rotations",
    "rotation_angle",
    "rotation_error",
    "rpy_to_matrix",
    "se3_exp",
    "se3_log",
    "slerp",
    "so3_exp",
    "so3_log",
    "transform_points",
    "translation_error",
    "umeyama",
    "vee",
]
