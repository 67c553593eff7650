"""Joint nonlinear refinement of both hand-eye unknowns over every corner reprojection.

Unknowns: ``P`` and ``Q`` of ``A_i P = Q B_i`` (:mod:`.handeye`), each as a rotation update
``R = R0 Rodrigues(w)`` and a translation ``t = t0 + v`` (12 parameters, radians and metres).
Residuals: detected minus projected corner pixels through the full chain
``T_cam_board_i(P, Q, A_i)``. Two stages: a robust fit (``soft_l1``, scale ``f_scale_px``),
then corners farther than ``max(outlier_sigmas * sigma, min_outlier_px)`` are dropped
(sigma = 1.4826 * MAD of the residual components), views that lose more than half their
corners are dropped whole, and a plain least-squares fit on the inliers gives the result and
its covariance ``s^2 (J^T J)^-1`` (``s^2`` = residual sum of squares / (m - 12)).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from manisplat.calib.camera import CameraModel
from manisplat.calib.errors import CalibrationError, DegenerateMotionError
from manisplat.calib.handeye import predicted_board_poses
from manisplat.calib.poses import make_T, rodrigues


@dataclass
class RefineResult:
    """Outcome of :func:`refine`.

    Attributes:
        P, Q: (4, 4) refined unknowns.
        residuals: list per view of (N_i, 2) residual pixels (detected - projected), all corners.
        inliers: list per view of (N_i,) bool.
        view_used: (n,) bool, views kept.
        cov: (12, 12) covariance of (w_P, v_P, w_Q, v_Q), rad and m.
        sigma_px: estimated corner noise (residual RMS per coordinate, inliers).
        iterations: function evaluations of both stages.
    """

    P: np.ndarray
    Q: np.ndarray
    residuals: list[np.ndarray]
    inliers: list[np.ndarray]
    view_used: np.ndarray
    cov: np.ndarray
    sigma_px: float
    iterations: int
    notes: list[str] = field(default_factory=list)

    def std(self, which: str) -> tuple[float, float]:
        """(rotation deg, translation mm) 1-sigma of ``"P"`` or ``"Q"`` (root of the trace of its
        3x3 rotation and translation blocks)."""
        o = 0 if which == "P" else 6
        r = np.sqrt(max(np.trace(self.cov[o:o + 3, o:o + 3]), 0.0))
        t = np.sqrt(max(np.trace(self.cov[o + 3:o + 6, o + 3:o + 6]), 0.0))
        return float(np.degrees(r)), float(1000.0 * t)


def _apply(x: np.ndarray, P0: np.ndarray, Q0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    P = make_T(P0[:3, :3] @ rodrigues(x[0:3]), P0[:3, 3] + x[3:6])
    Q = make_T(Q0[:3, :3] @ rodrigues(x[6:9]), Q0[:3, 3] + x[9:12])
    return P, Q


def reprojection_residuals(mount: str, A: np.ndarray, P: np.ndarray, Q: np.ndarray, obj: list[np.ndarray],
                           img: list[np.ndarray], camera: CameraModel) -> list[np.ndarray]:
    """Per view (N_i, 2) detected - projected pixels for unknowns ``P``, ``Q``."""
    B = predicted_board_poses(mount, A, P, Q)
    out = []
    for k in range(len(A)):
        if B[k, 2, 3] <= 0:
            out.append(np.full_like(img[k], 1e4))  # board behind the camera: a large, finite residual
        else:
            out.append(img[k] - camera.project(B[k], obj[k]))
    return out


def _fit(mount: str, A, P0, Q0, obj, img, camera, loss: str, f_scale: float, max_nfev: int):
    def fun(x: np.ndarray) -> np.ndarray:
        P, Q = _apply(x, P0, Q0)
        return np.concatenate([r.reshape(-1) for r in reprojection_residuals(mount, A, P, Q, obj, img, camera)])

    res = least_squares(fun, np.zeros(12), jac="2-point", method="trf", loss=loss, f_scale=f_scale,
                        x_scale=np.r_[np.full(3, 1e-3), np.full(3, 1e-3), np.full(3, 1e-3), np.full(3, 1e-3)],
                        max_nfev=max_nfev, xtol=1e-12, ftol=1e-12, gtol=1e-12)
    if not np.isfinite(res.x).all():
        raise CalibrationError("refinement diverged (non-finite parameters)")
    return res


def refine(mount: str, A: np.ndarray, obj: list[np.ndarray], img: list[np.ndarray], camera: CameraModel,
           P0: np.ndarray, Q0: np.ndarray, *, f_scale_px: float = 1.0, outlier_sigmas: float = 5.0,
           min_outlier_px: float = 0.5, max_nfev: int = 200) -> RefineResult:
    """Refine ``P0``, ``Q0`` (module docstring).

    Args:
        A: (n, 4, 4) robot poses ``T_base_link``.
        obj, img: per view the (N_i, 3) board points (metres) and (N_i, 2) detected pixels.
    Raises:
        DegenerateMotionError: the final Jacobian is rank deficient (unobservable direction).
        CalibrationError: divergence or too few inliers.
    """
    res1 = _fit(mount, A, P0, Q0, obj, img, camera, "soft_l1", f_scale_px, max_nfev)
    P1, Q1 = _apply(res1.x, P0, Q0)
    r1 = reprojection_residuals(mount, A, P1, Q1, obj, img, camera)
    comps = np.concatenate([r.reshape(-1) for r in r1])
    sigma = 1.4826 * float(np.median(np.abs(comps - np.median(comps))))
    thresh = max(outlier_sigmas * sigma, min_outlier_px)
    inl = [np.linalg.norm(r, axis=1) <= thresh for r in r1]
    used = np.array([m.mean() > 0.5 and m.sum() >= 4 for m in inl])
    notes = []
    if (~used).any():
        notes.append(f"dropped {int((~used).sum())} view(s) whose corners mostly disagree with the others: "
                     f"{np.flatnonzero(~used).tolist()}")
    if used.sum() < 3:
        raise CalibrationError(f"only {int(used.sum())} views agree with the solution; the data are inconsistent "
                               "(wrong board file, joint/image pairing or robot description?)")
    idx = np.flatnonzero(used)
    obj2 = [obj[k][inl[k]] for k in idx]
    img2 = [img[k][inl[k]] for k in idx]
    res2 = _fit(mount, A[idx], P1, Q1, obj2, img2, camera, "linear", 1.0, max_nfev)
    P, Q = _apply(res2.x, P1, Q1)
    J = res2.jac
    m = J.shape[0]
    JtJ = J.T @ J
    s = np.linalg.svd(J, compute_uv=False)
    if s[-1] <= 1e-9 * s[0]:
        raise DegenerateMotionError(f"the refinement Jacobian is rank deficient (condition {s[0] / max(s[-1], 1e-300):.2e}): "
                                    "some direction of the camera pose is not observable from these views")
    s2 = float(2.0 * res2.cost / max(m - 12, 1))
    cov = s2 * np.linalg.inv(JtJ)
    final = reprojection_residuals(mount, A, P, Q, obj, img, camera)
    inliers = [np.linalg.norm(r, axis=1) <= thresh if used[k] else np.zeros(len(r), bool) for k, r in enumerate(final)]
    if not (np.isfinite(P).all() and np.isfinite(Q).all() and np.isfinite(cov).all()):
        raise CalibrationError("refinement produced non-finite values")
    return RefineResult(P, Q, final, inliers, used, cov, float(np.sqrt(s2)), int(res1.nfev + res2.nfev), notes)
