"""Batched inverse kinematics of the TCP: Levenberg-Marquardt with joint limits and restarts.

Each target is solved independently but all targets step together as one batch. The error is
``e = (p* - p, w_rot * log(R* R^T))`` in the base frame, matching the geometric Jacobian; a step
``dq = (J^T J + lambda diag(J^T J) + mu I)^-1 J^T e`` is taken, clamped into the limits, and
accepted only if it lowers ``|e|`` (then ``lambda`` shrinks; otherwise it grows). Targets that
have not converged after ``max_iterations`` restart from several configurations at once, taken
from a scrambled Sobol sequence over the joint ranges; the best solution found is returned with
its residuals and a success flag.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from manisplat.geometry import rotation_error, so3_log
from manisplat.robot.model import RobotModel, RobotModelError


POLISH = 1e-3  # descend until the errors are this fraction of the tolerances
MAX_DAMPING = 1e7  # a target whose damping reaches this has stalled


@dataclass(frozen=True)
class IKResult:
    """Solutions of a batch of IK problems.

    Attributes:
        q: [B, dof] joint positions (within limits), the best found for each target.
        success: [B] both errors within tolerance.
        position_error: [B] TCP position error (m).
        rotation_error: [B] TCP rotation error (rad).
        attempts: [B] starts used (1 = the initial guess sufficed).
    """

    q: torch.Tensor
    success: torch.Tensor
    position_error: torch.Tensor
    rotation_error: torch.Tensor
    attempts: torch.Tensor


def _residual(model: RobotModel, q: torch.Tensor, target: torch.Tensor, w_rot: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Error [B, 6] and Jacobian [B, 6, dof], rotation rows weighted by ``w_rot``."""
    J, T = model.jacobian(q)
    e_pos = target[:, :3, 3] - T[:, :3, 3]
    e_rot = so3_log(target[:, :3, :3] @ T[:, :3, :3].transpose(-1, -2))
    scale = torch.tensor([1.0, 1.0, 1.0, w_rot, w_rot, w_rot], dtype=q.dtype, device=q.device)
    return torch.cat([e_pos, e_rot], -1) * scale, J * scale[:, None]


