"""Hybrid pseudo ground truth: the gripper prior, tracking overrides, and the tracker itself on
a synthetic textured plane with known motion."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from manisplat.align.phases import GripperEvents, Segment
from manisplat.align.pseudo_gt import (ATTACHED, MAX_REST_SHIFT, MAX_REST_TILT_DEG, STATIC, TRACKED, close_end,
                                      follow_slip, hybrid_pseudo_poses, kinematic_prior, noise_floor, open_end,
                                      pad_push, rest_on_support, settle_at_rest)
from manisplat.align.surface_fit import MAX_VIEW_CHANGE_DEG, ModelViews, SurfaceModel
from manisplat.align.tracking import DepthEvidence, TrackerSettings, track_object
from manisplat.geometry import so3_exp


def tcp_track(T=60):
    poses = np.repeat(np.eye(4)[None], T, axis=0)
    poses[:, 0, 3] = np.linspace(0.0, 0.3, T)
    poses[:, 2, 3] = 0.2
    return poses


def test_kinematic_prior_rests_then_follows_the_gripper_then_rests():
    tcp = tcp_track()
    start = np.eye(4)
    start[:3, 3] = [0.1, 0.0, 0.0]
    poses, held = kinematic_prior(start, tcp, [GripperEvents(grasp=20, release=40)])
    assert np.allclose(poses[:20], start) and not held[:20].any() and held[20:40].all()
    rel = np.linalg.inv(tcp[20]) @ start
    assert np.allclose(poses[20:40], tcp[20:40] @ rel)
    assert np.allclose(poses[40:], poses[39]) and not held[40:].any()


def segments():
    return [Segment("motion", "M_approach", 0, 15), Segment("skill", "S_pick", 15, 25),
            Segment("motion", "M_transfer", 25, 35), Segment("skill", "S_place", 35, 45),
            Segment("motion", "M_return", 45, 60)]


def test_hybrid_follows_the_prior_when_tracking_agrees():
    tcp = tcp_track()
    start = np.eye(4)
    calls = []

    def agreeing_tracker(frames, T_first, prior):
        calls.append((frames.start, frames.stop))
        return prior, np.zeros(len(frames), dtype=bool)

    pseudo = hybrid_pseudo_poses(segments(), start, tcp, [GripperEvents(20, 40)], agreeing_tracker)
    expected, _ = kinematic_prior(start, tcp, [GripperEvents(20, 40)])
    assert np.allclose(pseudo.poses, expected)
    assert pseudo.source[:15] == [STATIC] * 15 and pseudo.source[15:25] == [TRACKED] * 10
    assert pseudo.source[25:35] == [ATTACHED] * 10 and pseudo.source[45:] == [STATIC] * 15
    assert calls == [(14, 25), (34, 45)]  # skills start from the previous frame's pose


def textured_plane_episode(T=12, size=(160, 120), degrees_per_frame=0.7):
    """A 10 cm textured square 0.6 m in front of a camera, translating and turning: images,
    masks, depth and the true T_cam_obj poses (base = camera frame here)."""
    W, H = size
    K = np.array([[200.0, 0, W / 2 - 0.5], [0, 200.0, H / 2 - 0.5], [0, 0, 1]])
    rng = np.random.default_rng(0)
    texture = cv2.resize(rng.integers(0, 255, (32, 32), dtype=np.uint8), (256, 256), interpolation=cv2.INTER_CUBIC)
    poses, grays, masks, depths = [], [], [], []
    for k in range(T):
        angle = np.radians(degrees_per_frame * k)
        c, s = np.cos(angle), np.sin(angle)
        T_co = np.eye(4)
        T_co[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        T_co[:3, 3] = [0.004 * k, -0.003 * k, 0.6]
        corners = np.array([[-0.05, -0.05, 0], [0.05, -0.05, 0], [0.05, 0.05, 0], [-0.05, 0.05, 0]])
        cam = corners @ T_co[:3, :3].T + T_co[:3, 3]
        px = (cam @ K.T)[:, :2] / cam[:, 2:3]
        Hm = cv2.getPerspectiveTransform(np.float32([[0, 0], [255, 0], [255, 255], [0, 255]]), np.float32(px))
        gray = cv2.warpPerspective(texture, Hm, (W, H))
        mask = cv2.warpPerspective(np.full((256, 256), 255, np.uint8), Hm, (W, H)) > 127
        poses.append(T_co)
        grays.append(gray)
        masks.append(mask)
        depths.append(np.where(mask, 0.6, 0.0).astype(np.float32))  # fronto-parallel: z is constant
    return K, np.stack(poses), grays, masks, depths


def test_tracker_recovers_a_moving_textured_plane():
    K, truth, grays, masks, depths = textured_plane_episode()
    track = track_object(lambda i: grays[i], lambda i: masks[i], lambda i: depths[i], K, np.eye(4),
                         range(len(truth)), truth[0], TrackerSettings(confident_inliers=10))
    assert track.solved.all()
    err = np.linalg.norm(track.poses[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert err.max() < 0.002  # 2 mm
    angle = np.degrees(np.arccos(np.clip((np.einsum("nii->n", track.poses[:, :3, :3].transpose(0, 2, 1) @ truth[:, :3, :3]) - 1) / 2, -1, 1)))
    assert angle.max() < 0.1 * 7.7  # within 10 % of the 7.7 deg turn (LK under-reads sub-pixel rotation, ~7 %)


def test_tracker_lag_on_fast_rotation_is_bounded():
    K, truth, grays, masks, depths = textured_plane_episode(degrees_per_frame=2.0)
    track = track_object(lambda i: grays[i], lambda i: masks[i], lambda i: depths[i], K, np.eye(4),
                         range(len(truth)), truth[0], TrackerSettings(confident_inliers=10))
    final = np.degrees(np.arccos(np.clip((np.trace(track.poses[-1, :3, :3].T @ truth[-1, :3, :3]) - 1) / 2, -1, 1)))
    assert final < 0.1 * 22.0  # under 10 % of the 22 deg turn (measured about 7 %)


def test_tracker_overrides_a_wrong_prior_only_when_the_evidence_persists():
    K, truth, grays, masks, depths = textured_plane_episode()
    static_prior = np.repeat(truth[:1], len(truth), axis=0)  # a prior that says "it does not move"
    settings = TrackerSettings(confident_inliers=10, persistence=3)
    track = track_object(lambda i: grays[i], lambda i: masks[i], lambda i: depths[i], K, np.eye(4),
                         range(len(truth)), truth[0], settings, prior=static_prior)
    assert track.from_tracking.any()
    first = int(np.argmax(track.from_tracking))
    assert first >= settings.persistence  # not on the first disagreement
    assert track.from_tracking[first:].all()  # and keeps following while confident
    assert np.linalg.norm(track.poses[-1, :3, 3] - truth[-1, :3, 3]) < 0.002  # follows the real motion


def test_tracker_refuses_an_override_the_depth_does_not_back():
    """Tracks dragged across a still object (the texture slides, as under closing fingers) while
    its mask and depth stay put: confident, persistent, and wrong; the prior must stand."""
    K, truth, grays, masks, depths = textured_plane_episode(degrees_per_frame=0.0)
    still = np.repeat(truth[:1], len(truth), axis=0)
    mask0, depth0 = masks[0], depths[0]
    settings = TrackerSettings(confident_inliers=10, persistence=3)
    track = track_object(lambda i: grays[i], lambda i: mask0, lambda i: depth0, K, np.eye(4),
                         range(len(truth)), truth[0], settings, prior=still)
    assert not track.from_tracking.any()
    assert np.allclose(track.poses, still)


def test_depth_evidence_with_the_object_model_prefers_the_true_pose_over_one_covering_unseen_surface():
    """Fingers hid half the object where tracking started; once they open, the model (the half seen
    then) fits a pose slid over the revealed half better than the true one, unless the object's
    model points (seen whole in another frame) complete it."""
    K, truth, grays, masks, depths = textured_plane_episode(T=1)
    W = masks[0].shape[1]
    half = masks[0].copy()
    half[:, W // 2:] = False  # the right half hidden when tracking started
    whole = DepthEvidence(masks[0], depths[0], K, np.eye(4), truth[0])
    model_points = (whole.surface(masks[0], depths[0]) - truth[0][:3, 3]) @ truth[0][:3, :3]  # object frame
    revealed = whole.surface(masks[0], depths[0])  # the surface once the fingers open
    slid = truth[0].copy()
    slid[0, 3] += 0.015  # towards the revealed half, by a whole number of the 3 mm point spacing
    seen_half = DepthEvidence(half, depths[0], K, np.eye(4), truth[0])
    assert seen_half.misfit(revealed, slid) < seen_half.misfit(revealed, truth[0]) - 0.0003  # the failure
    completed = DepthEvidence(half, depths[0], K, np.eye(4), truth[0], model_points=model_points)
    assert completed.misfit(revealed, truth[0]) < 1e-4
    assert completed.misfit(revealed, slid) > completed.misfit(revealed, truth[0]) + 0.0005


def box_points(size=(0.04, 0.04, 0.05), n=12):
    """Surface points [M, 3] of a box centred on its frame's origin."""
    axes = [np.linspace(-s / 2, s / 2, n) for s in size]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    on_face = (np.abs(np.abs(grid) - np.array(size) / 2) < 1e-9).any(-1)
    return grid[on_face]


