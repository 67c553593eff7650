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


def test_fit_image_example(tmp_path):
    from manisplat.splat import load_ply

    module = runpy.run_path(str(ROOT / "examples" / "fit_image.py"))
    result = module["main"](str(tmp_path), steps=120)
    assert result["psnr"] > 25.0 and result["gaussians"] > 2000  # densified and fitting
    assert len(load_ply(tmp_path / "fit.ply")["means"]) == result["gaussians"]
