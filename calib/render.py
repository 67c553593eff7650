"""The project's own renderer of board views: the printed ChArUco sheet seen through a camera
model (distortion included), for benchmarks, tests and synthetic episodes. No MuJoCo.

Each output pixel is the mean of ``supersample`` x ``supersample`` sub-pixel rays (OpenCV's
pixel-centre convention: sub-pixel ``(a, b)`` of pixel ``(u, v)`` is at ``u + (a + 0.5)/S - 0.5``);
every ray is undistorted, intersected with the board plane and samples the board drawing
bilinearly. Then optional Gaussian blur and Gaussian grey-level noise.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from manisplat.calib.board import BoardSpec
from manisplat.calib.camera import CameraModel
from manisplat.calib.errors import CalibrationError

SHEET_MARGIN_SQUARES = 0.5
"""White paper margin around the pattern, in squares."""


@functools.lru_cache(maxsize=16)
def _texture(spec: BoardSpec, px_per_square: int) -> tuple[np.ndarray, int]:
    margin = int(round(SHEET_MARGIN_SQUARES * px_per_square))
    return spec.pattern_image(px_per_square, margin).astype(np.float32), margin


_RAY_CACHE: dict[tuple, np.ndarray] = {}


def _rays(camera: CameraModel, supersample: int) -> np.ndarray:
    """(H*S, W*S, 2) float64 normalized undistorted coordinates of every sub-pixel."""
    key = (camera.K.tobytes(), camera.dist.tobytes(), camera.width, camera.height, supersample)
    if key not in _RAY_CACHE:
        S = supersample
        xs = (np.arange(camera.width * S) + 0.5) / S - 0.5
        ys = (np.arange(camera.height * S) + 0.5) / S - 0.5
        grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
        _RAY_CACHE.clear() if len(_RAY_CACHE) > 4 else None
        _RAY_CACHE[key] = camera.undistort_normalized(grid).reshape(camera.height * S, camera.width * S, 2).astype(np.float32)
    return _RAY_CACHE[key]


def render_board(spec: BoardSpec, camera: CameraModel, T_cam_board: np.ndarray, *, supersample: int = 3,
                 blur_sigma: float = 0.0, noise_std: float = 0.0, background: float | np.ndarray = 96.0,
                 rng: np.random.Generator | None = None) -> np.ndarray:
    """(H, W) uint8 grey image of the board at pose ``T_cam_board`` (4, 4, metres).

    Args:
        supersample: sub-pixels per pixel side (box filter; exact for the pixel-centre convention).
        blur_sigma: Gaussian blur sigma in output pixels (0: none).
        noise_std: Gaussian grey-level noise (0..255 scale).
        background: grey level, or an (H, W) image behind the sheet.
        rng: random source for the noise.
    Raises:
        CalibrationError: on a non-finite pose or a board behind the camera.
    """
    T = np.asarray(T_cam_board, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise CalibrationError("render_board: T_cam_board must be a finite 4x4 matrix")
    if T[2, 3] <= 0:
        raise CalibrationError(f"render_board: the board origin is behind the camera (z = {T[2, 3]:.3f} m)")
    m = SHEET_MARGIN_SQUARES * spec.square_length_m
    w_m, h_m = spec.size_m
    sheet_corners = np.array([[-m, -m, 0, 1], [w_m + m, -m, 0, 1], [-m, h_m + m, 0, 1], [w_m + m, h_m + m, 0, 1]])
    if ((sheet_corners @ T.T)[:, 2] <= 1e-3).any():
        raise CalibrationError("render_board: part of the sheet is behind the camera")
    S = int(supersample)
    H = np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]])  # board (X, Y, 1) -> camera ray
    # texture resolution ~ the finest sub-pixel footprint of a square
    depth = max(float(T[2, 3]) - 0.5 * max(spec.size_m), 0.05)
    pps = int(np.clip(round(camera.K[0, 0] * spec.square_length_m / depth * S), 16, 480))
    tex, margin = _texture(spec, pps)
    scale = pps / spec.square_length_m
    # texture pixel (u, v) centre <-> board (X, Y) = ((u - margin + 0.5) / scale, ...)
    tex_to_board = np.array([[1 / scale, 0, (0.5 - margin) / scale], [0, 1 / scale, (0.5 - margin) / scale], [0, 0, 1]])
    size = (camera.width * S, camera.height * S)
    const_bg = not isinstance(background, np.ndarray)
    bg_level = float(background) if const_bg else 0.0
    sees_front = (-(T[:3, :3].T @ T[:3, 3]))[2] < 0  # camera on the printed (-z) side
    # warp (sheet - background) with a zero border, so the sheet edge blends exactly
    layer = (tex if sees_front else np.full_like(tex, 200.0)) - np.float32(bg_level)
    if not len(camera.dist) or not np.any(camera.dist):
        # no distortion: one homography texture -> sub-pixel grid (x_s = S x + (S - 1) / 2)
        up = np.array([[S, 0, (S - 1) / 2], [0, S, (S - 1) / 2], [0, 0, 1]])
        Hs = up @ camera.K @ H @ tex_to_board

        def sample(src: np.ndarray) -> np.ndarray:
            return cv2.warpPerspective(src, Hs, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                       borderValue=0.0)
    else:
        rays = _rays(camera, S)
        Hinv = (np.linalg.inv(tex_to_board) @ np.linalg.inv(H)).astype(np.float32)
        v = rays[..., 0:1] * Hinv[:, 0] + rays[..., 1:2] * Hinv[:, 1] + Hinv[:, 2]  # [HS, WS, 3] texture coords
        valid = v[..., 2] > 0
        w = np.where(valid, v[..., 2], np.float32(1.0))
        mapx = np.where(valid, v[..., 0] / w, np.float32(-1e6))
        mapy = np.where(valid, v[..., 1] / w, np.float32(-1e6))

        def sample(src: np.ndarray) -> np.ndarray:
            return cv2.remap(src, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    img = sample(layer)
    if const_bg:
        img += np.float32(bg_level)
    else:
        bg = np.asarray(background, dtype=np.float32)
        if bg.shape != (camera.height, camera.width):
            raise CalibrationError(f"render_board: background must be {(camera.height, camera.width)}; got {bg.shape}")
        inside = sample(np.ones_like(tex))
        img = img + cv2.resize(bg, size, interpolation=cv2.INTER_NEAREST) * (1.0 - inside)
    img = cv2.resize(img, (camera.width, camera.height), interpolation=cv2.INTER_AREA) if S > 1 else img
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    if noise_std > 0:
        rng = rng if rng is not None else np.random.default_rng()
        img = img + rng.normal(0.0, noise_std, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
