"""Object trajectories (shared static twists, held-out interpolation) and the evaluation metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from manisplat.geometry import make_transform, se3_exp, so3_exp
from manisplat.reconstruct.metrics import fit_constant_offset, pose_errors, psnr, ssim, start_anchored_errors
from manisplat.reconstruct.poses import ObjectTrajectory, TwistAdam


def test_static_stretches_share_one_twist_and_moving_frames_get_their_own():
    pseudo = np.repeat(np.eye(4)[None], 10, axis=0)
    source = ["static"] * 4 + ["tracked"] * 3 + ["static"] * 3
    traj = ObjectTrajectory(pseudo, source)
    assert traj.n_params == 1 + 3 + 1
    assert traj.index.tolist() == [0, 0, 0, 0, 1, 2, 3, 4, 4, 4]
    assert ObjectTrajectory(pseudo, source, static=True).n_params == 1


def _pull(traj: ObjectTrajectory, opt: TwistAdam, frame: int, target: float = 0.01) -> None:
    """One step pulling ``frame``'s pose towards x = ``target`` (m)."""
    (traj.pose(frame)[0, 3] - target).square().backward()
    opt.step(frame)


def test_only_the_twists_of_the_rendered_frame_step():
    """A frame's twist moves when its frame is rendered and keeps its value while other frames
    are (a dense Adam kept moving it on its momentum)."""
    traj = ObjectTrajectory(np.repeat(np.eye(4)[None], 4, axis=0), ["tracked"] * 4)
    opt = TwistAdam({"box": traj}, lr=1e-3)
    _pull(traj, opt, 1)
    assert traj.xi[1, 0].item() == pytest.approx(1e-3)  # Adam's first step: the learning rate
    _pull(traj, opt, 1)
    after_frame_1 = traj.xi.detach().clone()
    for _ in range(5):
        _pull(traj, opt, 2)
    assert torch.equal(traj.xi[1], after_frame_1[1])
    assert traj.xi[2, 0].item() > 4e-3 and torch.count_nonzero(traj.xi[[0, 3]]) == 0
    assert opt.steps["box"] == [0, 2, 5, 0]


def test_a_twist_steps_at_the_given_fraction_of_its_learning_rate():
    traj = ObjectTrajectory(np.repeat(np.eye(4)[None], 2, axis=0), ["tracked"] * 2)
    opt = TwistAdam({"box": traj}, lr=1e-3)
    (traj.pose(0)[0, 3] - 0.01).square().backward()
    opt.step(0, scale=0.1)
    assert traj.xi[0, 0].item() == pytest.approx(1e-4)  # Adam's first step: the scaled rate
    assert opt.lr == 1e-3  # the base rate kept (a schedule passes its factor each step)


def test_the_twist_optimizer_continues_from_its_state():
    def run(split: bool) -> torch.Tensor:
        traj = ObjectTrajectory(np.repeat(np.eye(4)[None], 3, axis=0), ["tracked"] * 3)
        opt = TwistAdam({"box": traj})
        for i, frame in enumerate([0, 1, 0, 0, 1, 0]):
            if split and i == 3:
                state, opt = opt.state_dict(), TwistAdam({"box": traj}, lr=1.0)
                opt.load_state_dict(state)
            _pull(traj, opt, frame)
        return traj.xi.detach()

    assert torch.equal(run(split=False), run(split=True))
    traj = ObjectTrajectory(np.repeat(np.eye(4)[None], 3, axis=0), ["tracked"] * 3)
    other = TwistAdam({"box": ObjectTrajectory(np.repeat(np.eye(4)[None], 5, axis=0), ["tracked"] * 5)})
    with pytest.raises(ValueError, match="5 pose twists"):
        TwistAdam({"box": traj}).load_state_dict(other.state_dict())


def test_held_out_frames_interpolate_the_trained_neighbours():
    pseudo = np.repeat(np.eye(4)[None], 5, axis=0)
    traj = ObjectTrajectory(pseudo, ["tracked"] * 5)
    with torch.no_grad():
        traj.xi[1] = torch.tensor([0.01, 0, 0, 0, 0, 0], dtype=torch.float64)
        traj.xi[3] = torch.tensor([0.03, 0, 0, 0, 0, 0], dtype=torch.float64)
        traj.xi[2] = 5.0  # never trained: must be ignored
    poses = traj.evaluation_poses(trained=[1, 3])
    assert abs(poses[2][0, 3] - 0.02) < 1e-12
    assert abs(poses[0][0, 3] - 0.01) < 1e-12 and abs(poses[4][0, 3] - 0.03) < 1e-12
    assert traj.pose_loss(1).item() == (0.01 / 0.01) ** 2


