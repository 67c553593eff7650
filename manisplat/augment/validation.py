"""The checks every new demonstration passes before it is returned (issue 12 item 3), each with its
measured value:

* joint limits, velocity, acceleration, jumps: ``manisplat-replay``'s own
  :func:`manisplat.drivers.piper.trajectory.check_trajectory` at speed 1.0 (arm speed 100 %), on
  the commanded actions and on the joints, after the episode's joint convention is mapped to
  the arm's as the replay maps it;
* self and environment collisions along the path the arm is commanded (linear in joint space
  between frames, as the replay streams it), every ``RESOLUTION`` rad, in the collision state of
  each frame's segment; the smallest clearance at the motion frames is reported;
* IK residuals of the skill frames, and the skill-relative pose: the TCP in the frame of the object
  the skill acts on, new vs source, within the IK tolerances;
* continuity: the largest joint step between two frames (no more than the replay allows).
"""

from __future__ import annotations

import math

import numpy as np

from manisplat.augment.errors import Rejected
from manisplat.augment.kinematics import pose_error
from manisplat.augment.planning import RESOLUTION


def replay_problems(t: np.ndarray, q: np.ndarray, gripper: np.ndarray, convention) -> tuple[list[str], dict]:
    """``check_trajectory``'s problems and ``trajectory_figures`` for frames ``q`` (episode convention)."""
    from manisplat.drivers.piper.trajectory import ReplayLimits, Trajectory, check_trajectory, trajectory_figures

    robot = _arm()
    q_arm = convention.to_arm(q) if convention is not None else q
    traj = Trajectory(np.asarray(t, np.float64), q_arm, np.asarray(gripper, np.float64), "actions", 1.0)
    limits = ReplayLimits()
    return check_trajectory(traj, robot, limits), trajectory_figures(traj, robot, limits)


_ARM = None


def _arm():
    global _ARM
    if _ARM is None:
        from manisplat.robot import builtin_piper
        _ARM = builtin_piper(with_geometry=False)
    return _ARM


def within_limits(q: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> bool:
    """Every joint position of ``q`` [T, dof] (rad) within [``lower``, ``upper``] (1e-9 rad of rounding)."""
    return bool(np.all(q >= lower - 1e-9) and np.all(q <= upper + 1e-9))


def dense_collision(scene, q: np.ndarray, gripper: np.ndarray, states: list, first: int, last: int) -> tuple[int, tuple] | None:
    """First frame interval ``[i, i+1]`` (``first <= i < last``) whose joint-linear interpolation
    collides, with the pair; ``states[i]`` is the collision state (a key for ``scene``) of frame i."""
    current = None
    for i in range(first, last + 1):
        if states[i] is not current:
            states[i].apply(scene)
            current = states[i]
        a = q[i]
        b = q[i + 1] if i < last else q[i]
        n = max(1, int(np.ceil(np.abs(b - a).max() / RESOLUTION))) if i < last else 1
        for u in np.linspace(0.0, 1.0, n + 1)[:-1] if i < last else [0.0]:
            qq = a + u * (b - a)
            w = gripper[i] + u * ((gripper[i + 1] if i < last else gripper[i]) - gripper[i])
            if scene.collides(qq, w):
                return i, scene.first_collision(qq, w)
    return None


def skill_relative_errors(T_tcp_new: np.ndarray, T_ref_new: np.ndarray, T_tcp_src: np.ndarray,
                          T_ref_src: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and rotation (rad) differences of the TCP in the object's frame, new vs source."""
    rel_new = np.linalg.inv(T_ref_new) @ T_tcp_new
    rel_src = np.linalg.inv(T_ref_src) @ T_tcp_src
    return pose_error(rel_new, rel_src)


def check_all(*, t, q, action_q, gripper, action_gripper, convention, lower, upper, tol_pos, tol_rot, skill_errors,
              ik_errors) -> dict:
    """The limit, IK, skill-pose and continuity checks; raises :class:`Rejected`, returns the figures."""
    out: dict = {}
    inside = within_limits(q, lower, upper)
    out["joint_limits_ok"] = inside
    problems_q, figures_q = replay_problems(t, q, gripper, convention)
    problems_a, figures_a = replay_problems(t, action_q, action_gripper, convention)
    out["replay_check"] = {"joints": problems_q, "actions": problems_a}
    out["max_velocity_of_limit"] = max(figures_q["peak_velocity_of_limit"], figures_a["peak_velocity_of_limit"])
    out["max_acceleration_of_limit"] = max(figures_q.get("peak_acceleration_of_limit", 0.0),
                                           figures_a.get("peak_acceleration_of_limit", 0.0))
    step = np.abs(np.diff(q, axis=0)).max() if len(q) > 1 else 0.0
    out["max_joint_step_deg"] = math.degrees(float(step))
    pos = np.concatenate([e[0] for e in ik_errors]) if ik_errors else np.zeros(0)
    rot = np.concatenate([e[1] for e in ik_errors]) if ik_errors else np.zeros(0)
    out["ik_residual_max_mm"] = float(pos.max() * 1e3) if len(pos) else 0.0
    out["ik_residual_max_deg"] = math.degrees(float(rot.max())) if len(rot) else 0.0
    sp = np.concatenate([e[0] for e in skill_errors]) if skill_errors else np.zeros(0)
    sr = np.concatenate([e[1] for e in skill_errors]) if skill_errors else np.zeros(0)
    out["skill_error_mm"] = float(sp.max() * 1e3) if len(sp) else 0.0
    out["skill_error_deg"] = math.degrees(float(sr.max())) if len(sr) else 0.0
    out["tolerance_mm"], out["tolerance_deg"] = tol_pos * 1e3, math.degrees(tol_rot)
    if not inside:
        raise Rejected("limits", "a joint leaves its position limits")
    if problems_q or problems_a:
        raise Rejected("limits", "; ".join(problems_a or problems_q))
    if len(pos) and (pos.max() > tol_pos or rot.max() > tol_rot):
        raise Rejected("ik_unreachable", f"IK residual {pos.max() * 1e3:.3f} mm / {math.degrees(rot.max()):.4f} deg "
                                         f"above the tolerance")
    if len(sp) and (sp.max() > tol_pos * (1 + 1e-6) or sr.max() > tol_rot * (1 + 1e-6)):
        raise Rejected("skill_pose", f"the TCP relative to the object differs from the source's by "
                                     f"{sp.max() * 1e3:.3f} mm / {math.degrees(sr.max()):.4f} deg")
    return out