def test_grasp_centres_the_object_between_the_pads():
    tcp = tcp_track()
    width = np.full(60, 0.04)  # the pads stopped on the box's 4 cm
    start = np.eye(4)
    start[:3, 3] = tcp[20, :3, 3] + [0.0, 0.004, 0.0]  # 4 mm off the pads' centre along TCP y
    poses, _ = kinematic_prior(start, tcp, [GripperEvents(20, None)], model_points=box_points(), width=width)
    assert np.allclose(poses[19], start)  # at rest until the grasp
    assert np.allclose(poses[20:, :3, 3], tcp[20:, :3, 3], atol=1e-9)  # centred, then carried
    far = start.copy()
    far[1, 3] += 0.03  # 3.4 cm off: not between the pads, no centring
    poses, _ = kinematic_prior(far, tcp, [GripperEvents(20, None)], model_points=box_points(), width=width)
    assert np.allclose(poses[20], far)


def test_no_centring_from_a_model_that_shows_one_side_the_pads_touch():
    """The box seen from its +y side only (its -y half hidden, as a camera looking along the
    closing axis sees it): the middle of what is seen is 1 cm off the box's centre, and the
    grasp is kept as seen; without the opening nothing checks the model, and it is kept too."""
    tcp = tcp_track()
    start = np.eye(4)
    start[:3, 3] = tcp[20, :3, 3] + [0.0, 0.004, 0.0]
    near_half = box_points()[box_points()[:, 1] >= 0]
    poses, _ = kinematic_prior(start, tcp, [GripperEvents(20, None)], model_points=near_half,
                               width=np.full(60, 0.04))
    assert np.allclose(poses[20:, :3, 3], tcp[20:, :3, 3] + [0.0, 0.004, 0.0], atol=1e-9)
    poses, _ = kinematic_prior(start, tcp, [GripperEvents(20, None)], model_points=box_points())
    assert np.allclose(poses[20:, :3, 3], tcp[20:, :3, 3] + [0.0, 0.004, 0.0], atol=1e-9)


