"""The bodies of wrist cameras, which no URDF has, found in the head camera's depth and added to
the links they ride on: the two-arm sample renders each wrist camera's body (a 4 x 3 x 2.5 cm
box behind its lens) in every image and labels it robot/<arm>/wrist_camera."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import trimesh

from manisplat.episode.synthetic_arms import T_LINK6_WRIST_CAM, write_two_arm_sample_episode, wrist_camera_body
from manisplat.reconstruct.camera_bodies import body_labels, find_camera_bodies
from manisplat.reconstruct.config import TrainConfig
from manisplat.reconstruct.data import load_episode_data
from manisplat.reconstruct.masks import ObjectPrompt, complete_masks
from manisplat.reconstruct.pipeline import build
from manisplat.reconstruct.plan import make_plan
from tests.reconstruct.test_two_arms import prompts_of


@pytest.fixture(scope="module")
def episode(tmp_path_factory):
    return write_two_arm_sample_episode(tmp_path_factory.mktemp("bodies") / "ep", duration=3.0, wrist_cameras=True)


def drawn_data(episode):
    """The head camera's view, its masks drawn from the robot and the prompted boxes."""
    data = load_episode_data(episode, use_masks=False)
    links = [n for n in data.robot.link_names if data.robot.visuals.get(n)]
    names = prompts_of(episode)[1::2]
    complete_masks(data, links, [ObjectPrompt(t.split("=")[0], point=tuple(map(float, t.split("=")[1].split(","))))
                                 for t in names], progress=False)
    return data


def true_body_in_link() -> trimesh.Trimesh:
    body = wrist_camera_body()
    body.apply_transform(T_LINK6_WRIST_CAM)
    return body


@pytest.fixture(scope="module")
def drawn(episode):
    return drawn_data(episode)


def test_each_wrist_cameras_body_is_found_on_its_link(drawn):
    data = drawn
    bodies = find_camera_bodies(data, list(range(data.n_frames)))
    assert {b.camera: b.link for b in bodies} == {"cam_left_wrist": "left/link6", "cam_right_wrist": "right/link6"}
    truth = true_body_in_link()
    for body in bodies:
        # to a voxel (about 1.5 of the head camera's pixels there, 12 mm)
        assert body.voxel_m < 0.015
        assert np.abs(body.mesh.bounds - truth.bounds).max() <= body.voxel_m, (body.camera, body.mesh.bounds,
                                                                               truth.bounds)


def test_with_the_episodes_masks_the_bodies_are_its_robot_labels_that_name_no_link(episode):
    """The sample's own masks label each body robot/<arm>/wrist_camera: robot, but no link of
    the URDF. Those pixels are where the bodies are looked for, and found on their links."""
    data = load_episode_data(episode)
    assert data.mask_source == "episode"
    assert {data.labels.robot[v] for v in body_labels(data)} == {"left/wrist_camera", "right/wrist_camera"}
    bodies = find_camera_bodies(data, list(range(data.n_frames)))
    assert {b.camera: b.link for b in bodies} == {"cam_left_wrist": "left/link6", "cam_right_wrist": "right/link6"}
    truth = true_body_in_link()
    for body in bodies:
        assert np.abs(body.mesh.bounds - truth.bounds).max() <= body.voxel_m, body.camera


def test_what_does_not_move_with_the_link_is_no_body(drawn):
    """Around a point 25 cm beyond link6's flange the table and the boxes pass under the gripper:
    seen from many poses, they land in other voxels of the link's frame each time, so nothing
    there is a body (kept voxels need 3 poses and a quarter of them)."""
    T_link_point = np.eye(4)
    T_link_point[2, 3] = 0.25
    data = dataclasses.replace(drawn, riding_cameras={"nothing": ("left/link6", torch.tensor(T_link_point))})
    assert find_camera_bodies(data, list(range(data.n_frames))) == []


def test_the_robots_masks_and_gaussians_include_the_bodies(episode):
    """Without the bodies the drawn robot misses the camera bodies' pixels, which the episode's
    own masks label as robot (robot/<arm>/wrist_camera); with them it covers most of those pixels, and the link's Gaussians
    fill the body."""
    data = drawn_data(episode)
    robot_values = torch.tensor(sorted(data.labels.robot), dtype=torch.uint8)
    frames = range(data.n_frames)
    truth = torch.stack([data.eval_region(f, "robot") for f in frames])

    def recall() -> float:
        drawn = torch.stack([torch.isin(data.masks[f], robot_values) for f in frames])
        return float((drawn & truth).sum() / truth.sum())

    before = recall()
    rec, _ = build(data, make_plan(data), TrainConfig(iters=1))
    after = recall()
    # the bodies are about 1 % of the robot's pixels here: what the drawn robot missed falls by more than half
    assert 1 - after < 0.5 * (1 - before), (before, after)
    means = rec.graph.links["left/link6"].params["means"].detach().double().numpy()
    low, high = true_body_in_link().bounds
    near = ((means > low - 0.012) & (means < high + 0.012)).all(1)  # within a voxel of the body's box
    assert near.sum() >= 20, near.sum()
