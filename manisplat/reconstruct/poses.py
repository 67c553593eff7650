"""Trainable object trajectories around the pseudo ground truth.

``T_obj(t) = T_pseudo(t) @ exp(xi_k(t))`` with a correction twist ``xi`` (object frame): one shared
by every frame of a static stretch (an object at rest has one pose), one per frame where it moves.
The pose loss is the squared SE(3) distance to the pseudo pose in units of ``sigma_t`` and
``sigma_r``; the smoothness loss the same distance between a moving frame's correction and the
mean of its trained neighbours' in the same stretch (the pseudo ground truth's errors drift, they
do not jump from frame to frame). Held-out frames are never rendered in training, so their
corrections are interpolated from the nearest trained frames of the same stretch.

The twists are stepped by :class:`TwistAdam`, which moves only the twists the rendered frame used
(a twist table in a dense Adam moves every row on its momentum each iteration, though one frame
was rendered).
"""

from __future__ import annotations

import numpy as np
import torch

from manisplat.align.pseudo_gt import STATIC
from manisplat.compilation import compilable, constant_tensor
from manisplat.geometry import se3_exp
from manisplat.geometry.rotation import hat

SIGMA_T = 0.01  # m
SIGMA_R = 0.05  # rad (about 3 deg)


class ObjectTrajectory(torch.nn.Module):
    """Per-frame object poses: pseudo poses [T, 4, 4] plus trainable twists.

    Args:
        pseudo: T_base_obj [T, 4, 4] (float64).
        source: per frame "static", "attached" or "tracked"; consecutive static frames share a twist.
        static: the object never moves: one twist for the whole episode.
        episode_starts: the first frames of the episodes a fused recording joins
            (:mod:`manisplat.reconstruct.fusion`): no twist is shared across one, and a held-out
            frame's twist is interpolated within its own episode.
    """

    def __init__(self, pseudo: np.ndarray, source: list[str], *, static: bool = False,
                 episode_starts: tuple[int, ...] = (0,)) -> None:
        super().__init__()
        T = len(pseudo)
        index, k = np.zeros(T, dtype=np.int64), -1
        starts = set(episode_starts)
        for i in range(T):
            shared = i not in starts and (static or (source[i] == STATIC and source[i - 1] == STATIC))
            if not (shared and k >= 0):
                k += 1
            index[i] = k
        self.register_buffer("pseudo", torch.as_tensor(np.asarray(pseudo), dtype=torch.float64))
        self.register_buffer("index", torch.as_tensor(index))
        self._twist_of = index.tolist()  # frame -> twist on the host: looking one up reads nothing back from a GPU
        #: per frame, the episode it belongs to (index into ``episode_starts``, sorted)
        self._episode_of = np.searchsorted(np.array(sorted(starts | {0})), np.arange(T), side="right") - 1
        self.xi = torch.nn.Parameter(torch.zeros(k + 1, 6, dtype=torch.float64))
        self._source = list(source)

    @property
    def n_params(self) -> int:
        return len(self.xi)

    def pose(self, t: int) -> torch.Tensor:
        """T_base_obj [4, 4] (float64, on the trajectory's device) at frame ``t``."""
        return corrected_pose(self.pseudo[t], self.twist(t))

    def twist(self, t: int) -> torch.Tensor:
        """[6] float64 the correction twist of frame ``t`` (a view of the trained table)."""
        return self.xi[self._twist_of[t]]

    def pose_loss(self, t: int) -> torch.Tensor:
        """[] float64: the squared SE(3) distance of frame ``t``'s correction, in sigma units."""
        return pose_penalty(self.twist(t))

    def trained_neighbours(self, trained: list[int]) -> dict[int, tuple[int, ...]]:
        """Trained frame -> the twists (indices) of the nearest trained frames before and after it
        that have twists of their own, within its stretch: the same episode and the same pseudo
        source (a grasp or a release may change the correction at once). Frames of a static
        stretch, which share one twist, have none."""
        trained_set, T = set(trained), len(self._source)
        neighbours = {}
        for i in sorted(trained_set):
            found = []
            for step in (-1, 1):
                j = i + step
                while 0 <= j < T and self._episode_of[j] == self._episode_of[i] and self._source[j] == self._source[i]:
                    if j in trained_set and self._twist_of[j] != self._twist_of[i]:
                        found.append(self._twist_of[j])
                        break
                    j += step
            if found:
                neighbours[i] = tuple(found)
        return neighbours

    def smoothness_loss(self, t: int, neighbours: tuple[int, ...]) -> torch.Tensor:
        """[] float64: the squared SE(3) distance (sigma units) of frame ``t``'s correction to the
        mean of its neighbours' twists (indices, from :meth:`trained_neighbours`), those held
        fixed: only frame ``t``'s twist is pulled."""
        mean = sum(self.xi[k] for k in neighbours).detach() / len(neighbours)
        return pose_penalty(self.twist(t) - mean)

    @torch.no_grad()
    def evaluation_poses(self, trained: list[int]) -> np.ndarray:
        """Poses [T, 4, 4] for every frame; frames whose own twist was never trained take the
        twist interpolated (linearly, in time) between the nearest trained frames of its episode."""
        trained_twists = {self._twist_of[j] for j in trained}
        anchors_of: dict[int, list[int]] = {}  # episode -> its trained frames, in order
        for j in sorted(trained):
            anchors_of.setdefault(int(self._episode_of[j]), []).append(j)
        xi = self.xi.detach().cpu()[self.index.cpu()]  # [T, 6] (a copy), on the host: a per-frame loop
        for i in range(len(xi)):
            if self._twist_of[i] in trained_twists:
                continue
            anchors = anchors_of.get(int(self._episode_of[i]))
            if not anchors:
                continue
            left = max((j for j in anchors if j < i), default=None)
            right = min((j for j in anchors if j > i), default=None)
            if left is None or right is None:  # before the first or after the last trained frame
                xi[i] = xi[right if left is None else left]
            else:
                w = (i - left) / (right - left)
                xi[i] = (1 - w) * xi[left] + w * xi[right]
        return (self.pseudo.cpu() @ se3_exp(xi)).numpy()


