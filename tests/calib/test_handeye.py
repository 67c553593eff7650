import numpy as np
import pytest

from manisplat.calib.detect import BoardDetector
from manisplat.calib.errors import DegenerateMotionError, NotEnoughDataError
from manisplat.calib.handeye import (_check_result, check_motion, closed_form, opencv_closed_forms, to_problem)
from manisplat.calib.poses import inv_T, make_T, pose_difference, rodrigues
from manisplat.calib.render import render_board
from manisplat.calib.solve import solve_hand_eye
from manisplat.calib.synth import default_scene, random_board_poses, robot_poses_for


def _exact(spec, mount, n=8, seed=0):
    rng = np.random.default_rng(seed)
    sc = default_scene(rng)
    Tcb = random_board_poses(spec, sc.camera, n, rng)
    if mount == "base":
        return sc, robot_poses_for(sc, Tcb), Tcb, sc.T_base_cam, sc.T_link_board
    # eye-in-hand: camera on the link (T_link_cam), board fixed in the base
    T_link_cam = make_T(rodrigues([0.1, -0.2, 0.3]), [0.05, 0.0, 0.08])
    T_base_board = make_T(rodrigues([np.pi, 0, 0.4]), [0.3, 0.05, 0.0])
    A = T_base_board @ inv_T(Tcb) @ inv_T(T_link_cam)
    return sc, A, Tcb, T_link_cam, T_base_board


@pytest.mark.parametrize("mount", ["base", "link6"])
def test_closed_forms_are_exact_without_noise(spec, mount):
    sc, A, Tcb, T_mount_cam, T_other = _exact(spec, mount)
    Ap, B = to_problem(mount, A, Tcb)
    P, Q = closed_form(Ap, B)
    Tm = Q if mount == "base" else P
    assert max(pose_difference(Tm, T_mount_cam)) < 1e-6
    for name, res in opencv_closed_forms(mount, A, Tcb).items():
        assert not isinstance(res, str), f"{name}: {res}"
        Tm = res[1] if mount == "base" else res[0]
        rot, trans = pose_difference(Tm, T_mount_cam)
        assert rot < 1e-4 and trans < 1e-3, name


def test_opencv_identity_and_nan_are_refused():
    A = np.stack([make_T(np.eye(3), [0.3, 0, 0.2])] * 3)
    assert "identity" in _check_result("TSAI", np.eye(4), A)
    assert "NaN" in _check_result("PARK", np.full((4, 4), np.nan), A)


def test_single_axis_motion_is_degenerate():
    R0 = rodrigues([0.3, -0.2, 0.1])
    A = np.stack([make_T(R0 @ rodrigues([0, 0, th]), [0.3 + 0.01 * k, 0.0, 0.2]) for k, th in
                  enumerate(np.radians([-40, -20, 0, 20, 40]))])
    with pytest.raises(DegenerateMotionError, match="one axis"):
        check_motion(A)
    small = np.stack([make_T(rodrigues(np.radians([k, -k, 0.5 * k])), [0.3, 0, 0.2]) for k in range(4)])
    with pytest.raises(DegenerateMotionError, match="barely rotates"):
        check_motion(small)
    with pytest.raises(NotEnoughDataError):
        check_motion(A[:2])


def _views(spec, sc, Tcb, rng, noise_px=0.2):
    det = BoardDetector(spec)
    views = []
    for k, T in enumerate(Tcb):
        d = det.detect(render_board(spec, sc.camera, T, blur_sigma=0.8, noise_std=2.0, rng=rng))
        d.corners = d.corners + rng.normal(0, noise_px, d.corners.shape)
        v, why = det.view(k, d, sc.camera)
        assert v is not None, why
        views.append(v)
    return views


def test_refinement_meets_the_goal_and_beats_opencv(spec):
    rng = np.random.default_rng(11)
    sc = default_scene(rng)
    Tcb = random_board_poses(spec, sc.camera, 15, rng)
    views = _views(spec, sc, Tcb, rng)
    r = solve_hand_eye(views, robot_poses_for(sc, Tcb), spec, sc.camera)
    rot, trans = pose_difference(r.T_mount_cam, sc.T_base_cam)
    assert rot < 0.05 and trans < 0.5
    closed_forms = opencv_closed_forms("base", robot_poses_for(sc, Tcb), np.stack([v.T_cam_board for v in views]))
    best_cf = min(pose_difference(closed_forms[m][1], sc.T_base_cam)[1] for m in ("TSAI", "PARK", "SHAH"))
    assert trans < best_cf
    u = r.uncertainty()
    assert 0 < u["T_mount_cam_trans_std_mm"] < 0.5 and 0 < u["T_mount_cam_rot_std_deg"] < 0.05
    assert 0.1 < u["corner_sigma_px"] < 0.4  # 0.2 px added + the detector's own error


def test_a_mispaired_view_is_dropped(spec):
    rng = np.random.default_rng(12)
    sc = default_scene(rng)
    Tcb = random_board_poses(spec, sc.camera, 12, rng)
    views = _views(spec, sc, Tcb, rng, noise_px=0.1)
    A = robot_poses_for(sc, Tcb)
    A[4] = A[4] @ make_T(rodrigues([0.0, 0.0, np.radians(8)]), [0.02, 0, 0])  # the joints of another pose
    r = solve_hand_eye(views, A, spec, sc.camera)
    assert not r.refine.view_used[4] and r.refine.view_used.sum() == 11
    rot, trans = pose_difference(r.T_mount_cam, sc.T_base_cam)
    assert rot < 0.05 and trans < 0.5


def test_too_few_views(spec):
    rng = np.random.default_rng(1)
    sc = default_scene(rng)
    Tcb = random_board_poses(spec, sc.camera, 2, rng)
    views = _views(spec, sc, Tcb, rng)
    with pytest.raises(NotEnoughDataError, match="at least 3"):
        solve_hand_eye(views, robot_poses_for(sc, Tcb), spec, sc.camera)


def test_eye_in_hand_refinement(spec):
    """Camera on link6, board fixed in the base: T_link_cam and T_base_board both recovered."""
    sc, A, Tcb, T_link_cam, T_base_board = _exact(spec, "link6", n=12, seed=4)
    rng = np.random.default_rng(4)
    views = _views(spec, sc, Tcb, rng)
    r = solve_hand_eye(views, A, spec, sc.camera, mount="link6", link="link6")
    rot, trans = pose_difference(r.T_mount_cam, T_link_cam)
    assert rot < 0.05 and trans < 0.5
    rot_b, trans_b = pose_difference(r.T_other, T_base_board)
    assert rot_b < 0.1 and trans_b < 1.0
