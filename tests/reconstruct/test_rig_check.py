"""A two-arm rig's calibration checked against its robots: a base-to-base error is found from the
head camera's view of both arms (the first arm anchors the world), a wrist camera's
``T_link6_cam`` error from its view of the static scene the head camera measured (its own fingers
alone cannot tell), and the corrected rig goes into the twin."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
import torch

from manisplat.episode.synthetic_arms import write_two_arm_sample_episode
from manisplat.reconstruct.cli import main
from manisplat.reconstruct.data import load_episode_data
from manisplat.reconstruct.extrinsic import pose_difference, refine_extrinsic
from manisplat.reconstruct.plan import make_plan
from manisplat.reconstruct.rig_check import check_rig
from manisplat.reconstruct.static_surface import static_surface
from manisplat.twin import Twin

WRISTS = ("cam_left_wrist", "cam_right_wrist")


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    return write_two_arm_sample_episode(tmp_path_factory.mktemp("rig") / "ep", duration=3.0, wrist_cameras=True)


def _error(axis, deg: float, direction, mm: float) -> np.ndarray:
    E = np.eye(4)
    axis, direction = np.asarray(axis, float), np.asarray(direction, float)
    E[:3, :3] = cv2.Rodrigues(axis / np.linalg.norm(axis) * np.radians(deg))[0]
    E[:3, 3] = direction / np.linalg.norm(direction) * mm / 1000
    return E


def _miscalibrated(source, out, *, base: bool = False, wrist: str | None = None):
    """A copy of ``source`` with the right arm's base and/or one wrist camera off by 0.3 deg / 3 mm;
    the true values."""
    shutil.copytree(source, out)
    meta = json.loads((out / "episode.json").read_text())
    truth = {"base": np.asarray(meta["arms"]["right"]["T_world_base"]),
             **{c: np.asarray(meta["cameras"][c]["T_mount_cam"]) for c in WRISTS}}
    if base:
        meta["arms"]["right"]["T_world_base"] = (truth["base"] @ _error([0.3, -1, 0.5], 0.3, [0.6, 0.5, -0.6], 3)).tolist()
    if wrist:
        meta["cameras"][wrist]["T_mount_cam"] = (truth[wrist] @ _error([-1, 0.2, 0.4], 0.3, [0.2, -0.7, 0.5], 3)).tolist()
    (out / "episode.json").write_text(json.dumps(meta))
    return out, truth


def _loaded(episode):
    data = load_episode_data(episode, camera="cam_high")
    views = {c: load_episode_data(episode, camera=c, load_meshes=False) for c in WRISTS}
    for view in views.values():
        view.robot = data.robot
    return data, views, make_plan(data).train_frames


def test_a_base_to_base_error_is_found_from_the_head_camera_and_the_first_arm_anchors_the_world(rig, tmp_path):
    episode, truth = _miscalibrated(rig, tmp_path / "base", base=True)
    data, views, frames = _loaded(episode)
    left = data.robot.T_world_base["left"].copy()
    T_cam = np.linalg.inv(data.viewmat.double().numpy())
    check = check_rig(data, views, frames)
    base = check.bases["right"]
    assert base.applied, base.reason
    assert pose_difference(truth["base"], base.T_before) == pytest.approx((0.3, 3.0), rel=1e-3)
    deg, mm = pose_difference(truth["base"], base.T_after)
    assert deg < 0.03 and mm < 0.3, (deg, mm)
    assert base.rotation_deg == pytest.approx(0.3, abs=0.03) and 0 < base.sigma_rotation_deg < 0.05
    np.testing.assert_array_equal(data.robot.T_world_base["left"], left)  # the gauge
    np.testing.assert_array_equal(data.robot.T_world_base["right"], base.T_after)
    assert [a.T_world_base.tolist() for a in data.arms] == [left.tolist(), base.T_after.tolist()]
    # the camera fitted to the left arm alone stays where it was (the episode's camera was right)
    assert max(pose_difference(T_cam, check.camera.T_fitted)[0], 0) < 0.03
    # the links of every camera's view were placed anew from the moved base
    right6 = data.robot.link_names.index("right/link6")
    np.testing.assert_allclose(views["cam_right_wrist"].link_poses[3, right6].double().numpy(),
                               data.link_poses[3, right6].double().numpy(), atol=1e-6)


def test_a_wrist_camera_error_is_found_against_the_static_scene_the_head_camera_measured(rig, tmp_path):
    episode, truth = _miscalibrated(rig, tmp_path / "wrist", wrist="cam_left_wrist")
    data, views, frames = _loaded(episode)
    robot_alone = refine_extrinsic(views["cam_left_wrist"], frames)
    check = check_rig(data, views, frames)
    wrist = check.riding["cam_left_wrist"]
    assert wrist.applied, wrist.reason
    deg, mm = pose_difference(truth["cam_left_wrist"], wrist.T_after)
    assert deg < 0.05 and mm < 0.5, (deg, mm)
    assert deg < 2 * wrist.sigma_rotation_deg and mm < 2 * wrist.sigma_translation_mm, (wrist.sigma_parts, deg, mm)
    assert wrist.points > 2 * robot_alone.points  # the static scene's points besides the robot's
    np.testing.assert_allclose(views["cam_left_wrist"].T_mount_cam.numpy(), wrist.T_after)
    right = check.riding["cam_right_wrist"]  # calibrated: kept, and said to agree
    assert not right.applied and ("agrees" in right.reason or "fits the camera as recorded" in right.reason)
    assert (views["cam_right_wrist"].T_mount_cam.numpy() == truth["cam_right_wrist"]).all()
    gt = np.load(episode / "gt.npz")["T_world_cam_cam_left_wrist"]
    placed = torch.linalg.inv(views["cam_left_wrist"].viewmat.double()).numpy()
    for f in (0, 15, 29):
        assert pose_difference(gt[f], placed[f])[1] < 0.5


def test_the_static_surface_is_where_a_wrist_camera_sees_the_table(rig):
    """The head camera's static surface (robot and objects left out, no triangle across a depth
    edge) is hit by most of a wrist camera's rays that do not meet the robot, at the depth the wrist
    camera measures."""
    data, views, _ = _loaded(rig)
    surface = static_surface(data, 0)
    assert abs(np.median(surface.vertices[:, 2])) < 1e-3  # mostly table
    view = views["cam_left_wrist"]
    T = torch.linalg.inv(view.viewmat[10].double()).numpy()
    free = np.isin(view.masks[10].numpy(), view.labels.static)
    rows, cols = np.nonzero(free & (view.depth[10].numpy() > 0))
    K = view.K_opencv.numpy()
    z = view.depth[10].numpy()[rows, cols].astype(np.float64)
    p = np.stack([(cols - K[0, 2]) / K[0, 0] * z, (rows - K[1, 2]) / K[1, 1] * z, z], 1)
    rays = p / np.linalg.norm(p, axis=1, keepdims=True) @ T[:3, :3].T
    hit, ray, _ = surface.ray.intersects_location(np.broadcast_to(T[:3, 3], rays.shape), rays, multiple_hits=False)
    assert len(ray) > 0.5 * len(p)
    measured = p[ray] @ T[:3, :3].T + T[:3, 3]
    assert np.median(np.linalg.norm(hit - measured, axis=1)) < 1e-3


def test_the_corrected_rig_goes_into_the_twin_and_its_metrics(rig, tmp_path):
    episode, truth = _miscalibrated(rig, tmp_path / "both", base=True, wrist="cam_right_wrist")
    out = tmp_path / "twin"
    assert main([str(episode), "--out", str(out), "--iters", "2", "-q"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["rig"]["bases"]["right"]["applied"]
    assert metrics["rig"]["cameras"]["cam_right_wrist"]["applied"]
    assert not metrics["rig"]["cameras"]["cam_left_wrist"]["applied"]
    twin = Twin.load(out)
    base = next(a for a in twin.arms if a.name == "right").T_world_base
    assert pose_difference(truth["base"], base)[1] < 0.3
    assert pose_difference(truth["cam_right_wrist"], twin.cameras["cam_right_wrist"].T_mount_cam)[1] < 0.5