class TwistAdam:
    """Adam over the trajectories' twist tables in which an iteration steps only the twists its
    frame used; each twist keeps its own moments and step count (gsplat's ``SelectiveAdam`` does
    the same for Gaussians out of view).

    In one dense Adam a frame's twist, rendered about once per hundred iterations, kept moving on
    its momentum in the iterations between, each step as large as the learning rate: single
    frames of the test set's pick-and-places came out 5-10 mm off the pseudo ground truth their
    neighbours kept (``benchmarks/bench_reconstruct_testset.py``).
    """

    def __init__(self, trajectories: dict[str, ObjectTrajectory], *, lr: float = 5e-4,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8) -> None:
        self.trajectories, self.lr, self.betas, self.eps = trajectories, lr, betas, eps
        self.exp_avg = {k: torch.zeros_like(t.xi) for k, t in trajectories.items()}
        self.exp_avg_sq = {k: torch.zeros_like(t.xi) for k, t in trajectories.items()}
        #: steps taken by each twist, on the host (bias correction without reading the device)
        self.steps = {k: [0] * t.n_params for k, t in trajectories.items()}

    @torch.no_grad()
    def step(self, frame: int, scale: float = 1.0) -> None:
        """Step the twists frame ``frame`` used from their gradients, at ``scale`` times the learning
        rate (the training's decay), then clear the gradients."""
        b1, b2 = self.betas
        for name, traj in self.trajectories.items():
            if traj.xi.grad is None:
                continue
            k = traj._twist_of[frame]
            g, m, v = traj.xi.grad[k], self.exp_avg[name][k], self.exp_avg_sq[name][k]
            n = self.steps[name][k] = self.steps[name][k] + 1
            m.mul_(b1).add_(g, alpha=1 - b1)
            v.mul_(b2).addcmul_(g, g, value=1 - b2)
            denom = (v / (1 - b2 ** n)).sqrt_().add_(self.eps)
            traj.xi[k].addcdiv_(m, denom, value=-self.lr * scale / (1 - b1 ** n))
            traj.xi.grad = None

    def state_dict(self) -> dict:
        return {"exp_avg": {k: v.detach().clone() for k, v in self.exp_avg.items()},
                "exp_avg_sq": {k: v.detach().clone() for k, v in self.exp_avg_sq.items()},
                "steps": {k: list(v) for k, v in self.steps.items()}, "lr": self.lr}

    def load_state_dict(self, state: dict) -> None:
        """Continue from :meth:`state_dict` (moments moved to the twists' device)."""
        for name, traj in self.trajectories.items():
            if len(state["steps"][name]) != traj.n_params:
                raise ValueError(f"object {name}: the checkpoint has {len(state['steps'][name])} pose twists, "
                                 f"this reconstruction {traj.n_params}")
            self.exp_avg[name] = state["exp_avg"][name].to(traj.xi.device)
            self.exp_avg_sq[name] = state["exp_avg_sq"][name].to(traj.xi.device)
            self.steps[name] = list(state["steps"][name])
        self.lr = state["lr"]


