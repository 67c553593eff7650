"""Image panels side by side under a header that names each one (contact sheets, videos)."""

from __future__ import annotations

import cv2
import numpy as np


def labelled_sheet(sheet: np.ndarray, columns: tuple[str, ...], caption: str) -> np.ndarray:
    """``sheet`` [H, W, 3] uint8 (equal-width panels side by side) under a header strip naming each
    panel, the caption (frame number, time) in its first panel."""
    height, width = sheet.shape[:2]
    panel = width // len(columns)
    scale = max(0.3, min(0.6, panel / 400))
    line = int(round(22 * scale / 0.4))
    header = np.full((2 * line, width, 3), 255, np.uint8)
    for k, name in enumerate(columns):
        cv2.putText(header, name, (k * panel + 4, line - 6), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(header, caption, (4, 2 * line - 6), cv2.FONT_HERSHEY_SIMPLEX, scale, (90, 90, 90), 1, cv2.LINE_AA)
    return np.concatenate([header, sheet], axis=0)