def test_the_object_rests_while_the_pads_close_and_is_held_centred_once_they_stop():
    """Closing from 7 to 4 cm over frames 20-26 on a 4 cm box 4 mm off the pads' midplane while
    the arm yields 1 mm towards it: the box stays put until the nearer pad reaches it (frame 25,
    when the pads are 5 mm wider than the box: 0.5 mm of the 3 mm still to go), is pushed the
    rest of the way, and is carried from frame 26, centred at that frame's TCP."""
    tcp = tcp_track()
    tcp[20:26, 1, 3] = np.linspace(0.0, 0.001, 6)  # the TCP drifts 1 mm along y during the close
    tcp[26:, 1, 3] = 0.001
    tcp[20:27, 0, 3] = tcp[20, 0, 3]  # and stands still along x meanwhile
    width = np.full(60, 0.07)
    width[20:27] = np.linspace(0.07, 0.04, 7)  # opening (m): the pads stop at the box's 4 cm
    width[27:] = 0.04
    start = np.eye(4)
    start[:3, 3] = tcp[20, :3, 3] + [0.0, 0.004, 0.0]
    poses, held = kinematic_prior(start, tcp, [GripperEvents(20, None)], model_points=box_points(), width=width)
    assert np.allclose(poses[:25], start)  # the pads are still wider than box + offset
    assert not held[:26].any() and held[26:].all()
    assert poses[25, 1, 3] == pytest.approx(0.0035) and poses[25, 0, 3] == start[0, 3]  # pushed along y only
    assert np.allclose(poses[26:, :3, 3], tcp[26:, :3, 3], atol=1e-9)  # centred at frame 26's TCP, carried


def test_pad_push_and_close_end():
    assert pad_push(0.004, 0.02) == 0.0 and pad_push(-0.004, 0.0) == -0.004
    assert pad_push(0.004, 0.004) == pytest.approx(0.002)
    width = np.array([0.07, 0.07, 0.06, 0.05, 0.0401, 0.0400, 0.0400, 0.05])
    assert close_end(width, 1) == 4  # 0.1 mm to the next frame: stopped
    assert close_end(width, 1, release=3) == 2


def rotation_x(deg):
    a = np.radians(deg)
    R = np.eye(4)
    R[1:3, 1:3] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return R


