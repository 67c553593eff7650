"""Skills moved rigidly with their object: ``T_tcp'(s) = D @ T_tcp(s)``, ``D = T_new @ inv(T_src)``,
solved by IK frame by frame.

The first frame is seeded with the source's joints there (falling back to restarts), every later
one with the previous solution plus the source's own joint step (a predictor that keeps the
branch and converges in 2-3 iterations). A skill keeps its recorded timing (one new frame per
source frame) unless its new joints break a joint velocity or acceleration limit (finite
differences at the parent's fps, as ``manisplat-replay`` computes them); then it is slowed
uniformly by the smallest factor ``k`` that passes: the new frames sit at source times
``s_j = first + j (last - first) / (n - 1)``, the source TCP there being the FK of a C2 cubic spline
through the source joints (so accelerations fall as ``1/k^2``), and the gripper is interpolated.
The skill's commands (its joints led and pressed as the source's were, :mod:`.commands`) are held
to the same limits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from manisplat.augment.commands import SourceCommands
from manisplat.augment.errors import Rejected
from manisplat.augment.kinematics import PinRobot, pose_error


@dataclass
class SkillResult:
    s: np.ndarray            # [n] source time (fractional source frame index) of each new frame
    q: np.ndarray            # [n, dof]
    gripper: np.ndarray      # [n]
    press: np.ndarray        # [n, dof] rad the source's press at s, added to the commands
    tcp_target: np.ndarray   # [n, 4, 4]
    tcp_source: np.ndarray   # [n, 4, 4] the source TCP at s (before D)
    pos_err: np.ndarray      # [n] m
    rot_err: np.ndarray      # [n] rad
    slow: float              # 1 = recorded timing
    ik_iterations: int
    ik_restarts: int


class SourceSpline:
    """C2 cubic spline of the source joints and linear interpolation of its gripper over frame index."""

    def __init__(self, kin: PinRobot, q: np.ndarray, gripper: np.ndarray, tcp: np.ndarray) -> None:
        self.kin, self.q, self.gripper, self.tcp = kin, q, gripper, tcp
        self.frames = np.arange(len(q), dtype=np.float64)
        self.spline = CubicSpline(self.frames, q, axis=0)

    def joints(self, s: np.ndarray) -> np.ndarray:
        out = self.spline(s)
        integer = np.isclose(s, np.round(s), atol=1e-12)
        out[integer] = self.q[np.round(s[integer]).astype(int)]
        return out

    def tcp_at(self, s: np.ndarray) -> np.ndarray:
        out = np.empty((len(s), 4, 4))
        q = self.joints(s)
        for j, sj in enumerate(s):
            r = round(sj)
            out[j] = self.tcp[r] if abs(sj - r) < 1e-12 else self.kin.tcp(q[j])
        return out

    def gripper_at(self, s: np.ndarray) -> np.ndarray:
        return np.interp(s, self.frames, self.gripper)


def finite_difference_ratios(q: np.ndarray, dt: float, vlim: np.ndarray, alim: np.ndarray) -> tuple[float, float]:
    """Peak |velocity| / limit and |acceleration| / limit of frames ``q`` [n, dof] at spacing ``dt``."""
    if len(q) < 2:
        return 0.0, 0.0
    v = np.diff(q, axis=0) / dt
    rv = float((np.abs(v) / vlim).max())
    ra = float((np.abs(np.diff(v, axis=0)) / dt / alim).max()) if len(q) >= 3 else 0.0
    return rv, ra


def solve_skill(kin: PinRobot, spline: SourceSpline, first: int, last: int, D: np.ndarray, *, dt: float,
                vlim: np.ndarray, alim: np.ndarray, tol_pos: float, tol_rot: float, commands: SourceCommands,
                margin: float = 0.95, max_slow: float = 12.0, seed: int = 0, name: str = "skill",
                min_slow: float = 1.0) -> SkillResult:
    """The skill on source frames ``first..last`` moved by ``D``, slowed if its joints or its
    commands must be (and at least by ``min_slow``)."""
    k = max(1.0, float(min_slow))
    result = _solve_at(kin, spline, commands, first, last, D, k, tol_pos, tol_rot, seed, name)
    for _ in range(12):
        rv, ra = np.max([finite_difference_ratios(path, dt, vlim * margin, alim * margin)
                         for path in (result.q, _joined_commands(commands, result))], axis=0)
        if rv <= 1.0 and ra <= 1.0:
            return result
        need = max(rv, math.sqrt(ra)) * k
        k = max(need, k * 1.05)
        if k > max_slow:
            raise Rejected("limits", f"{name}: its new joints and commands would have to be slowed more than "
                                     f"{max_slow:g}x to stay within the velocity/acceleration limits")
        result = _solve_at(kin, spline, commands, first, last, D, k, tol_pos, tol_rot, seed, name)
    raise Rejected("limits", f"{name}: no uniform slow-down within the limits")


def _joined_commands(commands: SourceCommands, result: SkillResult) -> np.ndarray:
    """[n + 1, dof] the skill's commands and the one before it: the motions on either side join the
    skill at its end velocities (a frame extrapolated at each end, pressing nothing), which the
    first and last commands' lead mixes in."""
    q = result.q
    if len(q) < 2:
        return commands.commanded(q, result.press)
    joined = np.concatenate([2 * q[:1] - q[1:2], q, 2 * q[-1:] - q[-2:-1]])
    press = np.concatenate([np.zeros((1, q.shape[1])), result.press, np.zeros((1, q.shape[1]))])
    return commands.commanded(joined, press)[:-1]


def _solve_at(kin, spline: SourceSpline, commands: SourceCommands, first: int, last: int, D: np.ndarray, k: float,
              tol_pos: float, tol_rot: float, seed: int, name: str) -> SkillResult:
    n = int(math.ceil((last - first) * k - 1e-9)) + 1
    s = np.linspace(first, last, n) if k > 1.0 else np.arange(first, last + 1, dtype=np.float64)
    q_src = spline.joints(s)
    T_src = spline.tcp_at(s)
    targets = D @ T_src
    q = np.empty_like(q_src)
    pos = np.empty(n)
    rot = np.empty(n)
    iters = restarts = 0
    prev = None
    for j in range(n):
        if prev is None:
            sol = kin.solve(targets[j], q_src[j], tol_pos=tol_pos, tol_rot=tol_rot, restarts=True, seed=seed)
        else:
            guess = np.clip(prev + (q_src[j] - q_src[j - 1]), kin.lower, kin.upper)
            sol = kin.solve(targets[j], guess, tol_pos=tol_pos, tol_rot=tol_rot)
            if not sol.ok(tol_pos, tol_rot):
                sol = kin.solve(targets[j], prev, tol_pos=tol_pos, tol_rot=tol_rot)
        iters += sol.iterations
        restarts += int(sol.restarted)
        if not sol.ok(tol_pos, tol_rot):
            raise Rejected("ik_unreachable",
                           f"{name}: no IK solution within the limits at source frame {s[j]:.2f} (residual "
                           f"{sol.position_error * 1e3:.2f} mm, {math.degrees(sol.rotation_error):.3f} deg; target "
                           f"TCP at ({targets[j][0, 3]:.3f}, {targets[j][1, 3]:.3f}, {targets[j][2, 3]:.3f}) m)")
        q[j], prev = sol.q, sol.q
    reached = kin.tcp_batch(q)
    pos, rot = pose_error(reached, targets)
    return SkillResult(s, q, spline.gripper_at(s), commands.press_at(s, first, last), targets, T_src, pos, rot, k,
                       iters, restarts)
