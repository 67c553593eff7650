"""Hand-eye closed forms and the motion-diversity check.

Both set-ups are written as one problem ``A_i P = Q B_i`` over the views ``i``:

=============  ==========================  ================  ==================  ===================
set-up         camera                      A_i (robot FK)    B_i (PnP)           unknowns P, Q
=============  ==========================  ================  ==================  ===================
eye-to-hand    fixed to the base           T_base_link       T_cam_board         T_link_board, T_base_cam
eye-in-hand    on ``link`` (e.g. link6)    T_base_link       T_board_cam         T_link_cam, T_base_board
=============  ==========================  ================  ==================  ===================

Pairs give ``(A_j^-1 A_i) P = P (B_j^-1 B_i)`` (AX = XB). :func:`closed_form` (ours) solves the
rotation of P from the rotation axes of all pairs (Park & Martin, by SVD), the rotation of Q as
the chordal mean of ``A_i R_P B_i^T``, then both translations together by linear least squares
over ``R_Ai t_P - t_Q = R_Q t_Bi - t_Ai``. :func:`opencv_closed_forms` runs every OpenCV method
(keyword ``method=``: a positional flag lands in an output slot and silently runs TSAI) and
refuses NaN, identity and non-rigid results instead of passing them on.

:func:`check_motion` refuses motions that do not determine P: all relative rotations about one
axis (the translation along that axis is then unobservable) or rotations that are too small.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from manisplat.calib.errors import DegenerateMotionError, NotEnoughDataError
from manisplat.calib.poses import inv_T, is_rigid, log_rotations, make_T, mean_transform, project_rotation

MIN_PAIR_ANGLE_DEG = 2.0
"""Pairs whose relative rotation is smaller carry no rotation-axis information."""
MIN_AXIS_SPREAD_DEG = 5.0
"""Smallest accepted spread of the relative rotation axes (see :class:`MotionDiversity`)."""
MIN_MAX_ANGLE_DEG = 10.0
"""The largest relative rotation must be at least this."""

OPENCV_HAND_EYE = ("TSAI", "PARK", "HORAUD", "ANDREFF", "DANIILIDIS")
OPENCV_ROBOT_WORLD = ("SHAH", "LI")


def is_eye_to_hand(mount: str) -> bool:
    """``mount == "base"``: camera fixed to the base, board on a robot link."""
    return mount == "base"


def to_problem(mount: str, T_base_link: np.ndarray, T_cam_board: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(A, B)`` [n, 4, 4] of the ``A_i P = Q B_i`` form (see the module docstring)."""
    A = np.asarray(T_base_link, dtype=np.float64)
    B = np.asarray(T_cam_board, dtype=np.float64)
    return A, (B if is_eye_to_hand(mount) else inv_T(B))