def test_release_settles_a_small_tilt_but_not_a_reorientation():
    tcp = tcp_track()
    start = np.eye(4)
    start[:3, 3] = tcp[20, :3, 3]
    for tilt, settles in ((3.0, True), (25.0, False)):
        slipped = tcp.copy()
        slipped[25:] = slipped[25:] @ rotation_x(tilt)  # the hand turns the object by ``tilt``
        poses, _ = kinematic_prior(start, slipped, [GripperEvents(20, 40)], model_points=box_points())
        final = poses[-1]
        up_angle = np.degrees(np.arccos(np.clip(final[2, 2], -1, 1)))
        if settles:
            assert up_angle < 1e-6
            centre = final[:3, 3]  # the model's centre is the frame's origin: it stays where it was let go
            assert np.allclose(centre, poses[39, :3, 3], atol=1e-9)
        else:
            assert abs(up_angle - tilt) < 1e-6


def test_an_object_never_released_stays_in_the_hand():
    """Pick-and-hold: the grasp has no release; every later segment carries the object."""
    tcp = tcp_track()
    start = np.eye(4)
    start[:3, 3] = tcp[20, :3, 3]
    segs = [Segment("motion", "M_approach", 0, 15), Segment("skill", "S_pick", 15, 25),
            Segment("motion", "M_transfer", 25, 60)]

    def agreeing_tracker(frames, T_first, prior):
        return prior, np.zeros(len(frames), dtype=bool)

    pseudo = hybrid_pseudo_poses(segs, start, tcp, [GripperEvents(20, None)], agreeing_tracker)
    assert np.allclose(pseudo.poses[20:, :3, 3], tcp[20:, :3, 3])
    assert pseudo.source[25:] == [ATTACHED] * 35


def visible_box_surface(pose, size=(0.04, 0.04, 0.05), n=2000, seed=1):
    """Random points [n, 3] (base frame) on the faces a camera above and to the +x, -y side sees
    (top, +x, -y) of a box at ``pose``: another sampling than the model's grid."""
    rng = np.random.default_rng(seed)
    half = np.array(size) / 2
    points = rng.uniform(-half, half, (n, 3))
    face = rng.integers(0, 3, n)
    points[face == 0, 2] = half[2]
    points[face == 1, 0] = half[0]
    points[face == 2, 1] = -half[1]
    return points @ pose[:3, :3].T + pose[:3, 3]


def test_the_shift_fit_finds_where_the_object_came_to_rest():
    model = box_points(n=41)  # about 1 mm spacing
    prior = np.eye(4)
    prior[:3, 3] = [0.3, 0.1, 0.025]
    rest = prior.copy()
    rest[:3, 3] += [0.002, -0.003, -0.0025]  # slipped in the hand and dropped onto its support
    surfaces = [visible_box_surface(rest, seed=k) for k in range(3)]
    shift, before, after = SurfaceModel(model).fit_shift(surfaces, [prior] * 3)
    assert np.linalg.norm(shift - [0.002, -0.003, -0.0025]) < 3e-4  # 0.3 mm: the model's 1 mm grid
    assert after < 0.5 * before


def test_a_side_the_model_lacks_does_not_pull_the_shift_fit_to_its_edge():
    """The model is what the first view saw (top, +x and -y faces); after the release the camera
    sees the top, +x and the +y face instead, which the model lacks. At the true pose the fit must
    stay put: matched to the nearest model point alone, the +y face's points pull the model towards
    +y and down, onto the edge of the top (1.4 mm here)."""
    model = box_points(n=41)
    seen_first = (model[:, 2] > 0.0249) | (model[:, 0] > 0.0199) | (model[:, 1] < -0.0199)
    rest = np.eye(4)
    rest[:3, 3] = [0.3, 0.1, 0.025]
    turned_view = visible_box_surface(rest, seed=5)
    on_minus_y = np.abs(turned_view[:, 1] - rest[1, 3] + 0.02) < 1e-9
    turned_view[on_minus_y, 1] += 0.04  # the -y face's points moved onto the +y face
    shift, before, after = SurfaceModel(model[seen_first]).fit_shift([turned_view], [rest])
    assert np.linalg.norm(shift) < 3e-4 and after <= before + 1e-6


def test_settle_at_rest_moves_the_frames_after_the_release_and_learns_nothing_from_held_out_ones():
    model = box_points(n=41)
    T = 30
    poses = np.repeat(np.eye(4)[None], T, axis=0)
    poses[:, :3, 3] = [0.3, 0.1, 0.025]
    true_shift = np.array([0.001, 0.002, -0.002])
    width = np.full(T, 0.07)
    width[18:21] = [0.045, 0.055, 0.065]  # opens over frames 18-21 after the release at 18

    def surface(f):
        truth = poses[f].copy()
        truth[:3, 3] += true_shift
        if f == 25:  # a held-out frame whose depth says something else entirely
            truth[:3, 3] += [0.006, 0.0, 0.0]
        return visible_box_surface(truth, seed=f)

    assert open_end(width, 18, T) == 21
    settled = poses.copy()
    shifts = settle_at_rest(settled, [GripperEvents(5, 18)], surface, model, width, observe=frozenset({25}))
    assert len(shifts) == 1 and np.linalg.norm(shifts[0] - true_shift) < 3e-4
    assert np.allclose(settled[:18], poses[:18]) and np.allclose(settled[18:, :3, 3], poses[18:, :3, 3] + shifts[0])
    # a shift beyond MAX_REST_SHIFT is not a settle: the prior stands
    far = lambda f: visible_box_surface(poses[f] @ _translation([MAX_REST_SHIFT * 0.9] * 3), seed=f)  # noqa: E731
    kept = poses.copy()
    assert settle_at_rest(kept, [GripperEvents(5, 18)], far, model, width) == [] and np.allclose(kept, poses)


