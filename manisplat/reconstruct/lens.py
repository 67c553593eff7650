"""Lens distortion removed on load: an episode whose camera reports OpenCV distortion
(``camera.dist``) is resampled to the pinhole camera with the same intrinsics ``K``, which is
what the rasterizer renders. Colour is resampled bilinearly; depth and mask labels by nearest
neighbour (a depth or a label is never averaged across an edge). Pixels whose source falls
outside the recorded image are invalid: black, depth 0, label 0, and out of every loss and metric.
"""

from __future__ import annotations

import cv2
import numpy as np


class Undistortion:
    """Resampling maps from a distorted camera to the pinhole camera with the same ``K``.

    Args:
        K: [3, 3] OpenCV intrinsics (pixel centres at integers). dist: (D,) OpenCV coefficients
            (k1, k2, p1, p2[, k3...]). width, height: image size in pixels.
    """

    def __init__(self, K: np.ndarray, dist: np.ndarray, width: int, height: int) -> None:
        K = np.asarray(K, dtype=np.float64)
        dist = np.asarray(dist, dtype=np.float64)
        self.map_x, self.map_y = cv2.initUndistortRectifyMap(K, dist, None, K, (width, height), cv2.CV_32FC1)
        if not (np.isfinite(self.map_x).all() and np.isfinite(self.map_y).all()):
            raise ValueError(f"camera.dist {dist.tolist()} gives no finite undistortion map for K {K.tolist()}")
        inside = ((self.map_x >= -0.5) & (self.map_x <= width - 0.5)
                  & (self.map_y >= -0.5) & (self.map_y <= height - 0.5))
        #: [H, W] bool: the pinhole pixels the recorded image covers
        self.valid: np.ndarray = inside
        self.shift_px = float(np.max(np.hypot(self.map_x - np.arange(width)[None], self.map_y - np.arange(height)[:, None])))

    @property
    def valid_fraction(self) -> float:
        return float(self.valid.mean())

    def rgb(self, image: np.ndarray) -> np.ndarray:
        """[H, W, 3] uint8, bilinear; invalid pixels black."""
        out = cv2.remap(image, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out[~self.valid] = 0
        return out

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """[H, W] float32 z-depth (m, 0 invalid), nearest neighbour (z along the axis is unchanged)."""
        return self._nearest(depth)

    def labels(self, mask: np.ndarray) -> np.ndarray:
        """[H, W] uint8 labels, nearest neighbour; invalid pixels 0."""
        return self._nearest(mask)

    def _nearest(self, image: np.ndarray) -> np.ndarray:
        out = cv2.remap(image, self.map_x, self.map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        out[~self.valid] = 0
        return out


def undistortion_for(K: np.ndarray, dist: np.ndarray, width: int, height: int) -> Undistortion | None:
    """The :class:`Undistortion` of a camera, or None for a pinhole one (no or all-zero ``dist``)."""
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    if dist.size == 0 or not np.any(dist != 0):
        return None
    return Undistortion(K, dist, width, height)


__all__ = ["Undistortion", "undistortion_for"]
