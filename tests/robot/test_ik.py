"""Batched IK on the built-in PiPER: success on reachable targets, honest failure on
unreachable ones, limits always respected, branch kept with a good initial guess."""

from __future__ import annotations

import pytest
import torch

from manisplat.geometry import make_transform, pose_error
from manisplat.robot import RobotModelError, builtin_piper, solve_ik


@pytest.fixture(scope="module")
def piper():
    return builtin_piper(with_geometry=False)


def test_solves_random_reachable_targets(piper):
    q_true = piper.sample_configurations(300, generator=torch.Generator().manual_seed(10))
    targets = piper.tcp_pose(q_true)
    result = solve_ik(piper, targets)
    assert float(result.success.float().mean()) >= 0.99
    assert bool(piper.within_limits(result.q).all())
    t_err, r_err = pose_error(piper.tcp_pose(result.q), targets)
    ok = result.success
    assert float(t_err[ok].max()) <= 1e-4 and float(r_err[ok].max()) <= 1e-3
    assert torch.allclose(t_err, result.position_error) and torch.allclose(r_err, result.rotation_error, atol=1e-12)
    assert float(t_err[ok].median()) < 1e-6  # polished far below the tolerance, not stopped at it


def test_a_targets_result_does_not_depend_on_its_batch(piper):
    q_true = piper.sample_configurations(64, generator=torch.Generator().manual_seed(13))
    targets = piper.tcp_pose(q_true)
    batch = solve_ik(piper, targets)
    for i in (0, 17, 42):
        alone = solve_ik(piper, targets[i])
        assert torch.allclose(alone.q, batch.q[i], atol=1e-9) and int(alone.attempts) == int(batch.attempts[i])


def test_unreachable_target_fails_honestly(piper):
    far = make_transform(torch.eye(3, dtype=torch.float64), torch.tensor([2.0, 0.0, 0.5], dtype=torch.float64))
    result = solve_ik(piper, far, restarts=8)
    assert not bool(result.success)
    assert float(result.position_error) > 1.0 and torch.isfinite(result.q).all()
    assert bool(piper.within_limits(result.q))
    assert int(result.attempts) == 9


def test_good_initial_guess_keeps_the_branch(piper):
    q_true = piper.sample_configurations(50, generator=torch.Generator().manual_seed(11))
    noisy = q_true + 0.02 * torch.randn(q_true.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(12))
    result = solve_ik(piper, piper.tcp_pose(q_true), q_init=piper.clamp(noisy), restarts=0)
    assert bool(result.success.all())
    # Same branch: a wrist flip moves joints 4 and 6 by ~pi. Near the wrist singularity (q5 ~ 0)
    # joints 4 and 6 trade off within the pose tolerance, so allow a few hundredths of a radian.
    assert float((result.q - q_true).abs().max()) < 0.05
    assert bool((result.attempts == 1).all())


def test_single_target_and_bad_input(piper):
    q = torch.tensor([0.3, 1.2, -1.0, 0.1, 0.4, -0.2], dtype=torch.float64)
    result = solve_ik(piper, piper.tcp_pose(q))
    assert result.q.shape == (6,) and bool(result.success)
    bad = piper.tcp_pose(q).clone()
    bad[0, 3] = float("nan")
    with pytest.raises(RobotModelError, match="NaN"):
        solve_ik(piper, bad)
    with pytest.raises(RobotModelError, match=r"\[B, 4, 4\]"):
        solve_ik(piper, torch.zeros(3, 3, dtype=torch.float64))
