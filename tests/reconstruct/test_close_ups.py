"""The wrist cameras' close-ups seed the background where they see it more finely than the fixed
camera's seeds: static surface points placed by the camera's pose at that frame, each added once;
and, built, the objects' seeds (their close-ups: test_object_close_ups.py)."""

from __future__ import annotations

import pytest
import torch

from manisplat.episode.synthetic_arms import write_two_arm_sample_episode
from manisplat.reconstruct.config import TrainConfig
from manisplat.reconstruct.data import load_episode_data
from manisplat.reconstruct.init import (backproject, background_gaussians, close_up_points, sample_spacing,
                                        seen_through)
from manisplat.reconstruct.pipeline import build
from manisplat.reconstruct.plan import make_plan

FRAMES = [4, 12]


@pytest.fixture(scope="module")
def episode(tmp_path_factory):
    return write_two_arm_sample_episode(tmp_path_factory.mktemp("close_ups") / "ep", duration=2.0, wrist_cameras=True)


@pytest.fixture(scope="module")
def wrist(episode):
    return load_episode_data(episode, camera="cam_left_wrist", load_meshes=False)


def own_points(view, frames, stride):
    """The view's static points at ``stride`` and their spacing (m), as seeds."""
    points, spacing = [], []
    for f in frames:
        keep = view.region(f, view.labels.static)
        T_base_cam = torch.linalg.inv(view.view_at(f).double())
        p, rows, cols = backproject(view.depth[f], view.K_opencv, T_base_cam, keep, stride)
        points.append(p)
        spacing.append(sample_spacing(view.depth[f], rows, cols, view.K_opencv, stride))
    return torch.cat(points), torch.cat(spacing)


def test_close_ups_are_static_surface_points_where_the_camera_saw_them(wrist):
    coarse = torch.tensor([[0.0, 0.0, 0.0]]), torch.tensor([10.0])  # one seed 10 m wide covers everything
    points, colours, spacing = close_up_points(wrist, FRAMES[:1], *coarse)
    assert len(points) > 100 and colours.shape == points.shape and (spacing > 0).all()
    f = FRAMES[0]
    V, K = wrist.view_at(f).double(), wrist.K_opencv.double()
    cam = points.double() @ V[:3, :3].T + V[:3, 3]
    u = (cam[:, 0] / cam[:, 2] * K[0, 0] + K[0, 2]).round().long()
    v = (cam[:, 1] / cam[:, 2] * K[1, 1] + K[1, 2]).round().long()
    depth = wrist.depth[f][v, u].double()
    assert (cam[:, 2] - depth).abs().max() < 1e-3, "each point lies where the frame's depth put it"
    assert wrist.region(f, wrist.labels.static)[v, u].all(), "robot and object pixels seed nothing"


def test_only_what_the_seeds_show_more_coarsely_is_added(wrist):
    fine = own_points(wrist, FRAMES, stride=1)  # seeds 4 times as fine as the close-ups' stride
    assert len(close_up_points(wrist, FRAMES, *fine)[0]) == 0
    coarse = own_points(wrist, FRAMES, stride=16)  # the same surfaces, 4 times as coarse
    added = close_up_points(wrist, FRAMES, *coarse)[0]
    assert len(added) > 0.5 * len(own_points(wrist, FRAMES[:1], stride=4)[0])


def test_a_surface_two_frames_show_is_added_once(wrist):
    coarse = torch.tensor([[0.0, 0.0, 0.0]]), torch.tensor([10.0])
    once = close_up_points(wrist, FRAMES[:1], *coarse)[0]
    twice = close_up_points(wrist, FRAMES[:1] * 2, *coarse)[0]
    assert len(twice) == len(once)


def test_points_in_space_the_fixed_camera_saw_past_are_found(episode):
    """A point 5 cm in front of a static surface the head camera saw (a riding camera's pixel at
    a moving part's edge) is in empty space; on the surface or behind it (hidden) it is not."""
    head = load_episode_data(episode, load_meshes=False)
    f = FRAMES[0]
    keep = head.region(f, head.labels.static)
    surface, rows, cols = backproject(head.depth[f], head.K_opencv, torch.linalg.inv(head.viewmat.double()), keep, 8)
    eye = torch.linalg.inv(head.viewmat.double())[:3, 3]
    ray = surface.double() - eye
    ray = ray / ray.norm(dim=1, keepdim=True)
    in_front, behind = (surface.double() - 0.05 * ray).float(), (surface.double() + 0.05 * ray).float()
    assert seen_through(head, [f], in_front).float().mean() > 0.95
    assert not seen_through(head, [f], surface).any()
    assert not seen_through(head, [f], behind).any()


def test_close_ups_in_space_the_fixed_camera_saw_past_are_left_out(episode):
    """A wrist camera's depth 10 % short in one frame puts its close-ups in the air above the
    table: the head camera saw the table through them, so none seeds the background."""
    head = load_episode_data(episode, load_meshes=False)
    wrist = load_episode_data(episode, camera="cam_left_wrist", load_meshes=False)
    f = FRAMES[0]
    wrist.depth[f] *= 0.9
    floating = close_up_points(wrist, [f], torch.zeros(1, 3), torch.full((1,), 10.0))[0]
    assert seen_through(head, [f], floating).sum() > 50
    background = background_gaussians(head, frames=[f], riding=[wrist])
    assert not seen_through(head, [f], background.params["means"].detach()).any()


def test_a_camera_without_depth_cannot_seed_close_ups(episode):
    view = load_episode_data(episode, camera="cam_left_wrist", use_depth=False, load_meshes=False)
    with pytest.raises(ValueError, match="cam_left_wrist: close-up seeds need its depth"):
        close_up_points(view, FRAMES, torch.zeros(1, 3), torch.ones(1))


@pytest.fixture(scope="module")
def builds(episode):
    """The sample's reconstruction built without and with its two wrist cameras."""
    def built(with_wrists: bool):
        data = load_episode_data(episode)
        views = {name: load_episode_data(episode, camera=name) for name in ("cam_left_wrist", "cam_right_wrist")}
        return build(data, make_plan(data), TrainConfig(iters=1), views=views if with_wrists else None)[0]

    return built(False), built(True)


def test_the_wrist_cameras_add_to_the_fixed_camera_s_background_seeds(builds):
    alone, with_wrists = (len(rec.graph.background) for rec in builds)
    assert with_wrists > 1.1 * alone, (alone, with_wrists)


def test_the_wrist_cameras_add_to_the_objects_seeds(builds):
    alone, with_wrists = ({name: len(g) for name, g in rec.graph.objects.items()} for rec in builds)
    assert set(alone) == {"box_left", "box_right"}
    assert all(with_wrists[name] > 1.1 * alone[name] for name in alone), (alone, with_wrists)
