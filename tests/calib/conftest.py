"""Shared synthetic data for the calibration tests (made here with the project's renderer)."""

from __future__ import annotations

import numpy as np
import pytest

from manisplat.calib.board import BoardSpec, save_board
from manisplat.calib.synth import default_truth, sample_configurations, write_calibration_episode


@pytest.fixture(scope="session")
def spec() -> BoardSpec:
    return BoardSpec()


@pytest.fixture(scope="session")
def calib_episode(tmp_path_factory, spec):
    """A 12-pose eye-to-hand episode (640x480, blur 0.6 px, grey noise 1.5) and its truth."""
    root = tmp_path_factory.mktemp("calib")
    truth = default_truth(spec)
    rng = np.random.default_rng(0)
    q = sample_configurations(spec, truth, 12, rng)
    write_calibration_episode(root / "ep", spec, truth, q, rng=rng)
    save_board(root / "board.json", spec)
    return root / "ep", root / "board.json", truth
