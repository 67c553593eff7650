"""Few tensor operations per training iteration: on a GPU each is a kernel launch, and launches,
not arithmetic, bound a small scene's iteration (issue 35). Counted on the CPU, where the count is
the same."""

from __future__ import annotations

import pytest
import torch

from manisplat.episode.synthetic import write_sample_episode
from manisplat.geometry import matrix_to_quat, quat_multiply, random_rotations
from manisplat.reconstruct.config import TrainConfig
from manisplat.reconstruct.data import load_episode_data
from manisplat.reconstruct.poses import pose_penalty, twist_exp
from manisplat.reconstruct.pipeline import build
from manisplat.reconstruct.plan import make_plan
from manisplat.reconstruct.tensor_ops import TensorOpCounter
from manisplat.splat.sh import spherical_harmonics


def ops_of(fn, *inputs: torch.Tensor) -> int:
    """Tensor operations of ``fn(*inputs)`` and its backward (after a first call: constants cached)."""
    fn(*inputs)
    leaves = [x.detach().requires_grad_() for x in inputs]
    with TensorOpCounter() as ops:
        fn(*leaves).sum().backward()
    return ops.total


@pytest.mark.parametrize("batch", [3, 3000])
def test_the_placements_rotation_algebra_is_a_fixed_handful_of_ops(batch):
    g = torch.Generator().manual_seed(batch)
    R = random_rotations(batch, generator=g)
    q = torch.nn.functional.normalize(torch.randn(batch, 4, dtype=torch.float64, generator=g), dim=-1)
    assert ops_of(matrix_to_quat, R) <= 45  # 37; kornia's conversion by cases: 363
    assert ops_of(quat_multiply, q, q.flip(0)) <= 12  # 9; written out per component: 95
    coeffs = torch.randn(batch, 16, 3, dtype=torch.float64, generator=g)
    assert ops_of(lambda d, c: spherical_harmonics(3, d, c), q[:, :3], coeffs) <= 50  # 41; term by term: 280


@pytest.mark.parametrize("angle", [0.0, 1e-6, 0.1, 3.0])
def test_an_object_pose_correction_is_a_fixed_handful_of_ops(angle):
    xi = torch.tensor([0.01, -0.02, 0.005, angle, -0.5 * angle, 0.25 * angle], dtype=torch.float64)
    assert ops_of(twist_exp, xi) <= 90  # 79 either side of the Taylor switch; element by element: 135
    assert ops_of(pose_penalty, xi) <= 10  # 8; as two norms: 28


def test_a_training_iteration_issues_few_tensor_ops(tmp_path):
    episode = write_sample_episode(tmp_path / "ep", frames=24, width=80, height=60)
    data = load_episode_data(episode)
    rec, _ = build(data, make_plan(data), TrainConfig(iters=12, shadow_start=4, refine_start=10 ** 6, sh_every=3,
                                                        eval_every=100, log_every=5, compile="off"))
    rec.train(progress=False)  # shadows on, every SH band in use
    ops = rec.tensor_ops(4)
    per_iteration = ops.total / 4
    # 1 470 before the rotations and the SH basis became matrix products (the sample at 160x120)
    assert per_iteration <= 950, f"{per_iteration:.0f} tensor ops per iteration: {ops.counts.most_common(12)}"
    assert rec.step == 16
