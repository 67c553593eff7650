"""The twin's robot as a Pinocchio model: double-precision FK, TCP Jacobian and a warm-started IK.

Why Pinocchio (``pin``) beside :mod:`manisplat.robot`: augmentation solves IK for every frame of
every skill and checks collisions at thousands of configurations per demonstration, one at a time
(each warm-started from the last). The project's torch model is built for batches; a single
configuration costs it ~0.5 ms of Python-level tensor work, Pinocchio ~5 us in C++. The same
kinematic tree is copied joint by joint from the :class:`~manisplat.robot.RobotModel` (no second
URDF parse, so the built-in PiPER and a loaded URDF give the same model), and
``tests/augment/test_kinematics.py`` checks that both agree to 1e-9 m.

The IK here is Levenberg-Marquardt on the TCP's world-aligned Jacobian, clamped into the joint
limits, from a warm start (the previous frame's joints); it polishes far below the tolerances.
Only when the warm start fails does :func:`solve` fall back to the project's
:func:`manisplat.robot.solve_ik` with its Sobol restarts (a different IK branch is then possible;
the callers keep continuity checks).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin
import torch

from manisplat.robot import RobotModel, solve_ik


@dataclass(frozen=True)
class IKSolution:
    q: np.ndarray            # (dof,) rad
    position_error: float    # m
    rotation_error: float    # rad
    iterations: int
    restarted: bool = False

    def ok(self, tol_pos: float, tol_rot: float) -> bool:
        return self.position_error <= tol_pos and self.rotation_error <= tol_rot


class PinRobot:
    """Pinocchio copy of a :class:`RobotModel` (every movable joint, mimic and finger joints driven
    from ``(q_arm, gripper width)`` exactly as the torch model drives them)."""

    def __init__(self, robot: RobotModel) -> None:
        self.robot = robot
        self.model = pin.Model()
        by_child = {j.child: j for j in robot.joints}
        # link -> (pin joint id, placement of the link in that joint's frame)
        self.link_joint: dict[str, tuple[int, pin.SE3]] = {robot.link_names[0]: (0, pin.SE3.Identity())}
        movable: list[str] = []
        for link in robot.link_names[1:]:
            j = by_child[link]
            parent_id, parent_place = self.link_joint[j.parent]
            placement = parent_place * pin.SE3(np.asarray(j.origin, np.float64))
            if j.kind == "fixed":
                self.link_joint[link] = (parent_id, placement)
                continue
            axis = np.asarray(j.axis, np.float64) / np.linalg.norm(j.axis)
            jm = pin.JointModelRevoluteUnaligned(axis) if j.kind == "revolute" else pin.JointModelPrismaticUnaligned(axis)
            big = np.array([1e3])
            jid = self.model.addJoint(parent_id, jm, placement, j.name, big, big, -big, big)
            self.link_joint[link] = (jid, pin.SE3.Identity())
            movable.append(j.name)
        self.data = self.model.createData()
        # q_full = A @ [q_arm..., width] + b
        dof = robot.dof
        nq = self.model.nq
        self.A = np.zeros((nq, dof + 1))
        self.b = np.zeros(nq)
        arm_pos = {n: i for i, n in enumerate(robot.arm_joint_names)}
        finger = dict(robot.gripper.finger_joints) if robot.gripper else {}

        def coeffs(name: str) -> tuple[np.ndarray, float]:
            joint = robot.joint_map[name]
            row = np.zeros(dof + 1)
            if joint.mimic is not None:
                src, mult, off = joint.mimic
                r, c = coeffs(src)
                return mult * r, mult * c + off
            if name in arm_pos:
                row[arm_pos[name]] = 1.0
            elif name in finger:
                row[dof] = finger[name]
            return row, 0.0

        for name in movable:
            jid = self.model.getJointId(name)
            iq = self.model.joints[jid].idx_q
            self.A[iq], self.b[iq] = coeffs(name)
        self.A_arm = self.A[:, :dof]
        tcp_jid, tcp_place = self.link_joint[robot.tcp_link]
        self.tcp_frame = self.model.addFrame(
            pin.Frame("augment_tcp", tcp_jid, tcp_place * pin.SE3(np.asarray(robot.T_link_tcp, np.float64)),
                      pin.FrameType.OP_FRAME))
        self.data = self.model.createData()
        self.lower, self.upper = robot.lower.astype(np.float64), robot.upper.astype(np.float64)
        self.dof = dof

    # ------------------------------------------------------------------ kinematics
    def full_q(self, q: np.ndarray, width: float = 0.0) -> np.ndarray:
        return self.A_arm @ np.asarray(q, np.float64) + self.A[:, -1] * float(width) + self.b

    def tcp(self, q: np.ndarray) -> np.ndarray:
        """``T_base_tcp`` (4, 4) at arm joints ``q``."""
        pin.framesForwardKinematics(self.model, self.data, self.full_q(q))
        return self.data.oMf[self.tcp_frame].homogeneous.copy()

    def tcp_batch(self, Q: np.ndarray) -> np.ndarray:
        return np.stack([self.tcp(q) for q in np.asarray(Q, np.float64)]) if len(Q) else np.zeros((0, 4, 4))

    def link_poses(self, q: np.ndarray, width: float = 0.0) -> dict[str, np.ndarray]:
        pin.forwardKinematics(self.model, self.data, self.full_q(q, width))
        return {link: (self.data.oMi[jid] * place).homogeneous for link, (jid, place) in self.link_joint.items()}

    # ------------------------------------------------------------------ IK
    def ik(self, target: np.ndarray, q0: np.ndarray, *, tol_pos: float, tol_rot: float,
           max_iterations: int = 60) -> IKSolution:
        """Levenberg-Marquardt from ``q0`` towards ``T_base_tcp`` ``target`` (4, 4), within the limits."""
        M_target = pin.SE3(np.asarray(target, np.float64))
        q = np.clip(np.asarray(q0, np.float64), self.lower, self.upper)
        lam = 1e-4
        e, J = self._residual(q, M_target)
        cost = float(e @ e)
        it = 0
        for it in range(1, max_iterations + 1):
            if np.linalg.norm(e[:3]) <= 1e-3 * tol_pos and np.linalg.norm(e[3:]) <= 1e-3 * tol_rot:
                break
            JtJ = J.T @ J
            dq = np.linalg.solve(JtJ + lam * (np.diag(np.diag(JtJ)) + 1e-9 * np.eye(self.dof)), J.T @ e)
            q_new = np.clip(q + dq, self.lower, self.upper)
            e_new, J_new = self._residual(q_new, M_target)
            cost_new = float(e_new @ e_new)
            if cost_new < cost:
                q, e, J, cost = q_new, e_new, J_new, cost_new
                lam = max(lam / 3, 1e-9)
            else:
                lam *= 4
                if lam > 1e8:
                    break
        return IKSolution(q, float(np.linalg.norm(e[:3])), float(np.linalg.norm(e[3:])), it)

    def _residual(self, q: np.ndarray, M_target: pin.SE3) -> tuple[np.ndarray, np.ndarray]:
        qf = self.full_q(q)
        pin.computeJointJacobians(self.model, self.data, qf)
        pin.updateFramePlacements(self.model, self.data)
        M = self.data.oMf[self.tcp_frame]
        e_pos = M_target.translation - M.translation
        e_rot = pin.log3(M_target.rotation @ M.rotation.T)
        Jf = pin.getFrameJacobian(self.model, self.data, self.tcp_frame, pin.LOCAL_WORLD_ALIGNED)
        return np.concatenate([e_pos, e_rot]), Jf @ self.A_arm

    def solve(self, target: np.ndarray, q0: np.ndarray, *, tol_pos: float, tol_rot: float,
              restarts: bool = False, seed: int = 0) -> IKSolution:
        """:meth:`ik` from ``q0``; with ``restarts``, when that fails, the project's IK with Sobol
        restarts (``solve_ik``), polished here."""
        sol = self.ik(target, q0, tol_pos=tol_pos, tol_rot=tol_rot)
        if sol.ok(tol_pos, tol_rot) or not restarts:
            return sol
        res = solve_ik(self.robot, torch.as_tensor(np.asarray(target, np.float64)), q_init=torch.as_tensor(q0),
                       position_tolerance=tol_pos, rotation_tolerance=tol_rot, seed=seed)
        polished = self.ik(target, res.q.numpy(), tol_pos=tol_pos, tol_rot=tol_rot)
        best = polished if polished.position_error + polished.rotation_error < sol.position_error + sol.rotation_error else sol
        return IKSolution(best.q, best.position_error, best.rotation_error, sol.iterations + best.iterations, True)


def pose_error(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and rotation (rad) differences between pose stacks ``A``, ``B`` [..., 4, 4]."""
    dp = np.linalg.norm(A[..., :3, 3] - B[..., :3, 3], axis=-1)
    R = np.swapaxes(A[..., :3, :3], -1, -2) @ B[..., :3, :3]
    skew = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    ang = np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0))
    return dp, np.abs(ang)
