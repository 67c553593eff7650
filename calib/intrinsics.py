"""Intrinsics: from an OAK device's factory calibration at the recording size, or solved from
board frames with ``cv2.calibrateCamera`` (reprojection RMS, per-view errors, image coverage).

Coverage: the image is cut into a ``grid`` (8 x 6 cells); a cell is covered when a detected
corner falls in it. Distortion extrapolates badly where no corner was seen, so a solve whose
coverage is below ``min_coverage`` (default 0.6) is refused unless the caller allows it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from manisplat.calib.board import BoardSpec
from manisplat.calib.camera import CameraModel
from manisplat.calib.detect import BoardDetector, Detection
from manisplat.calib.errors import CalibrationError, InputError, NotEnoughDataError, read_json

MIN_VIEWS = 6
MIN_CORNERS_PER_VIEW = 8
DIST_MODELS = {"none": 0, "k1k2": 4, "k1k2k3": 5, "rational": 8}


@dataclass
class IntrinsicsResult:
    """A solved camera.

    Attributes:
        camera: K, dist, size.
        rms_px: overall reprojection RMS, px (OpenCV's value).
        per_view_rms_px: (n,) per view.
        coverage: fraction of grid cells holding a corner (0..1).
        coverage_grid: (rows, cols) bool.
        views: number of views used.
        std: 1-sigma of (fx, fy, cx, cy) in px from OpenCV's covariance.
    """

    camera: CameraModel
    rms_px: float
    per_view_rms_px: np.ndarray
    coverage: float
    coverage_grid: np.ndarray
    views: int
    std: np.ndarray

    def to_dict(self) -> dict:
        return {"format": "manisplat-intrinsics", **self.camera.to_dict(), "rms_px": self.rms_px,
                "per_view_rms_px": self.per_view_rms_px.tolist(), "coverage": self.coverage,
                "views": self.views, "std_fx_fy_cx_cy_px": self.std.tolist()}


def coverage(points: list[np.ndarray], width: int, height: int, grid: tuple[int, int] = (8, 6)) -> np.ndarray:
    """(rows, cols) bool: grid cells holding at least one of the (N, 2) pixel arrays' points."""
    cols, rows = grid
    cells = np.zeros((rows, cols), bool)
    for p in points:
        c = np.clip((p[:, 0] / width * cols).astype(int), 0, cols - 1)
        r = np.clip((p[:, 1] / height * rows).astype(int), 0, rows - 1)
        cells[r, c] = True
    return cells


def solve_intrinsics(detections: list[Detection], spec: BoardSpec, width: int, height: int, *,
                     model: str = "k1k2k3", min_coverage: float = 0.6,
                     grid: tuple[int, int] = (8, 6)) -> IntrinsicsResult:
    """``calibrateCamera`` over the detections (views with >= 8 corners).

    Raises:
        NotEnoughDataError: fewer than 6 usable views.
        CalibrationError: coverage below ``min_coverage``, or a non-finite solution.
    """
    if model not in DIST_MODELS:
        raise CalibrationError(f"distortion model must be one of {sorted(DIST_MODELS)}; got {model!r}")
    board = spec.cv_board()
    obj_all, img_all = [], []
    for d in detections:
        if len(d.ids) < MIN_CORNERS_PER_VIEW:
            continue
        if board.checkCharucoCornersCollinear(d.ids.reshape(-1, 1).astype(np.int32)):
            continue
        obj_all.append(spec.corners_3d()[d.ids].astype(np.float32).reshape(-1, 1, 3))
        img_all.append(d.corners.astype(np.float32).reshape(-1, 1, 2))
    if len(obj_all) < MIN_VIEWS:
        raise NotEnoughDataError(f"intrinsics need at least {MIN_VIEWS} views with >= {MIN_CORNERS_PER_VIEW} "
                                 f"non-collinear corners; got {len(obj_all)} of {len(detections)}")
    cells = coverage([i.reshape(-1, 2) for i in img_all], width, height, grid)
    cov = float(cells.mean())
    if cov < min_coverage:
        raise CalibrationError(f"the corners cover only {cov:.0%} of the image ({grid[0]}x{grid[1]} grid; "
                               f"need {min_coverage:.0%}): move the board into the empty regions, especially the "
                               "corners and edges, and record again")
    flags = {"none": cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
             "k1k2": cv2.CALIB_FIX_K3, "k1k2k3": 0, "rational": cv2.CALIB_RATIONAL_MODEL}[model]
    rms, K, dist, _, _, std_in, _, per_view = cv2.calibrateCameraExtended(
        obj_all, img_all, (width, height), None, None, flags=flags)
    n = DIST_MODELS[model]
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)[:n] if n else np.zeros(0)
    if not (np.isfinite(K).all() and np.isfinite(dist).all() and np.isfinite(rms)):
        raise CalibrationError("calibrateCamera returned non-finite values: the views do not constrain the camera")
    cam = CameraModel(K=K, dist=dist, width=width, height=height)
    return IntrinsicsResult(cam, float(rms), np.asarray(per_view, dtype=np.float64).reshape(-1), cov, cells,
                            len(obj_all), np.asarray(std_in, dtype=np.float64).reshape(-1)[:4])


def intrinsics_from_images(images, spec: BoardSpec, **kw) -> IntrinsicsResult:
    """Detect the board in every image (RGB or grey, same size) and :func:`solve_intrinsics`."""
    detector = BoardDetector(spec)
    dets, size = [], None
    for img in images:
        size = size or (img.shape[1], img.shape[0])
        if (img.shape[1], img.shape[0]) != size:
            raise CalibrationError(f"all images must have one size; got {img.shape[1]}x{img.shape[0]} after {size}")
        dets.append(detector.detect(img))
    if size is None:
        raise NotEnoughDataError("no images given")
    return solve_intrinsics(dets, spec, size[0], size[1], **kw)


def intrinsics_from_oak(width: int, height: int, *, calib_json: str | Path | None = None, socket: str = "CAM_A",
                        resize: str = "crop", device: str | None = None) -> CameraModel:
    """The OAK factory intrinsics at ``width`` x ``height``: from a connected device (``device``
    id or the first found) or from a calibration dump (``calib_json``,
    ``CalibrationHandler.eepromToJsonFile``). ``resize`` must match how the recording was made."""
    import depthai as dai

    from manisplat.drivers.oak import intrinsics_at
    if calib_json is not None:
        path = Path(calib_json)
        if not path.is_file():
            raise InputError(f"{path}: OAK calibration file not found")
        handler = dai.CalibrationHandler(str(path))
    else:
        from manisplat.drivers.base import DriverError
        devices = dai.Device.getAllAvailableDevices()
        if not devices and device is None:
            raise DriverError("no OAK device found (USB or network); pass --oak-json with a calibration dump instead")
        with (dai.Device(dai.DeviceInfo(device)) if device else dai.Device()) as dev:
            handler = dev.readCalibration()
    K, dist = intrinsics_at(handler, socket, width, height, resize)
    return CameraModel(K=K, dist=dist, width=width, height=height)


def load_intrinsics(path: str | Path) -> CameraModel:
    """Intrinsics from an intrinsics or calibration JSON (``K``, ``dist``, ``width``, ``height``)."""
    path = Path(path)
    raw = read_json(path, "intrinsics file")
    try:
        return CameraModel(K=raw["K"], dist=raw.get("dist", []), width=raw["width"], height=raw["height"])
    except (KeyError, TypeError) as exc:
        raise InputError(f"{path}: not an intrinsics file ({exc})") from None
    except CalibrationError as exc:
        raise InputError(f"{path}: {exc}") from None
