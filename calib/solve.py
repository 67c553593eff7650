"""Hand-eye solve from board views and robot poses: checks, closed forms, refinement.

Steps: at least 3 usable views (:class:`NotEnoughDataError` otherwise) -> views grouped into
distinct robot poses -> motion-diversity check (:class:`DegenerateMotionError`) -> every closed
form (ours and OpenCV's), each scored by its median corner reprojection error -> the best one
refined jointly over all corners (:func:`.refine.refine`) -> result with residual statistics,
covariance and the closed forms' distances to it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from manisplat.calib.board import BoardSpec
from manisplat.calib.camera import CameraModel
from manisplat.calib.detect import BoardView
from manisplat.calib.errors import CalibrationError, NotEnoughDataError
from manisplat.calib.handeye import (MotionDiversity, check_motion, closed_form, from_problem, is_eye_to_hand,
                                     opencv_closed_forms, to_problem)
from manisplat.calib.poses import pose_difference
from manisplat.calib.refine import RefineResult, refine, reprojection_residuals

SAME_POSE_DEG = 0.05
SAME_POSE_M = 0.0005


@dataclass
class HandEyeResult:
    """A solved hand-eye calibration.

    Attributes:
        mount: ``"base"`` (eye-to-hand) or the camera's link (eye-in-hand).
        link: the robot link whose FK poses were used (board link or camera link).
        T_mount_cam: (4, 4) camera-to-mount (``T_base_cam`` or ``T_link_cam``), metres.
        T_other: (4, 4) the second unknown: ``T_link_board`` (eye-to-hand) or ``T_base_board``.
        refine: the refinement (residuals, inliers, covariance).
        view_index: (n,) the views' frame indices, in the order of the residuals.
        closed_forms: method -> ``{"rot_diff_deg", "trans_diff_mm", "median_px"}`` or ``{"error"}``.
        start: the closed form the refinement started from.
        diversity: the motion check.
        poses: number of distinct robot poses.
    """

    mount: str
    link: str
    T_mount_cam: np.ndarray
    T_other: np.ndarray
    refine: RefineResult
    view_index: np.ndarray
    closed_forms: dict[str, dict]
    start: str
    diversity: MotionDiversity
    poses: int
    notes: list[str] = field(default_factory=list)

    def residual_stats(self) -> dict:
        """Corner reprojection statistics (pixels) over inliers, plus counts."""
        norms = np.concatenate([np.linalg.norm(r, axis=1)[m] for r, m in zip(self.refine.residuals, self.refine.inliers)])
        total = sum(len(r) for r in self.refine.residuals)
        return {"rms_px": float(np.sqrt(np.mean(norms ** 2))), "median_px": float(np.median(norms)),
                "p95_px": float(np.percentile(norms, 95)), "max_px": float(norms.max()),
                "corners_used": int(len(norms)), "corners_total": int(total),
                "views_used": int(self.refine.view_used.sum()), "views_total": int(len(self.view_index))}

    def per_view(self) -> list[dict]:
        """Per view: frame index, used, rms and max residual (px) over its corners."""
        out = []
        for k, r in enumerate(self.refine.residuals):
            n = np.linalg.norm(r, axis=1)
            out.append({"frame": int(self.view_index[k]), "used": bool(self.refine.view_used[k]),
                        "corners": int(len(n)), "inliers": int(self.refine.inliers[k].sum()),
                        "rms_px": float(np.sqrt(np.mean(n ** 2))), "max_px": float(n.max())})
        return out

    def uncertainty(self) -> dict:
        """1-sigma of both unknowns from the refinement covariance."""
        rq, tq = self.refine.std("Q" if is_eye_to_hand(self.mount) else "P")
        ro, to = self.refine.std("P" if is_eye_to_hand(self.mount) else "Q")
        return {"T_mount_cam_rot_std_deg": rq, "T_mount_cam_trans_std_mm": tq,
                "other_rot_std_deg": ro, "other_trans_std_mm": to, "corner_sigma_px": self.refine.sigma_px}


def distinct_poses(A: np.ndarray) -> np.ndarray:
    """Indices of the first view of each run of (nearly) equal consecutive robot poses."""
    keep = [0]
    for k in range(1, len(A)):
        rot, trans = pose_difference(A[keep[-1]], A[k])
        if rot > SAME_POSE_DEG or trans > SAME_POSE_M * 1000:
            keep.append(k)
    return np.asarray(keep)


def _median_px(mount, A, P, Q, obj, img, camera) -> float:
    r = reprojection_residuals(mount, A, P, Q, obj, img, camera)
    v = float(np.median(np.concatenate([np.linalg.norm(x, axis=1) for x in r])))
    return v if np.isfinite(v) else float("inf")


def solve_hand_eye(views: list[BoardView], T_base_link: np.ndarray, spec: BoardSpec, camera: CameraModel,
                   mount: str = "base", link: str = "link6", *, use_opencv: bool = True,
                   min_spread_deg: float | None = None) -> HandEyeResult:
    """Solve from views and the robot poses ``T_base_link`` (n, 4, 4) at those views.

    Args:
        mount: ``"base"`` (camera fixed, board on ``link``) or the camera's link (board fixed).
        link: the link holding the board (eye-to-hand) or the camera (eye-in-hand).
        use_opencv: also try OpenCV's closed forms (ours always runs).
        min_spread_deg: override of the rotation-axis spread threshold.
    """
    A_all = np.asarray(T_base_link, dtype=np.float64)
    if len(views) != len(A_all):
        raise CalibrationError(f"{len(views)} views but {len(A_all)} robot poses: they must pair one to one")
    if len(views) < 3:
        raise NotEnoughDataError(f"hand-eye calibration needs at least 3 usable board views; got {len(views)}")
    if not is_eye_to_hand(mount) and mount != link:
        raise CalibrationError(f"eye-in-hand: the camera link ({mount!r}) and the FK link ({link!r}) must match")
    obj = [spec.corners_3d()[v.ids] for v in views]
    img = [v.corners for v in views]
    Bcam = np.stack([v.T_cam_board for v in views])
    first = distinct_poses(A_all)
    clear = np.array([k for k in first if not views[k].ambiguous])
    start_set = clear if len(clear) >= 3 else first
    kw = {} if min_spread_deg is None else {"min_spread_deg": min_spread_deg}
    diversity = check_motion(A_all[first], **kw)
    A, B = to_problem(mount, A_all, Bcam)
    candidates: dict[str, tuple[np.ndarray, np.ndarray] | str] = {}
    try:
        candidates["ours"] = closed_form(A[start_set], B[start_set])
    except CalibrationError as exc:
        candidates["ours"] = str(exc)
    if use_opencv:
        candidates.update(opencv_closed_forms(mount, A_all[start_set], Bcam[start_set]))
    scored = {}
    for name, c in candidates.items():
        if isinstance(c, str):
            continue
        scored[name] = _median_px(mount, A, c[0], c[1], obj, img, camera)
    if not scored:
        raise CalibrationError("no closed form produced a usable start: " +
                               "; ".join(f"{k}: {v}" for k, v in candidates.items()))
    start = min(scored, key=scored.get)
    P0, Q0 = candidates[start]  # type: ignore[misc]
    ref = refine(mount, A, obj, img, camera, P0, Q0)
    T_mount_cam, T_other = from_problem(mount, ref.P, ref.Q)
    table: dict[str, dict] = {}
    for name, c in candidates.items():
        if isinstance(c, str):
            table[name] = {"error": c}
            continue
        Tm, _ = from_problem(mount, *c)
        rot, trans = pose_difference(Tm, T_mount_cam)
        table[name] = {"rot_diff_deg": rot, "trans_diff_mm": trans,
                       "median_px": scored[name] if np.isfinite(scored[name]) else None}
    return HandEyeResult(mount, link, T_mount_cam, T_other, ref, np.array([v.index for v in views]), table, start,
                         diversity, len(first), list(ref.notes))
