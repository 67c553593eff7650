"""Symmetric objects: the grasp of a new demonstration is taken on the face that keeps the wrist
nearest the source's, the object starts exactly where asked and is left where asked up to a turn
of its symmetry."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from manisplat.augment.sampling import perturb
from manisplat.augment.source import source_demo
from manisplat.augment.symmetry import Symmetry, axis_point, parse_symmetries, vertical_turn, wrist_keeping_turn
from manisplat.augment.trajectory import AugmentConfig, ObjectTarget, augment_trajectory, augmenter_for


def _yaw_deg(R: np.ndarray) -> float:
    return math.degrees(math.atan2(R[1, 0], R[0, 0]))


def test_parse_symmetries_reads_orders_and_round_and_names_bad_items():
    assert parse_symmetries(["box=4", "can=round"]) == {"box": Symmetry(4), "can": Symmetry(None)}
    for bad in ("box", "box=", "=4", "box=0", "box=square", "box=2.5"):
        with pytest.raises(ValueError, match="symmetry"):
            parse_symmetries([bad])


@pytest.mark.parametrize("order, wanted, turn", [(4, -60, -90), (4, 40, 0), (2, 100, 180), (1, 170, 0),
                                                  (None, 33, 33)])
def test_the_allowed_turn_nearest_the_wanted_one(order, wanted, turn):
    assert math.degrees(Symmetry(order).nearest_turn(math.radians(wanted))) == pytest.approx(turn, abs=1e-9)


def test_the_turn_keeps_the_grasp_heading_relative_to_the_arm():
    """An object turned by 60 deg and moved across the arm's azimuth: round, the grasp's heading seen
    from the base does not change at all; a square box's turn leaves it within 45 deg."""
    grasp_point = np.array([0.01, -0.005, 0.02])  # object frame
    T_src = perturb(np.eye(4), 0.30, -0.08, 0.0)
    T_new = perturb(np.eye(4), 0.25, 0.05, math.radians(60))
    azimuth = [math.degrees(math.atan2(*(T @ np.r_[grasp_point, 1])[[1, 0]])) for T in (T_src, T_new)]
    for symmetry, within in ((Symmetry(None), 1e-9), (Symmetry(4), 45.0)):
        S = wrist_keeping_turn(symmetry, T_src, T_new, grasp_point)
        D = T_new @ S @ np.linalg.inv(T_src)
        relative = _yaw_deg(D[:3, :3]) - (azimuth[1] - azimuth[0])
        assert abs(relative) <= within
        # a turn about the vertical through the grasp point: that point stays where the object puts it
        assert np.allclose(D @ T_src @ np.r_[grasp_point, 1], T_new @ np.r_[grasp_point, 1], atol=1e-12)
    assert np.allclose(vertical_turn(np.array([0.3, 0.1, 0.0]), 0.0), np.eye(4))


def test_the_axis_is_where_the_pads_centred_the_object_and_the_box_centre_across_them():
    """Closing along the object's x (the TCP's y): the axis takes the TCP's x and the box centre's y."""
    T_obj_tcp = np.eye(4)
    T_obj_tcp[:3, :3] = [[0, 1, 0], [-1, 0, 0], [0, 0, 1]]  # TCP y = object x
    T_obj_tcp[:3, 3] = [0.004, -0.010, 0.03]
    point = axis_point(T_obj_tcp, np.array([-0.002, 0.003, 0.0]), np.array([0.0, 0.0, 1.0]))
    assert np.allclose(point, [0.004, 0.003, 0.0], atol=1e-12)


def test_a_symmetric_object_is_grasped_on_the_face_nearest_the_source_wrist(twin):
    """The box turned by 60 deg: without a symmetry the pick turns with it (60 deg); declared square
    (order 4) it is taken on the next face pair (a -90 deg turn), so the grasp turns -30 deg; the
    box starts exactly at its new pose, rides rigidly in the gripper and is left at the place pose
    up to a quarter turn."""
    src = source_demo(twin)
    box = src.objects["box"]
    T_start = perturb(box.T_rest, 0.0, 0.0, math.radians(60))
    T_place = perturb(box.T_placed, 0.0, 0.0, math.radians(10))
    targets = {"box": ObjectTarget(T_start, T_place)}
    plain = augment_trajectory(twin, targets, AugmentConfig())
    turned = augment_trajectory(twin, targets, AugmentConfig(symmetries={"box": Symmetry(4)}))

    def pick_yaw(traj) -> float:
        pick = next(s for s in traj.segments if s["name"] == "S_pick")
        return _yaw_deg(np.array(pick["T"])[:3, :3])

    assert pick_yaw(plain) == pytest.approx(60, abs=1e-6)
    assert pick_yaw(turned) == pytest.approx(-30, abs=1e-6)
    assert turned.planner["symmetry_turns_deg"]["box"] == {"pick": -90.0, "place": 0.0}
    assert "symmetry_turns_deg" not in plain.planner or not plain.planner["symmetry_turns_deg"]
    poses = turned.object_poses["box"]
    assert np.allclose(poses[0], T_start, atol=1e-12)
    # carried rigidly: one grasp offset over the transfer
    transfer = next(s for s in turned.segments if s["name"] == "M_transfer")
    f0, f1 = transfer["frames"]
    tcp = twin.robot.tcp_pose(torch.as_tensor(turned.q[f0:f1 + 1])).numpy()
    grasp = np.linalg.inv(tcp) @ poses[f0:f1 + 1]
    assert np.allclose(grasp, grasp[0], atol=1e-9)
    # left at the place pose turned by a quarter turn about the vertical through the grasp axis
    left = np.linalg.inv(T_place) @ poses[-1]
    assert _yaw_deg(T_place[:3, :3] @ left[:3, :3] @ T_place[:3, :3].T) == pytest.approx(90, abs=1e-6)
    axis = np.r_[augmenter_for(twin).symmetry_axis("box"), 1]
    assert np.allclose(poses[-1] @ axis, T_place @ axis, atol=1e-9)
    assert np.allclose(turned.objects["box"]["T_end"], poses[-1])