def test_a_released_object_stands_on_the_support_under_it_as_it_stood_at_the_start():
    """The box starts on the table (support 0) and is carried onto a 5 mm mat, 3 mm too high (it
    sagged in the hand): its rest comes down 3 mm, though the depth reads both supports 1 mm low.
    The start's support is read from the release on, the mat's before the grasp, neither in a
    held-out frame."""
    model = box_points(n=21)
    T = 40
    poses = np.repeat(np.eye(4)[None], T, axis=0)
    poses[:, :3, 3] = [0.3, -0.1, 0.025]  # its lowest points on the table
    poses[10:25, :3, 3] = [0.32, 0.0, 0.1]  # carried
    poses[25:, :3, 3] = [0.32, 0.06, 0.033]  # released 3 mm above the mat
    read = []

    def support(hull_xy, z_low, frames):
        read.append((np.round(hull_xy.mean(0), 3).tolist(), frames))
        return -0.001 if hull_xy.mean(0)[1] < -0.05 else 0.004

    rested = poses.copy()
    heights = rest_on_support(rested, [GripperEvents(10, 25)], support, model, observe=frozenset({3, 30}))
    assert heights == [pytest.approx(-0.003)]
    assert np.allclose(rested[:25], poses[:25]) and np.allclose(rested[25:, 2, 3], 0.030)
    (start_xy, after_release), (rest_xy, before_grasp) = read
    assert start_xy == [0.3, -0.1] and after_release == [f for f in range(25, T) if f != 30]
    assert rest_xy == [0.32, 0.06] and before_grasp == [f for f in range(10) if f != 3]
    # a support not seen, or one that would move the rest beyond MAX_REST_SHIFT: the height stands
    for unseen in (lambda hull, low, frames: None,
                   lambda hull, low, frames: -0.001 if hull.mean(0)[1] < -0.05 else 0.004 + 2 * MAX_REST_SHIFT):
        kept = poses.copy()
        assert rest_on_support(kept, [GripperEvents(10, 25)], unseen, model) == [] and np.allclose(kept, poses)
    # a model with no area seen from above (points on a vertical line) has no footprint
    line = np.zeros((20, 3))
    line[:, 2] = np.linspace(-0.025, 0.025, 20)
    kept = poses.copy()
    assert rest_on_support(kept, [GripperEvents(10, 25)], support, line) == [] and np.allclose(kept, poses)


def test_an_object_let_go_on_another_face_keeps_its_height():
    """A box whose model lacks its lower 8 mm (as a camera from above sees it) stands 8 mm above
    its lowest model points at the start; handed over and laid on its side, another face (whole in
    the model) is down: the start's 8 mm do not apply, and its height stands. Turned by a few
    degrees it still stands on its support."""
    model = box_points(n=21)
    model = model[model[:, 2] > -0.017]
    T = 40
    poses = np.repeat(np.eye(4)[None], T, axis=0)
    poses[:, :3, 3] = [0.3, -0.1, 0.025]
    poses[10:25, :3, 3] = [0.32, 0.0, 0.1]
    poses[25:, :3, 3] = [0.32, 0.06, 0.027]  # carried onto the table 2 mm high
    support = lambda hull_xy, z_low, frames: 0.0  # noqa: E731
    for degrees, change in ((90.0, None), (MAX_REST_TILT_DEG / 2, -0.002)):
        rested = poses.copy()
        rested[25:, :3, :3] = Rotation.from_euler("x", degrees, degrees=True).as_matrix()
        turned = rested.copy()
        heights = rest_on_support(rested, [GripperEvents(10, 25)], support, model)
        if change is None:
            assert heights == [] and np.allclose(rested, turned), "laid on its side: its height stands"
        else:
            assert heights == [pytest.approx(change, abs=1e-3)], "turned a little: set on the support"


