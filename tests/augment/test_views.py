"""Views of the objects: how far a new demonstration's view of each object is from the recorded ones."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from manisplat.augment.sampling import perturb
from manisplat.augment.views import SeenViews
from manisplat.twin.rig import TwinCamera


def _camera(mount: str = "base") -> TwinCamera:
    """A 64x48 camera 1 m from the origin along -y, 0.5 m up, looking at the origin."""
    eye = np.array([0.0, -1.0, 0.5])
    z = -eye / np.linalg.norm(eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return TwinCamera("front", np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]]), 64, 48, mount, T)


def _turned(yaw_deg: float, x: float = 0.0) -> np.ndarray:
    return perturb(np.eye(4), x, 0.0, math.radians(yaw_deg))


def _twin(poses: np.ndarray, camera: TwinCamera) -> SimpleNamespace:
    return SimpleNamespace(cameras={camera.name: camera}, objects=["box"],
                           demonstrations={"ep": SimpleNamespace(object_poses={"box": poses})})


def test_a_turn_the_recording_never_showed_is_measured_and_one_it_showed_is_not():
    recorded = np.stack([_turned(yaw) for yaw in (0.0, 10.0, 20.0)])
    views = SeenViews.of(_twin(recorded, _camera()))
    assert views.change_deg({"box": recorded[[2, 0]]})["box"] == pytest.approx(0.0, abs=1e-4)
    # turned 60 deg about the vertical: 40 deg of azimuth past the nearest recorded view, seen
    # 26.6 deg below the horizon (the angle between the two directions)
    elevation = math.atan2(0.5, 1.0)
    expected = math.degrees(math.acos(math.cos(elevation) ** 2 * math.cos(math.radians(40)) + math.sin(elevation) ** 2))
    assert views.change_deg({"box": _turned(60.0)[None]})["box"] == pytest.approx(expected, abs=0.01)


def test_frames_out_of_the_image_add_no_view_and_riding_cameras_none():
    recorded = np.stack([_turned(0.0), _turned(90.0, x=5.0)])  # the turned one far outside the image
    views = SeenViews.of(_twin(recorded, _camera()))
    assert len(views.directions["box"]) == 1
    assert views.change_deg({"box": _turned(90.0)[None]})["box"] > 60
    assert SeenViews.of(_twin(recorded, _camera(mount="link6"))) is None
