"""Hybrid pseudo ground truth: the gripper prior, tracking overrides, and the tracker itself on
a synthetic textured plane with known motion."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from manisplat.align.phases import GripperEvents, Segment
from manisplat.align.pseudo_gt import ATTACHED, STATIC, TRACKED, hybrid_pseudo_poses, kinematic_prior
from manisplat.align.tracking import TrackerSettings, track_object


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