#: the inverse squared sigmas of a twist's (v, w) components
_PENALTY_WEIGHTS = (1 / SIGMA_T ** 2,) * 3 + (1 / SIGMA_R ** 2,) * 3


def pose_penalty(xi: torch.Tensor) -> torch.Tensor:
    """[] the squared SE(3) distance of a correction twist [6] in units of SIGMA_T and SIGMA_R
    (a weighted sum of squares: two tensor operations, every iteration for every object)."""
    return (xi * xi) @ constant_tensor(_PENALTY_WEIGHTS, xi.dtype, xi.device)


@compilable
def corrected_pose(pseudo: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
    """[4, 4] ``pseudo @ exp(xi)``: a pose [4, 4] corrected by a twist [6] in its own frame."""
    return pseudo @ twist_exp(xi)


#: Taylor series of (sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3) in t^2: constant, t^2 term
_SERIES = ((1.0, 0.5, 1.0 / 6.0), (-1.0 / 6.0, -1.0 / 24.0, -1.0 / 120.0))
#: R = I + a W + b W^2 and V = I + b W + c W^2 pick from (1, a, b, c)
_PICK = ((0, 1, 2), (0, 2, 3))
_ONE, _BOTTOM = (1.0,), ((0.0, 0.0, 0.0, 1.0),)
_EYE = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def twist_exp(xi: torch.Tensor) -> torch.Tensor:
    """[4, 4] exp of one twist ``xi`` [6] = (v, w), as :func:`manisplat.geometry.se3_exp`, in a
    couple of dozen tensor operations (Rodrigues; Taylor series below 1e-4 rad, both branches
    finite and differentiable). Used in every training iteration: kornia's generic version issues
    about ten times the GPU kernels."""
    dtype, device = xi.dtype, xi.device
    v, w = xi[:3], xi[3:]
    theta2 = w @ w
    small = theta2 < 1e-8
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = safe2.sqrt()
    sin = torch.sin(theta)
    exact = torch.stack([sin, 1 - torch.cos(theta), theta - sin]) / torch.stack([theta, safe2, safe2 * theta])
    series = constant_tensor(_SERIES, dtype, device)
    coefficients = torch.where(small, series[0] + series[1] * theta2, exact)  # a, b, c
    picks = torch.cat([constant_tensor(_ONE, dtype, device), coefficients])[constant_tensor(_PICK, torch.long, device)]
    W = hat(w)
    powers = torch.stack([constant_tensor(_EYE, dtype, device), W, W @ W]).view(3, 9)
    R, V = (picks @ powers).view(2, 3, 3).unbind(0)
    return torch.cat([torch.cat([R, (V @ v)[:, None]], dim=1), constant_tensor(_BOTTOM, dtype, device)])
