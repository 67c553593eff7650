"""Board detection (OpenCV ``CharucoDetector``), the detector's corner-offset convention, and
the board pose of one view (IPPE with flip-ambiguity check, then Levenberg-Marquardt).

Corner offset: OpenCV 4.10's ``CharucoDetector`` returns corners shifted by +0.5 px in x and y
(opencv/opencv#25539); later versions do not. :func:`detector_corner_offset` measures the shift
of the installed OpenCV once (renders the board at known poses with :mod:`.render`, detects,
compares with the projection) and :class:`BoardDetector` subtracts it, so corners always follow
the pixel-centre convention. The measured value is reported in ``calibration.json``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from manisplat.calib.board import BoardSpec
from manisplat.calib.camera import CameraModel
from manisplat.calib.errors import CalibrationError, NotEnoughDataError
from manisplat.calib.poses import make_T

MIN_CORNERS = 6
"""Fewest ChArUco corners for a view to count (PnP needs 4 non-collinear; 6 adds margin)."""
KNOWN_OFFSETS = (0.0, 0.5)
_OFFSET_CACHE: dict[str, tuple[float, np.ndarray]] = {}


@dataclass
class Detection:
    """ChArUco corners found in one image.

    Attributes:
        ids: (N,) int64 corner ids.
        corners: (N, 2) float64 pixel positions (pixel-centre convention, offset removed).
        markers: number of ArUco markers found.
    """

    ids: np.ndarray
    corners: np.ndarray
    markers: int


@dataclass
class BoardView:
    """One image with a usable board pose.

    Attributes:
        index: the frame index in the episode (or any caller id).
        ids, corners: as in :class:`Detection`.
        T_cam_board: (4, 4) float64 board pose from PnP, metres.
        rms_px: PnP reprojection RMS, pixels.
        ambiguous: both planar PnP solutions fit about equally (small or far board): the pose
            is kept for the joint refinement (which fits corners, not poses) but not used to
            start it when enough unambiguous views exist.
    """

    index: int
    ids: np.ndarray
    corners: np.ndarray
    T_cam_board: np.ndarray
    rms_px: float
    ambiguous: bool = False


def _gray(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if image.ndim != 2:
        raise CalibrationError(f"detect: expected an (H, W) or (H, W, 3) image; got shape {image.shape}")
    return image


def _raw_detect(spec: BoardSpec, detector: cv2.aruco.CharucoDetector, gray: np.ndarray) -> Detection:
    corners, ids, _, marker_ids = detector.detectBoard(gray)
    markers = 0 if marker_ids is None else len(marker_ids)
    if ids is None or corners is None or len(ids) == 0:
        return Detection(np.zeros(0, np.int64), np.zeros((0, 2)), markers)
    return Detection(ids.reshape(-1).astype(np.int64), corners.reshape(-1, 2).astype(np.float64), markers)


def detector_corner_offset(refresh: bool = False) -> tuple[float, np.ndarray]:
    """The installed ``CharucoDetector``'s corner offset: ``(chosen, measured)``.

    ``measured`` (2,) is the mean (detected - true) corner position, px, over four rendered views
    (1280x720, f = 900 px, tilted 20-35 deg, supersampled, no blur or noise); ``chosen`` is the
    known convention (0.0 or 0.5 px) it matches within 0.1 px. Raises :class:`CalibrationError`
    when it matches neither, since then corners cannot be trusted.
    """
    key = cv2.__version__
    if key in _OFFSET_CACHE and not refresh:
        return _OFFSET_CACHE[key]
    from manisplat.calib.render import render_board  # local: render imports nothing from here

    spec = BoardSpec()
    cam = CameraModel(K=[[900.0, 0, 639.5], [0, 900.0, 359.5], [0, 0, 1]], width=1280, height=720)
    detector = cv2.aruco.CharucoDetector(spec.cv_board())
    obj = spec.corners_3d()
    errors = []
    for k, (ax, angle, z) in enumerate([((1, 0.3, 0), 25, 0.45), ((0.2, 1, 0), -30, 0.55), ((1, 1, 0.3), 35, 0.5),
                                        ((0.4, -1, 0.1), 20, 0.6)]):
        axis = np.asarray(ax, float) / np.linalg.norm(ax)
        R, _ = cv2.Rodrigues(axis * np.radians(angle))
        center = np.array([spec.size_m[0] / 2, spec.size_m[1] / 2, 0.0])
        t = np.array([0.02 * (k - 1.5), 0.01 * k, z]) - R @ center
        T = make_T(R, t)
        img = render_board(spec, cam, T, supersample=4)
        det = _raw_detect(spec, detector, img)
        if len(det.ids) < 10:
            raise CalibrationError("detector_corner_offset: the self-check render was not detected; "
                               "is the OpenCV aruco module working?")
        errors.append(det.corners - cam.project(T, obj[det.ids]))
    measured = np.concatenate(errors).mean(axis=0)
    for known in KNOWN_OFFSETS:
        if np.all(np.abs(measured - known) < 0.1):
            _OFFSET_CACHE[key] = (known, measured)
            return _OFFSET_CACHE[key]
    raise CalibrationError(f"OpenCV {cv2.__version__}'s CharucoDetector corners are off by {measured.round(3).tolist()} "
                           f"px, neither of the known conventions {KNOWN_OFFSETS}; pass corner_offset explicitly")


class BoardDetector:
    """Detects a ChArUco board and returns pixel-centre-convention corners.

    Args:
        spec: the board.
        corner_offset: px subtracted from OpenCV's corners in x and y; ``None`` measures it
            (:func:`detector_corner_offset`).
        min_corners: fewest corners for a usable view.
    """

    def __init__(self, spec: BoardSpec, corner_offset: float | None = None, min_corners: int = MIN_CORNERS) -> None:
        self.spec = spec
        self.board = spec.cv_board()
        self.detector = cv2.aruco.CharucoDetector(self.board)
        self.corner_offset = detector_corner_offset()[0] if corner_offset is None else float(corner_offset)
        self.min_corners = max(int(min_corners), 4)
        self.object_points = spec.corners_3d()

    def detect(self, image: np.ndarray) -> Detection:
        """Corners of one RGB or grey image (possibly none)."""
        det = _raw_detect(self.spec, self.detector, _gray(image))
        det.corners = det.corners - self.corner_offset
        return det

    def view(self, index: int, det: Detection, camera: CameraModel) -> tuple[BoardView | None, str]:
        """The board pose of a detection, or ``(None, reason)`` when it is unusable."""
        n = len(det.ids)
        if n < self.min_corners:
            return None, f"{n} corners (< {self.min_corners}; {det.markers} markers)"
        if self.board.checkCharucoCornersCollinear(det.ids.reshape(-1, 1).astype(np.int32)):
            return None, f"{n} corners on one line"
        T, rms, ambiguous, reason = board_pose(self.object_points[det.ids], det.corners, camera)
        if T is None:
            return None, reason
        return BoardView(index, det.ids, det.corners, T, rms, ambiguous), ""


def board_pose(obj: np.ndarray, img: np.ndarray, camera: CameraModel,
               ambiguity_ratio: float = 2.0) -> tuple[np.ndarray | None, float, bool, str]:
    """``(T_cam_board, rms_px, ambiguous, "")`` from planar points, or ``(None, nan, False, reason)``.

    IPPE gives both planar solutions; the pose is ``ambiguous`` when the other one fits nearly
    as well (error ratio < ``ambiguity_ratio``). The best is refined with ``solvePnPRefineLM``.
    """
    obj = np.ascontiguousarray(obj, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(img, dtype=np.float64).reshape(-1, 1, 2)
    try:
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img, camera.K, camera.cv_dist, flags=cv2.SOLVEPNP_IPPE)
    except cv2.error as exc:
        return None, float("nan"), False, f"PnP failed: {exc.err}"
    if n < 1:
        return None, float("nan"), False, "PnP found no pose"
    errs = np.asarray(errs, dtype=np.float64).reshape(-1)
    order = np.argsort(errs)
    best = int(order[0])
    ambiguous = bool(n > 1 and errs[order[1]] < ambiguity_ratio * max(errs[best], 1e-3))
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera.K, camera.cv_dist, rvecs[best].copy(), tvecs[best].copy())
    R, _ = cv2.Rodrigues(rvec)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, tvec.reshape(3)
    if not np.isfinite(T).all() or T[2, 3] <= 0:
        return None, float("nan"), False, "PnP pose not finite or behind the camera"
    res = camera.project(T, obj.reshape(-1, 3)) - img.reshape(-1, 2)
    return T, float(np.sqrt(np.mean(np.sum(res ** 2, axis=1)))), ambiguous, ""


def require_views(views: list, needed: int, rejected: dict[int, str], total: int) -> None:
    """Raise :class:`NotEnoughDataError` when fewer than ``needed`` views are usable, listing why
    the others were refused."""
    if len(views) >= needed:
        return
    reasons = "; ".join(f"frame {i}: {r}" for i, r in list(rejected.items())[:8])
    more = f" (and {len(rejected) - 8} more)" if len(rejected) > 8 else ""
    raise NotEnoughDataError(f"only {len(views)} of {total} frames have a usable board view; at least {needed} "
                             f"are needed. Refused: {reasons}{more}")