def from_problem(mount: str, P: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(T_mount_cam, T_other)``: for eye-to-hand ``(T_base_cam, T_link_board)``, for eye-in-hand
    ``(T_link_cam, T_base_board)``."""
    return (Q, P) if is_eye_to_hand(mount) else (P, Q)


def predicted_board_poses(mount: str, A: np.ndarray, P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """``T_cam_board`` [n, 4, 4] the unknowns predict for robot poses ``A``."""
    B = inv_T(Q) @ A @ P
    return B if is_eye_to_hand(mount) else inv_T(B)


@dataclass(frozen=True)
class MotionDiversity:
    """How well the robot's rotations determine the hand-eye problem.

    Attributes:
        pairs: pose pairs with a relative rotation >= ``MIN_PAIR_ANGLE_DEG``.
        max_angle_deg: largest relative rotation.
        axis_spread_deg: ``atan(sqrt(l2 / l1))`` of the angle-weighted scatter matrix of the
            relative rotation axes (eigenvalues l1 >= l2 >= l3): 0 when every axis is parallel,
            45 when two directions are equally present.
        weakest_axis: (3,) unit direction (in the link frame) that the axes cover least: rotating
            about it adds the most information.
    """

    pairs: int
    max_angle_deg: float
    axis_spread_deg: float
    weakest_axis: np.ndarray

    def to_dict(self) -> dict:
        return {"pairs": self.pairs, "max_angle_deg": self.max_angle_deg, "axis_spread_deg": self.axis_spread_deg,
                "weakest_axis": self.weakest_axis.tolist()}


def relative_rotations(A: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(i, j, w)`` over all pairs i < j: indices and rotation vectors [m, 3] of ``A_j^-1 A_i``."""
    n = len(A)
    i, j = np.triu_indices(n, k=1)
    rel = np.swapaxes(A[j, :3, :3], -1, -2) @ A[i, :3, :3]
    return i, j, log_rotations(rel).reshape(-1, 3)


def motion_diversity(A: np.ndarray) -> MotionDiversity:
    """:class:`MotionDiversity` of robot poses ``A`` [n, 4, 4]."""
    A = np.asarray(A, dtype=np.float64)
    if len(A) < 2:
        return MotionDiversity(0, 0.0, 0.0, np.array([1.0, 0.0, 0.0]))
    _, _, w = relative_rotations(A)
    angles = np.linalg.norm(w, axis=1)
    keep = angles >= np.radians(MIN_PAIR_ANGLE_DEG)
    max_angle = float(np.degrees(angles.max()))
    if keep.sum() == 0:
        return MotionDiversity(0, max_angle, 0.0, np.array([1.0, 0.0, 0.0]))
    axes = w[keep] / angles[keep, None]
    M = (axes * angles[keep, None]).T @ axes  # angle-weighted scatter of the axes
    evals, evecs = np.linalg.eigh(M)  # ascending
    l1, l2 = max(evals[2], 1e-300), max(evals[1], 0.0)
    spread = float(np.degrees(np.arctan(np.sqrt(l2 / l1))))
    return MotionDiversity(int(keep.sum()), max_angle, spread, evecs[:, 0])


def check_motion(A: np.ndarray, min_spread_deg: float = MIN_AXIS_SPREAD_DEG,
                 min_angle_deg: float = MIN_MAX_ANGLE_DEG) -> MotionDiversity:
    """The diversity of ``A``; raises :class:`DegenerateMotionError` (or
    :class:`NotEnoughDataError` for fewer than 3 poses) when it does not determine the solution."""
    if len(A) < 3:
        raise NotEnoughDataError(f"hand-eye calibration needs at least 3 distinct robot poses; got {len(A)}")
    d = motion_diversity(A)
    if d.max_angle_deg < min_angle_deg:
        raise DegenerateMotionError(
            f"the robot barely rotates between poses (largest relative rotation {d.max_angle_deg:.1f} deg < "
            f"{min_angle_deg:g} deg): the rotation is not observable. Tilt the gripper by 20-45 deg about "
            "different axes between poses.")
    if d.axis_spread_deg < min_spread_deg:
        ax = np.round(d.weakest_axis, 2).tolist()
        raise DegenerateMotionError(
            f"all relative rotations are about one axis (axis spread {d.axis_spread_deg:.2f} deg < {min_spread_deg:g} "
            f"deg over {d.pairs} pairs, e.g. only joint 6 turns): the translation along that axis is unobservable. "
            f"Add poses that rotate about another axis, e.g. {ax} in the link frame.")
    return d


def solve_translations(A: np.ndarray, B: np.ndarray, R_P: np.ndarray, R_Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(t_P, t_Q)`` by linear least squares over ``R_Ai t_P - t_Q = R_Q t_Bi - t_Ai``."""
    n = len(A)
    M = np.zeros((3 * n, 6))
    rhs = np.zeros(3 * n)
    for k in range(n):
        M[3 * k:3 * k + 3, :3] = A[k, :3, :3]
        M[3 * k:3 * k + 3, 3:] = -np.eye(3)
        rhs[3 * k:3 * k + 3] = R_Q @ B[k, :3, 3] - A[k, :3, 3]
    sol, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    return sol[:3], sol[3:]


def closed_form(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Our closed form ``(P, Q)`` of ``A_i P = Q B_i`` (module docstring). Call
    :func:`check_motion` first; raises :class:`DegenerateMotionError` if no pair rotates."""
    i, j, alpha = relative_rotations(A)
    relB = np.swapaxes(B[j, :3, :3], -1, -2) @ B[i, :3, :3]
    beta = log_rotations(relB).reshape(-1, 3)
    na, nb = np.linalg.norm(alpha, axis=1), np.linalg.norm(beta, axis=1)
    keep = (na >= np.radians(MIN_PAIR_ANGLE_DEG)) & (nb >= np.radians(MIN_PAIR_ANGLE_DEG))
    if keep.sum() < 2:
        raise DegenerateMotionError("closed form: fewer than 2 pose pairs rotate by more than "
                                    f"{MIN_PAIR_ANGLE_DEG} deg")
    # alpha = R_P beta (rotation axes, angles equal): orthogonal Procrustes without centring
    R_P = project_rotation(alpha[keep].T @ beta[keep])
    R_Q = project_rotation(np.sum(A[:, :3, :3] @ R_P @ np.swapaxes(B[:, :3, :3], -1, -2), axis=0))
    t_P, t_Q = solve_translations(A, B, R_P, R_Q)
    return make_T(R_P, t_P), make_T(R_Q, t_Q)


def _rt(T: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    return [np.ascontiguousarray(x[:3, :3]) for x in T], [np.ascontiguousarray(x[:3, 3:4]) for x in T]


def _check_result(name: str, T: np.ndarray, A: np.ndarray) -> str:
    """'' when ``T`` is a usable result, else why not (NaN, identity, not rigid, implausible)."""
    if not np.isfinite(T).all():
        return "returned NaN/Inf"
    if not is_rigid(T, 1e-5):
        return "returned a non-rigid matrix"
    if np.allclose(T[:3, :3], np.eye(3), atol=1e-12) and np.allclose(T[:3, 3], 0.0, atol=1e-12):
        return "returned exactly identity (OpenCV's silent failure: not enough informative motion)"
    scale = max(1.0, 10.0 * float(np.abs(A[:, :3, 3]).max()))
    if np.linalg.norm(T[:3, 3]) > scale:
        return f"translation {np.linalg.norm(T[:3, 3]):.2f} m is implausible"
    return ""


def opencv_closed_forms(mount: str, T_base_link: np.ndarray, T_cam_board: np.ndarray
                        ) -> dict[str, tuple[np.ndarray, np.ndarray] | str]:
    """Every OpenCV hand-eye method: name -> ``(P, Q)`` or the reason it failed.

    ``calibrateHandEye`` returns one unknown; the other is the chordal mean over the views
    (``Q = mean(A_i P B_i^-1)`` or ``P = mean(A_i^-1 Q B_i)``).
    """
    A, B = to_problem(mount, T_base_link, T_cam_board)
    out: dict[str, tuple[np.ndarray, np.ndarray] | str] = {}
    if not hasattr(cv2, "calibrateHandEye"):
        return {m: "this OpenCV has no calibrateHandEye" for m in OPENCV_HAND_EYE + OPENCV_ROBOT_WORLD}
    eth = is_eye_to_hand(mount)
    T_cam_board = np.asarray(T_cam_board, dtype=np.float64)
    # calibrateHandEye: gripper2base slot gets inv(FK) for eye-to-hand (output cam2base = Q),
    # FK for eye-in-hand (output cam2gripper = P).
    Rg, tg = _rt(inv_T(A) if eth else A)
    Rt, tt = _rt(T_cam_board)
    for name in OPENCV_HAND_EYE:
        try:
            R, t = cv2.calibrateHandEye(Rg, tg, Rt, tt, method=getattr(cv2, f"CALIB_HAND_EYE_{name}"))
            X = make_T(np.asarray(R), np.asarray(t))
        except cv2.error as exc:
            out[name] = f"raised cv2.error: {exc.err}"
            continue
        why = _check_result(name, X, A)
        if why:
            out[name] = why
            continue
        if eth:
            Q = X
            P = mean_transform(inv_T(A) @ Q @ B)
        else:
            P = X
            Q = mean_transform(A @ P @ inv_T(B))
        out[name] = (P, Q)
    # calibrateRobotWorldHandEye (AX = ZB): eye-to-hand: world2cam = T_cam_board, base2gripper = FK
    # -> base2world = T_board_link (P^-1), gripper2cam = T_cam_base (Q^-1);
    # eye-in-hand: base2gripper = inv(FK) -> base2world = T_board_base (Q^-1), gripper2cam = T_cam_link (P^-1).
    Rb, tb = _rt(A if eth else inv_T(A))
    for name in OPENCV_ROBOT_WORLD:
        try:
            Rw, tw, Rc, tc = cv2.calibrateRobotWorldHandEye(Rt, tt, Rb, tb,
                                                            method=getattr(cv2, f"CALIB_ROBOT_WORLD_HAND_EYE_{name}"))
            W, C = make_T(np.asarray(Rw), np.asarray(tw)), make_T(np.asarray(Rc), np.asarray(tc))
        except cv2.error as exc:
            out[name] = f"raised cv2.error: {exc.err}"
            continue
        why = _check_result(name, W, A) or _check_result(name, C, A)
        if why:
            out[name] = why
            continue
        out[name] = (inv_T(W), inv_T(C)) if eth else (inv_T(C), inv_T(W))
    return out
