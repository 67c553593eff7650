import numpy as np
import pytest

from manisplat.calib.camera import CameraModel
from manisplat.calib.detect import BoardDetector, detector_corner_offset, require_views
from manisplat.calib.errors import NotEnoughDataError
from manisplat.calib.poses import make_T, rodrigues
from manisplat.calib.render import render_board
from manisplat.calib.synth import random_board_poses

CAM = CameraModel(K=[[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]], width=640, height=480)


def test_detector_offset_is_a_known_convention():
    chosen, measured = detector_corner_offset()
    assert chosen in (0.0, 0.5)
    assert np.all(np.abs(measured - chosen) < 0.1)


@pytest.mark.parametrize("dist", [[], [-0.15, 0.06, 0.001, -0.0008, 0.0]])
def test_corrected_corners_are_unbiased(spec, dist):
    """Renders with the true camera model (also with distortion); detection minus projection
    has no offset left (a 0.5 px convention slip would show here)."""
    cam = CameraModel(CAM.K, 640, 480, dist)
    det = BoardDetector(spec)
    rng = np.random.default_rng(3)
    errs = []
    for T in random_board_poses(spec, cam, 6, rng, dist_range=(0.35, 0.5)):
        d = det.detect(render_board(spec, cam, T, blur_sigma=0.7, noise_std=1.0, rng=rng))
        assert len(d.ids) >= 15
        errs.append(d.corners - cam.project(T, spec.corners_3d()[d.ids]))
    e = np.concatenate(errs)
    assert np.all(np.abs(e.mean(axis=0)) < 0.03)
    assert np.sqrt(np.mean(np.sum(e ** 2, axis=1))) < 0.15


def test_pnp_pose_matches_truth(spec):
    det = BoardDetector(spec)
    T = random_board_poses(spec, CAM, 1, np.random.default_rng(5), dist_range=(0.35, 0.4), min_tilt_deg=25)[0]
    view, why = det.view(0, det.detect(render_board(spec, CAM, T, blur_sigma=0.5)), CAM)
    assert view is not None, why
    dR = view.T_cam_board[:3, :3].T @ T[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.1
    assert np.linalg.norm(view.T_cam_board[:3, 3] - T[:3, 3]) < 0.5e-3


def test_board_mostly_out_of_view_is_refused_with_reason(spec):
    det = BoardDetector(spec)
    R = rodrigues([np.pi, 0, 0])
    T = make_T(R, [-0.19, 0.12, 0.4])  # board origin near the right edge: at most a few corners in view
    view, why = det.view(7, det.detect(render_board(spec, CAM, T)), CAM)
    assert view is None and "corners" in why
    with pytest.raises(NotEnoughDataError, match="frame 7"):
        require_views([], 3, {7: why}, 1)