def test_model_views_see_an_object_turned_less_than_the_limit():
    camera = np.array([1.0, 0.0, 0.0])  # level with the object: its turn about z is the view's change
    T = np.eye(4)
    views = ModelViews.of(camera, [T])
    turned = lambda deg: so3_exp(torch.tensor([0.0, 0.0, np.radians(deg)], dtype=torch.float64)).numpy()  # noqa: E731
    assert views.sees(T) and views.sees(np.block([[turned(MAX_VIEW_CHANGE_DEG - 5), np.zeros((3, 1))], [0, 0, 0, 1]]))
    assert not views.sees(np.block([[turned(MAX_VIEW_CHANGE_DEG + 5), np.zeros((3, 1))], [0, 0, 0, 1]]))
    both = ModelViews.of(camera, [T, np.block([[turned(60.0), np.zeros((3, 1))], [0, 0, 0, 1]])])
    assert both.sees(np.block([[turned(60.0 + MAX_VIEW_CHANGE_DEG - 5), np.zeros((3, 1))], [0, 0, 0, 1]]))


def test_no_rest_fit_from_frames_that_see_the_object_from_elsewhere_than_its_model():
    """The frames after the release see the box from 66 deg away from where its model was seen
    (turned 90 deg about the vertical, the camera 40 deg above it): their depth is not fitted and
    the prior stands; seen from where the model was, it is."""
    model = box_points(n=41)
    T = 30
    poses = np.repeat(np.eye(4)[None], T, axis=0)
    poses[:, :3, 3] = [0.3, 0.1, 0.025]
    width = np.full(T, 0.07)
    width[18:21] = [0.045, 0.055, 0.065]
    surface = lambda f: visible_box_surface(poses[f] @ _translation([0.001, 0.002, -0.002]), seed=f)  # noqa: E731
    camera = poses[0, :3, 3] + [0.6, 0.0, 0.5]
    turned = poses[0].copy()
    turned[:3, :3] = so3_exp(torch.tensor([0.0, 0.0, np.radians(90.0)], dtype=torch.float64)).numpy()
    kept = poses.copy()
    assert settle_at_rest(kept, [GripperEvents(5, 18)], surface, model, width,
                          views=ModelViews.of(camera, [turned])) == [] and np.allclose(kept, poses)
    settled = poses.copy()
    shifts = settle_at_rest(settled, [GripperEvents(5, 18)], surface, model, width,
                            views=ModelViews.of(camera, [poses[0]]))
    assert len(shifts) == 1 and np.linalg.norm(shifts[0] - [0.001, 0.002, -0.002]) < 3e-4


def carried_box(T=50, grasp=10, release=40):
    """A box carried by a TCP that moves and turns, held rigidly from ``grasp`` to ``release``:
    (tcp [T, 4, 4], rigid poses [T, 4, 4], width [T]: the pads close over frames 10-13)."""
    tcp = np.repeat(np.eye(4)[None], T, axis=0)
    tcp[:, :3, 3] = np.stack([np.linspace(0.3, 0.1, T), np.linspace(0.0, 0.2, T), np.full(T, 0.12)], -1)
    angles = np.clip(np.arange(T) - grasp, 0, release - grasp) * 0.02  # the wrist turns up to 34 deg
    tcp[:, :3, :3] = so3_exp(torch.as_tensor(np.outer(angles, [0.3, 0.0, 1.0]))).numpy() @ np.diag([1.0, -1.0, -1.0])
    width = np.full(T, 0.07)
    width[grasp:grasp + 3] = [0.06, 0.05, 0.045]
    width[grasp + 3:release] = 0.04
    rigid, _ = kinematic_prior(tcp[0] @ _translation([0, 0, 0.01]), tcp, [GripperEvents(grasp, release)], width=width)
    return tcp, rigid, width


def test_follow_slip_carries_the_object_where_the_depth_sees_it_slip_in_the_hand():
    model = box_points(n=41)
    tcp, rigid, width = carried_box()
    slip = np.zeros((50, 3))  # in the TCP's frame: 0 until frame 20, then 4 mm over 15 frames, then held
    slip[20:] = np.minimum(np.arange(30) / 15, 1.0)[:, None] * [0.003, 0.0, 0.0025]
    truth = rigid.copy()
    truth[13:40, :3, 3] += np.einsum("nij,nj->ni", tcp[13:40, :3, :3], slip[13:40])
    truth[40:, :3, 3] += tcp[39, :3, :3] @ slip[39]  # let go where it had slipped to
    held_out = range(27, 31)  # four frames in a row: a majority of the running median's window

    def surface(f):
        seen = truth[f] @ _translation([0.0, 0.008, 0.0]) if f in held_out else truth[f]  # held-out frames lie
        return visible_box_surface(seen, seed=f)

    poses = rigid.copy()
    slips = follow_slip(poses, [GripperEvents(10, 40)], surface, model, tcp, width, observe=frozenset(held_out))
    assert len(slips) == 1 and np.linalg.norm(slips[0] - slip[39]) < 1e-4
    error = np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert np.allclose(poses[:13], rigid[:13])  # closing: not held yet
    # measured 0.05 mm at most (the model's 1 mm grid against random surface points; a median
    # follows a ramp); 10 % of the 3.9 mm slip missed would be 0.4 mm
    assert error[13:].max() < 2e-4 and error[13:].mean() < 1e-4, error.round(5)
    assert np.allclose(poses[:, :3, :3], rigid[:, :3, :3])  # position only


