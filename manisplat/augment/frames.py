"""The object frame that augmented episodes report.

A reconstructed object's canonical frame has its origin wherever its first observation put it
(the centroid of the visible surface: biased towards the camera and the top, 1-2 cm from the
object's centre on the shared pick-and-place). Augmentation plans in that frame, but writes poses
(``augmentation.json`` ``T_start``/``T_end``) and reads ``--poses`` in the *centre frame*: the same
axes, the origin moved to the centre of the object's bounding box, which is what a person, a
simulator or a pose estimator means by "where the object is". Relative transforms (a segment's
``T``) are the same in either frame.
"""

from __future__ import annotations

import numpy as np
import torch

from manisplat.twin import Twin

MIN_OPACITY = 0.5  # Gaussians fainter than this do not outline the object
PERCENTILES = (1.0, 99.0)  # robust bounding box: a few stray Gaussians do not move it


def solid_points(twin: Twin, name: str) -> np.ndarray:
    """The object's Gaussian means [M, 3] float64 (object frame) of opacity >= 0.5 (all of them
    when fewer than 10 are): the object's outline, without its faint Gaussians."""
    params = twin.graph.objects[name].params
    means = params["means"].detach().double().cpu()
    solid = torch.sigmoid(params["opacities"].detach().cpu()) >= MIN_OPACITY
    return (means[solid] if int(solid.sum()) >= 10 else means).numpy()


def centre_offset(twin: Twin, name: str) -> np.ndarray:
    """[4, 4] float64 translation from the object's reconstructed frame to its centre frame: the
    centre of the bounding box of its :func:`solid_points` (1st-99th percentiles)."""
    low, high = np.percentile(solid_points(twin, name), PERCENTILES, axis=0)
    offset = np.eye(4)
    offset[:3, 3] = (low + high) / 2
    return offset


def to_centre_frame(twin: Twin, name: str, T: np.ndarray) -> np.ndarray:
    """``T_base_obj`` [..., 4, 4] in the reconstructed frame -> the centre frame."""
    return np.asarray(T, np.float64) @ centre_offset(twin, name)


def from_centre_frame(twin: Twin, name: str, T: np.ndarray) -> np.ndarray:
    """``T_base_obj`` [..., 4, 4] in the centre frame -> the reconstructed frame."""
    return np.asarray(T, np.float64) @ np.linalg.inv(centre_offset(twin, name))
