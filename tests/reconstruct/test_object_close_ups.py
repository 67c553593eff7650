"""The wrist cameras' close-ups of an object complete its seeds: its surface as the riding camera
saw it, carried into the object's frame by the object's pose there, neither the robot nor the
support it stands on, where the fixed camera's first frame saw it coarsely or not at all."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from manisplat.episode.synthetic import BOX_SIZE
from manisplat.episode.synthetic_arms import write_two_arm_sample_episode
from manisplat.reconstruct.data import load_episode_data, load_ground_truth
from manisplat.reconstruct.init import canonical_object_points, object_close_up_points

BOX = "box_left"


@pytest.fixture(scope="module")
def episode(tmp_path_factory):
    return write_two_arm_sample_episode(tmp_path_factory.mktemp("object_close_ups") / "ep", duration=2.0,
                                        wrist_cameras=True)


@pytest.fixture(scope="module")
def scene(episode):
    """(the left wrist camera's view, the box's label, its first-frame points in its canonical
    frame with their spacing, its true poses of that frame [T, 4, 4], the true box poses)."""
    head = load_episode_data(episode, load_meshes=False)
    wrist = load_episode_data(episode, camera="cam_left_wrist", load_meshes=False)
    label = next(v for v, name in head.labels.objects.items() if name == BOX)
    points, _, spacing, T_start = canonical_object_points(head, label, 0)
    T_world_box = load_ground_truth(episode)[f"T_world_{BOX}"]
    poses = T_world_box @ np.linalg.inv(T_world_box[0]) @ T_start.numpy()
    return wrist, label, points.float(), spacing, poses, T_world_box


def in_box_frame(points: torch.Tensor, T_obj_box: np.ndarray) -> np.ndarray:
    """Object-frame points [N, 3] in the true box's own frame (its centre, its axes)."""
    return (points.double().numpy() - T_obj_box[:3, 3]) @ T_obj_box[:3, :3]


def test_close_ups_are_the_object_s_surface_without_its_support(scene):
    wrist, _, seeds, spacing, poses, T_world_box = scene
    frames = list(range(0, wrist.n_frames, 2))
    points, colours, gaps = object_close_up_points(wrist, frames, poses, seeds, spacing)
    assert len(points) > 50 and colours.shape == points.shape and (gaps > 0).all()
    T_obj_box = np.linalg.inv(poses[0]) @ T_world_box[0]
    local = in_box_frame(points, T_obj_box)
    half = BOX_SIZE / 2
    assert np.abs(local).max() < half + 2e-3, "every point lies on the box (not the robot, not the table)"
    assert local[:, 2].min() > -half + 5e-4, "the table under the box seeds nothing"
    on_a_face = np.abs(np.abs(local) - half).min(1)
    assert np.median(on_a_face) < 1e-3, "on the box's faces, as the wrist camera's depth put them"


def test_a_wrong_pose_puts_nothing_on_the_object(scene):
    """With the object's pose 10 cm off, the box around its seeds holds table and air only."""
    wrist, _, seeds, spacing, poses, _ = scene
    shifted = poses.copy()
    shifted[:, 1, 3] += 0.10
    points = object_close_up_points(wrist, list(range(0, wrist.n_frames, 2)), shifted, seeds, spacing)[0]
    assert len(points) < 10


def test_what_the_seeds_already_show_as_finely_is_not_added(scene):
    wrist, _, seeds, spacing, poses, _ = scene
    frames = list(range(0, wrist.n_frames, 2))
    first = object_close_up_points(wrist, frames, poses, seeds, spacing)
    again = object_close_up_points(wrist, frames, poses, torch.cat([seeds, first[0]]), torch.cat([spacing, first[2]]))
    assert len(again[0]) < 0.05 * len(first[0])


def test_a_camera_without_depth_cannot_seed_object_close_ups(episode, scene):
    _, _, seeds, spacing, poses, _ = scene
    view = load_episode_data(episode, camera="cam_left_wrist", use_depth=False, load_meshes=False)
    with pytest.raises(ValueError, match="cam_left_wrist: close-up seeds need its depth"):
        object_close_up_points(view, [0], poses, seeds, spacing)
