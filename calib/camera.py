"""The pinhole camera model shared by detection, rendering and refinement (OpenCV convention:
x right, y down, z forward; pixel centres at integer coordinates; OpenCV distortion order)."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from manisplat.calib.errors import CalibrationError

DIST_LENGTHS = (0, 4, 5, 8, 12, 14)


@dataclass(eq=False)
class CameraModel:
    """Intrinsics at one image size.

    Attributes:
        K: (3, 3) float64 pinhole matrix, pixels.
        dist: (D,) float64 OpenCV distortion coefficients, D in (0, 4, 5, 8, 12, 14).
        width, height: image size, pixels.
    """

    K: np.ndarray
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64)
        self.dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if self.K.shape != (3, 3) or not np.isfinite(self.K).all() or self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise CalibrationError(f"camera K must be a finite 3x3 matrix with positive fx, fy; got {self.K.tolist()}")
        if len(self.dist) not in DIST_LENGTHS or not np.isfinite(self.dist).all():
            raise CalibrationError(f"camera dist must have {DIST_LENGTHS} finite values; got {self.dist.tolist()}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise CalibrationError(f"camera size must be positive; got {self.width}x{self.height}")
        self.width, self.height = int(self.width), int(self.height)

    @property
    def cv_dist(self) -> np.ndarray:
        """Distortion for OpenCV calls (a 5-vector of zeros when there is none)."""
        return self.dist if len(self.dist) else np.zeros(5)

    def project(self, T_cam_obj: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(N, 2) float64 pixels of ``points`` (N, 3) in frame obj, seen with pose ``T_cam_obj`` (4, 4)."""
        rvec, _ = cv2.Rodrigues(np.asarray(T_cam_obj[:3, :3], dtype=np.float64))
        px, _ = cv2.projectPoints(np.asarray(points, dtype=np.float64).reshape(-1, 1, 3), rvec,
                                  np.asarray(T_cam_obj[:3, 3], dtype=np.float64), self.K, self.cv_dist)
        return px.reshape(-1, 2)

    def undistort_normalized(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) normalized image coordinates (x/z, y/z) of distorted ``pixels`` (N, 2)."""
        pts = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        if not len(self.dist) or not np.any(self.dist):
            Kinv = np.linalg.inv(self.K)
            h = np.concatenate([pts.reshape(-1, 2), np.ones((pts.shape[0], 1))], axis=1) @ Kinv.T
            return h[:, :2] / h[:, 2:3]
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        return cv2.undistortPointsIter(pts, self.K, self.cv_dist, None, None, crit).reshape(-1, 2)

    def to_dict(self) -> dict:
        return {"K": self.K.tolist(), "dist": self.dist.tolist(), "width": self.width, "height": self.height}
