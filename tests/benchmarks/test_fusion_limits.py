"""benchmarks.bench_fusion_limits: the box region's error split into its outline and its inside,
the image shift that explains a misplaced render, and what a shift alone costs."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.bench_fusion_limits import SHIFTS, outline_split, psnr_of, shift_errors, shift_price, shifted


def _textured_square(offset: float = 0.0, size: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A smooth textured square (image [size, size, 3] float32 on a grey ground) drawn 4x finer and
    averaged down, moved right by ``offset`` px, and its region [size, size] bool (unmoved)."""
    fine = 4 * size
    y, x = np.mgrid[0:fine, 0:fine] / 4.0
    inside = (x - offset >= 12) & (x - offset < 28) & (y >= 12) & (y < 28)
    texture = 0.7 + 0.1 * np.sin(0.3 * (x - offset)) * np.cos(0.2 * y)
    image = np.where(inside, texture, 0.3).astype(np.float32)
    image = image.reshape(size, 4, size, 4).mean((1, 3))
    region = np.zeros((size, size), bool)
    region[12:28, 12:28] = True
    return np.repeat(image[..., None], 3, axis=-1), region


def test_a_misplaced_render_errs_on_the_outline_and_the_best_shift_finds_it():
    target, region = _textured_square()
    pred, _ = _textured_square(offset=0.5)
    parts = outline_split(pred, target, region)
    assert parts["n"] == 256 and parts["outline_n"] + parts["inside_n"] == 256 and parts["inside_n"] == 144
    outline = parts["outline_sum"] / parts["outline_n"]
    inside = parts["inside_sum"] / parts["inside_n"]
    assert outline > 3 * inside  # the square's edges carry the misplacement
    errors = shift_errors(pred, target, region)
    a, b = np.unravel_index(errors.argmin(), errors.shape)
    assert (SHIFTS[a], SHIFTS[b]) == (-0.5, 0.0)  # moved back by what it was moved
    centre = len(SHIFTS) // 2
    assert psnr_of(errors[a, b]) > psnr_of(errors[centre, centre]) + 3


def test_the_price_of_a_shift_grows_with_the_shift_and_is_nothing_without_one():
    target, region = _textured_square()
    assert shift_price(target, region, 0.0) == pytest.approx(0.0, abs=1e-12)
    assert 0 < shift_price(target, region, 0.25) < shift_price(target, region, 0.5)
    np.testing.assert_allclose(shifted(target, 0.0, 0.0), target)
