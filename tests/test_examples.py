"""The examples a new user runs first keep working."""

from __future__ import annotations

import runpy
from pathlib import Path

import cv2

ROOT = Path(__file__).resolve().parent.parent


def test_sample_overlay_example(tmp_path):
    module = runpy.run_path(str(ROOT / "examples" / "sample_overlay.py"))
    path = module["main"](str(tmp_path))
    sheet = cv2.imread(str(path))
    assert sheet is not None and sheet.shape[1] > sheet.shape[0]
