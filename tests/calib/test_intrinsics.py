import json

import depthai as dai
import numpy as np
import pytest

from manisplat.calib.camera import CameraModel
from manisplat.calib.cli import main
from manisplat.calib.detect import BoardDetector
from manisplat.calib.errors import CalibrationError, NotEnoughDataError
from manisplat.calib.intrinsics import intrinsics_from_images, intrinsics_from_oak, solve_intrinsics
from manisplat.calib.render import render_board
from manisplat.calib.synth import random_board_poses

TRUE = CameraModel(K=[[560.0, 0, 322.0], [0, 556.0, 236.0], [0, 0, 1]], width=640, height=480,
                   dist=[-0.12, 0.05, 0.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def images(spec):
    rng = np.random.default_rng(8)
    poses = random_board_poses(spec, TRUE, 14, rng, dist_range=(0.28, 0.45), min_tilt_deg=15, max_tilt_deg=45)
    return [render_board(spec, TRUE, T, blur_sigma=0.6, noise_std=1.0, rng=rng, supersample=2) for T in poses]


def test_intrinsics_from_rendered_board_views(images, spec):
    res = intrinsics_from_images(images, spec, min_coverage=0.5)
    assert res.rms_px < 0.2
    assert np.abs(res.camera.K[[0, 1, 0, 1], [0, 1, 2, 2]] - TRUE.K[[0, 1, 0, 1], [0, 1, 2, 2]]).max() < 3.0
    assert abs(res.camera.dist[0] - TRUE.dist[0]) < 0.03
    assert 0.5 <= res.coverage <= 1.0


def test_low_coverage_and_too_few_views_are_refused(images, spec):
    det = BoardDetector(spec)
    dets = [det.detect(im) for im in images]
    for d in dets:  # keep only corners in the left half
        keep = d.corners[:, 0] < 300
        d.ids, d.corners = d.ids[keep], d.corners[keep]
    with pytest.raises(CalibrationError, match="cover only"):
        solve_intrinsics(dets, spec, 640, 480)
    with pytest.raises(NotEnoughDataError, match="at least 6 views"):
        solve_intrinsics([det.detect(im) for im in images[:3]], spec, 640, 480)


def test_oak_factory_intrinsics_from_a_calibration_dump(tmp_path):
    handler = dai.CalibrationHandler()
    handler.setCameraIntrinsics(dai.CameraBoardSocket.CAM_A, [[1000.0, 0, 960.0], [0, 1000.0, 540.0], [0, 0, 1]],
                                1920, 1080)
    handler.setDistortionCoefficients(dai.CameraBoardSocket.CAM_A, [0.1, -0.05, 0.001, 0.002, 0.01] + [0.0] * 9)
    handler.eepromToJsonFile(tmp_path / "calib.json")
    cam = intrinsics_from_oak(1280, 720, calib_json=tmp_path / "calib.json")
    assert cam.K[0, 0] == pytest.approx(1000.0 * 1280 / 1920, rel=1e-6) and cam.width == 1280
    assert len(cam.dist) == 5
    assert main(["intrinsics", "--oak-json", str(tmp_path / "calib.json"), "--width", "640", "--height", "360",
                 "--out", str(tmp_path / "k.json")]) == 0
    assert json.loads((tmp_path / "k.json").read_text())["width"] == 640