def test_follow_slip_keeps_the_rigid_grasp_without_clear_evidence_and_leaves_tracked_frames_alone():
    model = box_points(n=41)
    tcp, rigid, width = carried_box()
    still = rigid.copy()
    assert follow_slip(still, [GripperEvents(10, 40)], lambda f: visible_box_surface(rigid[f], seed=f),
                       model, tcp, width) == []
    assert np.array_equal(still, rigid)  # the surface fits the rigid grasp: nothing to follow
    assert follow_slip(still, [GripperEvents(10, 40)], lambda f: None, model, tcp, width) == []
    assert np.array_equal(still, rigid)  # no depth
    tracked = np.zeros(50, dtype=bool)
    tracked[25:28] = True
    slipped = rigid.copy()
    in_hand = lambda f: rigid[f] @ _translation([0.003, 0.0, 0.0]) if f >= 10 else rigid[f]  # noqa: E731
    assert len(follow_slip(slipped, [GripperEvents(10, 40)], lambda f: visible_box_surface(in_hand(f), seed=f),
                           model, tcp, width, keep=tracked)) == 1
    assert np.array_equal(slipped[tracked], rigid[tracked])
    assert np.allclose(np.linalg.norm(slipped[13:25, :3, 3] - rigid[13:25, :3, 3], axis=1), 0.003, atol=4e-4)


def test_follow_slip_counts_the_misfit_above_the_depths_noise_floor():
    """Stereo-like depth (1.5 mm scatter) and a model made of frame 0's noisy depth: a 2.5 mm slip
    in the hand is taken when the still frames before the grasp show the noise floor, missed
    without them (the misfit's drop is then measured against the noise too); no slip, none taken."""
    tcp, rigid, width = carried_box()
    noisy = lambda X, seed: X + np.random.default_rng(seed).normal(0.0, 0.0015, X.shape)  # noqa: E731
    model = noisy(visible_box_surface(np.eye(4), seed=999), 999)

    def depth(slip_m, still_frames=True):
        def surface(f):
            if f < 10 and not still_frames:
                return None
            pose = rigid[f] @ _translation([slip_m, 0.0, 0.0]) if f >= 10 else rigid[f]
            return noisy(visible_box_surface(pose, seed=f), 100 + f)
        return surface

    assert 0.0013 < noise_floor(SurfaceModel(model), rigid, [GripperEvents(10, 40)], depth(0.0025)) < 0.0016
    slipped = rigid.copy()
    slips = follow_slip(slipped, [GripperEvents(10, 40)], depth(0.0025), model, tcp, width)
    assert len(slips) == 1 and abs(np.linalg.norm(slips[0]) - 0.0025) < 5e-4
    assert follow_slip(rigid.copy(), [GripperEvents(10, 40)], depth(0.0025, still_frames=False), model, tcp, width) == []
    assert follow_slip(rigid.copy(), [GripperEvents(10, 40)], depth(0.0), model, tcp, width) == []


def test_follow_slip_holds_the_object_where_the_pads_closed_along_their_closing_axis():
    """The pads clamp the object along their closing axis (the TCP's y): what the depth shows
    there is one offset for the whole hold (the centring's error), not a drift; across it
    (x, z) the slip is followed frame by frame."""
    model = box_points(n=41)
    tcp, rigid, width = carried_box()
    ramp = np.clip((np.arange(50) - 13) / 26, 0.0, 1.0)  # 0 -> 1 over the hold
    centred_off = lambda f: rigid[f] @ _translation([0.0, 0.003, 0.0]) if f >= 10 else rigid[f]  # noqa: E731
    poses = rigid.copy()
    slips = follow_slip(poses, [GripperEvents(10, 40)], lambda f: visible_box_surface(centred_off(f), seed=f),
                        model, tcp, width)
    in_tcp = np.einsum("nji,nj->ni", tcp[13:40, :3, :3], poses[13:40, :3, 3] - rigid[13:40, :3, 3])
    assert len(slips) == 1 and np.abs(in_tcp - [0.0, 0.003, 0.0]).max() < 3e-4  # taken whole, from the close

    drifting = lambda f: rigid[f] @ _translation([0.004 * ramp[f], 0.003 * ramp[f], 0.0])  # noqa: E731
    poses = rigid.copy()
    slips = follow_slip(poses, [GripperEvents(10, 40)], lambda f: visible_box_surface(drifting(f), seed=f),
                        model, tcp, width)
    in_tcp = np.einsum("nji,nj->ni", tcp[13:40, :3, :3], poses[13:40, :3, 3] - rigid[13:40, :3, 3])
    assert len(slips) == 1 and np.ptp(in_tcp[:, 1]) < 1e-9 and abs(in_tcp[0, 1] - 0.0015) < 5e-4
    assert np.abs(in_tcp[:, 0] - 0.004 * ramp[13:40]).max() < 6e-4  # the drift across the pads followed