def test_smoothing_neighbours_are_the_nearest_trained_frames_of_the_same_stretch_and_episode():
    source = ["static"] * 4 + ["attached"] * 5 + ["tracked"] * 3 + ["static"] * 3
    traj = ObjectTrajectory(np.repeat(np.eye(4)[None], 15, axis=0), source, episode_starts=(0, 7))
    neighbours = traj.trained_neighbours([0, 2, 4, 5, 7, 8, 9, 11, 12, 14])
    twist = traj._twist_of
    # frame 4 (attached) looks past the static frame 3 for nothing; 5 has 4 before it and no
    # trained frame after it in its episode's stretch (6 is held out, 7 starts another episode)
    assert neighbours[4] == (twist[5],) and neighbours[5] == (twist[4],)
    assert neighbours[7] == (twist[8],) and neighbours[8] == (twist[7],)
    assert neighbours[9] == (twist[11],) and neighbours[11] == (twist[9],)  # tracked: 10 held out
    assert not {0, 2, 12, 14} & neighbours.keys()  # static stretches share one twist: nothing to smooth


def test_the_smoothness_loss_pulls_a_frame_towards_its_neighbours_mean_and_nothing_else():
    traj = ObjectTrajectory(np.repeat(np.eye(4)[None], 3, axis=0), ["tracked"] * 3)
    with torch.no_grad():
        traj.xi[0, 0], traj.xi[1, 0], traj.xi[2, 0] = 0.001, 0.004, 0.003
    neighbours = traj.trained_neighbours([0, 1, 2])
    assert neighbours == {0: (1,), 1: (0, 2), 2: (1,)}
    loss = traj.smoothness_loss(1, neighbours[1])
    assert loss.item() == pytest.approx(((0.004 - 0.002) / 0.01) ** 2)
    loss.backward()
    assert traj.xi.grad[1, 0] > 0 and torch.count_nonzero(traj.xi.grad[[0, 2]]) == 0
    with torch.no_grad():
        traj.xi[1, 0] = 0.002
    assert traj.smoothness_loss(1, neighbours[1]).item() == 0


def test_pose_errors_remove_one_constant_offset():
    rng = torch.Generator().manual_seed(0)
    gt = torch.stack([make_transform(so3_exp(torch.randn(3, dtype=torch.float64, generator=rng)),
                                     torch.randn(3, dtype=torch.float64, generator=rng)) for _ in range(20)]).numpy()
    X = se3_exp(torch.tensor([0.05, -0.02, 0.01, 0.3, -0.2, 0.1], dtype=torch.float64)).numpy()
    ours = gt @ np.linalg.inv(X)  # our canonical frame differs by X
    assert np.allclose(fit_constant_offset(ours, gt), X, atol=1e-10)
    err = pose_errors(ours, gt)
    assert err["et_cm"] < 1e-8 and err["er_deg"] < 1e-6
    noisy = ours.copy()
    noisy[:, 0, 3] += 0.01
    assert 0.5 < pose_errors(noisy, gt)["et_cm"] <= 1.0 + 1e-9


def test_start_anchored_error_shows_what_the_fitted_offset_absorbs():
    """An object that rests 10 frames, is carried 10 cm, and is placed: our estimate is right at
    rest but 1 cm off along x once it moves (a drift the fitted offset halves and hides)."""
    T = 30
    gt = np.repeat(np.eye(4)[None], T, axis=0)
    gt[10:20, 0, 3] = np.linspace(0.01, 0.1, 10)
    gt[20:, 0, 3] = 0.1
    X = se3_exp(torch.tensor([0.02, 0.0, -0.01, 0.0, 0.0, 0.4], dtype=torch.float64)).numpy()
    ours = gt @ np.linalg.inv(X)
    ours[10:, 0, 3] += 0.01
    phases = [("M_approach", 0, 10), ("M_transfer", 10, 20), ("M_return", 20, 30)]
    anchored = start_anchored_errors(ours, gt, phases)
    assert anchored["moved_frames"] == 20  # from the first frame 5 mm away from the start
    assert abs(anchored["et_cm"] - 1.0) < 1e-9 and anchored["er_deg"] < 1e-6
    assert abs(anchored["final"]["et_cm"] - 1.0) < 1e-9
    assert anchored["phases"]["M_approach"]["et_cm"] < 1e-9 and abs(anchored["phases"]["M_return"]["et_cm"] - 1.0) < 1e-9
    assert pose_errors(ours, gt)["et_cm"] < 0.6  # the fitted offset splits the drift
    assert start_anchored_errors(np.repeat(np.eye(4)[None], 5, axis=0), np.repeat(np.eye(4)[None], 5, axis=0)) is None


def test_psnr_and_ssim_over_regions():
    target = torch.full((20, 30, 3), 0.5)
    pred = target.clone()
    pred[:10] += 0.1
    region = torch.zeros(20, 30, dtype=torch.bool)
    region[10:] = True
    assert math.isinf(psnr(pred, target, region)) is False and psnr(pred, target, region) > 100
    assert abs(psnr(pred, target) - (-10 * math.log10(0.5 * 0.01))) < 1e-4
    assert ssim(target, target) > 0.999 and math.isnan(psnr(pred, target, torch.zeros_like(region)))


def test_the_smoothness_weight_is_on_with_a_riding_camera_unless_given():
    from manisplat.reconstruct.config import resolve_lambda_smooth

    assert resolve_lambda_smooth(None, riding=True) == 1.0
    assert resolve_lambda_smooth(None, riding=False) == 0.0
    assert resolve_lambda_smooth(0.3, riding=True) == 0.3 and resolve_lambda_smooth(0.0, riding=True) == 0.0
