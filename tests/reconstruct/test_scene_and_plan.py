"""The scene graph places each node's Gaussians where its frame is; the plan skips what a scene
does not need (links never seen, repeated states)."""

from __future__ import annotations

import math

import pytest
import torch

from manisplat.episode.synthetic import write_sample_episode
from manisplat.geometry import make_transform, quat_to_matrix, so3_exp
from manisplat.reconstruct.data import load_episode_data
from manisplat.reconstruct.pipeline import build
from manisplat.reconstruct.plan import make_plan
from manisplat.reconstruct.trainer import TrainConfig
from manisplat.scene.gaussians import GaussianSet
from manisplat.scene.graph import BACKGROUND, ROBOT, SceneGraph
from manisplat.scene.transforms import transform_gaussians


def _covariances(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    R = quat_to_matrix(quats / quats.norm(dim=-1, keepdim=True))
    return R @ torch.diag_embed(scales**2) @ R.transpose(-1, -2)


def _random_pose(gen: torch.Generator) -> torch.Tensor:
    R = so3_exp(torch.randn(3, generator=gen, dtype=torch.float64) * 1.5)
    return make_transform(R, torch.randn(3, generator=gen, dtype=torch.float64))


def test_a_rigid_transform_moves_means_and_rotates_covariances():
    gen = torch.Generator().manual_seed(0)
    means = torch.randn(50, 3, generator=gen, dtype=torch.float64)
    quats = torch.randn(50, 4, generator=gen, dtype=torch.float64)
    scales = torch.rand(50, 3, generator=gen, dtype=torch.float64) + 0.1
    T = _random_pose(gen)
    moved, moved_quats = transform_gaussians(T, means, quats)
    R, t = T[:3, :3], T[:3, 3]
    torch.testing.assert_close(moved, means @ R.T + t, rtol=0, atol=1e-12)
    # the covariance seen from the new frame is R Sigma R^T: the shape rides with the frame
    torch.testing.assert_close(_covariances(moved_quats, scales), R @ _covariances(quats, scales) @ R.T, rtol=0, atol=1e-12)


def _gaussians(points: torch.Tensor) -> GaussianSet:
    return GaussianSet.from_points(points, torch.full_like(points, 0.5), 0.01)


def test_compose_places_links_by_their_poses_and_objects_by_theirs():
    gen = torch.Generator().manual_seed(1)
    local = torch.randn(4, 3, generator=gen)
    graph = SceneGraph(_gaussians(local), {"link2": _gaussians(local), "link1": _gaussians(local[:2])},
                       ["link1", "link2"], {"box": _gaussians(local[:3])})
    link_poses = torch.stack([_random_pose(gen), _random_pose(gen)]).float()
    T_box = _random_pose(gen).float()
    g = graph.compose(link_poses, {"box": T_box})
    expected = {
        "background": local,
        "robot/link2": local @ link_poses[1, :3, :3].T + link_poses[1, :3, 3],  # by name, not by order of insertion
        "robot/link1": local[:2] @ link_poses[0, :3, :3].T + link_poses[0, :3, 3],
        "object/box": local[:3] @ T_box[:3, :3].T + T_box[:3, 3],
    }
    assert list(g.slices) == list(expected)
    for name, points in expected.items():
        start, end = g.slices[name]
        torch.testing.assert_close(g.means[start:end], points, rtol=0, atol=1e-5)
    assert g.groups.tolist() == [BACKGROUND] * 4 + [ROBOT] * 6 + [2] * 3


def test_links_outside_the_robot_are_refused():
    with pytest.raises(ValueError, match="not in the robot's link order"):
        SceneGraph(None, {"gripper_base": _gaussians(torch.zeros(1, 3))}, ["link1"], {})


@pytest.fixture(scope="module")
def pick(tmp_path_factory):
    return write_sample_episode(tmp_path_factory.mktemp("pick") / "ep", frames=24, width=80, height=60)


def test_a_link_never_seen_gets_no_gaussians(pick):
    data = load_episode_data(pick)
    hidden = next(name for name in make_plan(data).links if name != "base_link")
    value = next(v for v, name in data.labels.robot.items() if name == hidden)
    data.masks[data.masks == value] = 0  # as if the link were always out of view
    plan = make_plan(data)
    assert hidden in plan.skipped_links and hidden not in plan.links
    assert "never visible" in plan.summary()
    rec, _ = build(data, plan, TrainConfig(iters=1))
    assert hidden not in rec.graph.links and len(rec.graph.links) == len(plan.links)


def test_frames_that_repeat_a_still_state_are_trained_once(pick):
    data = load_episode_data(pick)
    before = make_plan(data).distinct_train_states
    assert len(before) == len(make_plan(data).train_frames)  # the sample never pauses
    for i in range(10, 16):  # the arm pauses after frame 9: state and image repeat
        data.q[i], data.gripper[i], data.rgb[i] = data.q[9], data.gripper[9], data.rgb[9]
    plan = make_plan(data)
    assert plan.distinct_train_states == [i for i in before if not 10 <= i < 16]
    assert f"{len(before) - len(plan.distinct_train_states)} frames repeat" in plan.summary()


def test_a_still_arm_over_a_moving_object_keeps_its_frames(pick):
    data = load_episode_data(pick)
    for i in range(10, 16):  # the joints repeat but the images differ: something else moved
        data.q[i], data.gripper[i] = data.q[9], data.gripper[9]
    plan = make_plan(data)
    assert any(o.moves for o in plan.objects)
    assert len(plan.distinct_train_states) == len(plan.train_frames)
    assert not math.isnan(plan.objects[0].displacement_m)