def _errors(model: RobotModel, q: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    T = model.tcp_pose(q)
    return (T[:, :3, 3] - target[:, :3, 3]).norm(dim=-1), rotation_error(T[:, :3, :3], target[:, :3, :3])


def _lm_step(J: torch.Tensor, e: torch.Tensor, lam: torch.Tensor, eye: torch.Tensor) -> torch.Tensor:
    """Levenberg-Marquardt step [B, dof] for residual ``e`` [B, 6] and Jacobian ``J`` [B, 6, dof]."""
    JtJ = J.transpose(-1, -2) @ J
    A = JtJ + lam[:, None, None] * torch.diag_embed(torch.diagonal(JtJ, dim1=-2, dim2=-1)) + 1e-9 * eye
    return torch.linalg.solve(A, J.transpose(-1, -2) @ e[..., None])[..., 0]


def _descend(
    model: RobotModel, q: torch.Tensor, target: torch.Tensor, iterations: int, w_rot: float, tol_pos: float, tol_rot: float
) -> torch.Tensor:
    """Levenberg-Marquardt from ``q`` [B, dof]; stops early once every target has converged."""
    B, n = q.shape
    lam = torch.full((B,), 1e-2, dtype=q.dtype, device=q.device)
    eye = torch.eye(n, dtype=q.dtype, device=q.device)
    lo = torch.as_tensor(model.lower, dtype=q.dtype, device=q.device)
    hi = torch.as_tensor(model.upper, dtype=q.dtype, device=q.device)
    e, J = _residual(model, q, target, w_rot)
    cost = (e * e).sum(-1)
    for _ in range(iterations):
        # Keep polishing well below the tolerances (LM converges quadratically there, so this
        # costs an iteration or two) unless the damping shows the target has stalled.
        pos_ok = e[:, :3].norm(dim=-1) <= POLISH * tol_pos
        rot_ok = e[:, 3:].norm(dim=-1) <= POLISH * tol_rot * w_rot
        active = ~(pos_ok & rot_ok) & (lam < MAX_DAMPING)
        if not bool(active.any()):
            break
        dq = _lm_step(J, e, lam, eye)
        # Joints at a limit that the step pushes further out are frozen and the step re-solved,
        # so the other joints can still make progress (clamping alone stalls there).
        blocked = ((q <= lo + 1e-12) & (dq < 0)) | ((q >= hi - 1e-12) & (dq > 0))
        if bool(blocked.any()):
            dq = _lm_step(J * (~blocked)[:, None, :].to(J.dtype), e, lam, eye)
        q_new = model.clamp(q + dq)
        e_new, J_new = _residual(model, q_new, target, w_rot)
        cost_new = (e_new * e_new).sum(-1)
        accept = (cost_new < cost) & active
        q = torch.where(accept[:, None], q_new, q)
        e = torch.where(accept[:, None], e_new, e)
        J = torch.where(accept[:, None, None], J_new, J)
        cost = torch.where(accept, cost_new, cost)
        lam = torch.where(accept, (lam / 3).clamp(min=1e-7), (lam * 4).clamp(max=MAX_DAMPING))
    return q


def solve_ik(
    model: RobotModel,
    target: torch.Tensor,
    *,
    q_init: torch.Tensor | None = None,
    max_iterations: int = 40,
    restarts: int = 32,
    parallel_starts: int = 8,
    position_tolerance: float = 1e-4,
    rotation_tolerance: float = 1e-3,
    rotation_weight: float = 0.1,
    seed: int = 0,
) -> IKResult:
    """Joint positions whose TCP reaches ``target`` poses ``T_base_tcp`` [B, 4, 4] (or [4, 4]).

    Args:
        q_init: [B, dof] or [dof] first guesses (e.g. the previous frame's joints, which keeps the
            solution on the same branch); default: the middle of the joint ranges.
        max_iterations: LM iterations per start.
        restarts: random starts allowed per target not solved from ``q_init``.
        parallel_starts: random starts tried at once for each unsolved target.
        position_tolerance: success bound on the position error (m).
        rotation_tolerance: success bound on the rotation error (rad).
        rotation_weight: metres per radian when mixing the two errors.
        seed: scrambles the restart sequence. Every target draws its restarts from the same
            low-discrepancy (Sobol) sequence over the joint ranges, so a target's result does
            not depend on the other targets in the batch.
    """
    single = target.ndim == 2
    target = target[None] if single else target
    if target.ndim != 3 or target.shape[-2:] != (4, 4):
        raise RobotModelError(f"IK targets must be [B, 4, 4] poses, got {tuple(target.shape)}")
    if not bool(torch.isfinite(target).all()):
        raise RobotModelError("IK targets contain NaN or Inf")
    dtype, B = target.dtype, target.shape[0]
    lo = torch.as_tensor(model.lower, dtype=dtype)
    hi = torch.as_tensor(model.upper, dtype=dtype)
    if q_init is None:
        q0 = ((lo + hi) / 2).expand(B, -1).clone()
    else:
        q0 = model.clamp(model.check_joints(q_init, dtype=dtype).expand(B, -1).clone())
    if restarts < 0 or parallel_starts < 1:
        raise ValueError(f"restarts must be >= 0 and parallel_starts >= 1; got {restarts}, {parallel_starts}")
    sobol = torch.quasirandom.SobolEngine(model.dof, scramble=True, seed=seed)
    starts = lo + sobol.draw(restarts, dtype=dtype) * (hi - lo) if restarts else lo[None]

    best_q = q0.clone()
    best_score = torch.full((B,), float("inf"), dtype=dtype)
    best_pos, best_rot = best_score.clone(), best_score.clone()
    attempts = torch.zeros(B, dtype=torch.long)
    pending = torch.arange(B)
    used = 0
    first = True
    while len(pending) > 0:
        if first:
            k, owner, q = 1, pending, q0
        elif used < restarts:
            k = min(parallel_starts, restarts - used)
            owner = pending.repeat_interleave(k)
            q = starts[used : used + k].repeat(len(pending), 1)
            used += k
        else:
            break
        q = _descend(model, q, target[owner], max_iterations, rotation_weight, position_tolerance, rotation_tolerance)
        pos, rot = _errors(model, q, target[owner])
        solved = (pos <= position_tolerance) & (rot <= rotation_tolerance)
        score = torch.where(solved, torch.zeros_like(pos), pos + rotation_weight * rot)
        # The best of each target's k starts: [len(pending), k] -> per-target argmin.
        per_target = score.reshape(len(pending), k)
        pick = per_target.argmin(dim=1)
        chosen = torch.arange(len(pending)) * k + pick
        better = score[chosen] < best_score[pending]
        idx = pending[better]
        best_q[idx], best_score[idx] = q[chosen][better], score[chosen][better]
        best_pos[idx], best_rot[idx] = pos[chosen][better], rot[chosen][better]
        attempts[pending] += k
        pending = pending[~solved.reshape(len(pending), k).any(dim=1)]
        first = False
    success = (best_pos <= position_tolerance) & (best_rot <= rotation_tolerance)
    result = IKResult(best_q, success, best_pos, best_rot, attempts)
    if single:
        return IKResult(*(x[0] for x in (result.q, result.success, result.position_error, result.rotation_error, result.attempts)))
    return result