def test_hybrid_pseudo_poses_follow_the_slip_the_depth_shows_unless_told_not_to():
    model = box_points(n=41)
    tcp, rigid, width = carried_box()
    events = [GripperEvents(10, 40)]
    phases = [Segment("motion", "M_approach", 0, 8), Segment("skill", "S_pick", 8, 14),
              Segment("motion", "M_transfer", 14, 36), Segment("skill", "S_place", 36, 44),
              Segment("motion", "M_return", 44, 50)]

    def agreeing_tracker(frames, T_first, prior):
        return prior, np.zeros(len(frames), dtype=bool)

    def pseudo(surface, slip_from_depth=True):
        return hybrid_pseudo_poses(phases, rigid[0], tcp, events, agreeing_tracker, model, width=width,
                                   surface=surface, slip_from_depth=slip_from_depth).poses

    held = pseudo(None)
    truth = held.copy()
    truth[13:40, :3, 3] += tcp[13:40, :3, :3] @ np.array([0.0, 0.0, 0.003])  # 3 mm along the TCP's z
    truth[40:, :3, 3] += tcp[39, :3, :3] @ np.array([0.0, 0.0, 0.003])
    seen = lambda f: visible_box_surface(truth[f], seed=f)  # noqa: E731
    followed = np.linalg.norm(pseudo(seen)[:, :3, 3] - truth[:, :3, 3], axis=1)
    rigid_grasp = np.linalg.norm(pseudo(seen, slip_from_depth=False)[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert followed.max() < 2e-4
    assert np.allclose(rigid_grasp[13:40], 0.003, atol=2e-4) and rigid_grasp[40:].max() < 3e-4  # the rest, from depth


def _translation(xyz):
    T = np.eye(4)
    T[:3, 3] = xyz
    return T


def test_an_object_too_small_to_track_is_reported_as_not_tracked_not_as_solved_0(caplog):
    """An object a few pixels across gives the tracker too few points: the log says it was not
    tracked and why, not "solved 0 of N" (which read as a failure on the built-in sample's box,
    about ten pixels across at 160x120)."""
    import logging

    K, truth, grays, masks, depths = textured_plane_episode()
    rows, cols = np.nonzero(masks[0])
    r, c = int(rows.mean()), int(cols.mean())
    speck = np.zeros_like(masks[0])
    speck[r - 2:r + 2, c - 2:c + 2] = True
    caplog.set_level(logging.INFO, logger="manisplat")
    track = track_object(lambda i: grays[i], lambda i: speck, lambda i: depths[i], K, np.eye(4),
                         range(len(truth)), truth[0], TrackerSettings(confident_inliers=10), prior=truth)
    assert not track.solved[1:].any() and np.allclose(track.poses, truth)
    text = caplog.text
    assert "not tracked: the object shows at most" in text and "the prior stands" in text
    assert "solved 0 of" not in text


def test_held_out_frames_are_not_read_and_take_the_pose_the_frames_before_imply():
    """A scored frame's pose must not come from its own image: the tracker never reads a held-out
    frame, which takes the prior with the correction tracking had made by then."""
    K, truth, grays, masks, depths = textured_plane_episode()
    static_prior = np.repeat(truth[:1], len(truth), axis=0)
    held_out = {len(truth) - 3, len(truth) - 1}
    read = []

    def gray(i):
        read.append(i)
        return grays[i]

    settings = TrackerSettings(confident_inliers=10, persistence=3)
    track = track_object(gray, lambda i: masks[i], lambda i: depths[i], K, np.eye(4), range(len(truth)), truth[0],
                         settings, prior=static_prior, observe=frozenset(held_out))
    assert not held_out & set(read)
    f = len(truth) - 3
    assert track.from_tracking[f - 1] and not track.from_tracking[f] and track.from_tracking[f + 1]
    np.testing.assert_allclose(track.poses[f], track.poses[f - 1], atol=1e-12)  # a static prior: the last correction
    assert np.linalg.norm(track.poses[f + 1, :3, 3] - truth[f + 1, :3, 3]) < 0.002  # tracking went on past it
