"""A robot model: a tree of links and joints with limits, a TCP and a parallel gripper, plus
batched forward kinematics and the TCP Jacobian in torch.

Every model (the built-in PiPER, a loaded URDF) is expressed in the same terms, so one FK serves
all: ``T_parent_child(q) = origin @ motion(axis, q)`` with ``origin`` the joint frame in the
parent link at q = 0 (URDF semantics). Lengths in metres, angles in radians.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import torch
import trimesh

from manisplat.geometry import DEFAULT_DTYPE, hat


class RobotModelError(ValueError):
    """An inconsistent robot description or joint input (unknown link, NaN joints, ...)."""


@dataclass(frozen=True)
class JointLimits:
    """Limits of one joint. ``velocity``/``acceleration`` are None when the source does not know them.

    Units: rad (revolute) or m (prismatic), per second and per second squared; effort in N*m or N.
    """

    lower: float
    upper: float
    velocity: float | None = None
    acceleration: float | None = None
    effort: float | None = None


@dataclass(frozen=True)
class Joint:
    """A joint between two links.

    Attributes:
        kind: "revolute", "prismatic" or "fixed".
        origin: (4, 4) float64, the joint frame in the parent link frame at zero position.
        axis: (3,) unit axis in the joint frame (ignored for fixed joints).
        limits: position/velocity limits, None for fixed joints.
        mimic: (source joint, multiplier, offset) when this joint copies another one.
    """

    name: str
    kind: str
    parent: str
    child: str
    origin: np.ndarray
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    limits: JointLimits | None = None
    mimic: tuple[str, float, float] | None = None


@dataclass(frozen=True)
class Gripper:
    """A parallel gripper driven by its opening ``width`` (the gap between the finger pads, m).

    Attributes:
        finger_joints: (joint name, factor) pairs: joint position = factor * width.
        width_range: the physical opening range (m).
    """

    finger_joints: tuple[tuple[str, float], ...]
    width_range: tuple[float, float] = (0.0, 0.07)


@dataclass(frozen=True)
class Visual:
    """Geometry of a link: a triangle mesh in link coordinates (m) and where it came from."""

    mesh: trimesh.Trimesh
    source: str


def link_meshes(visuals: dict[str, list[Visual]]) -> dict[str, trimesh.Trimesh]:
    """link -> its visuals' triangles as one mesh (link frame, m), for every link that has any
    (``visuals`` as :attr:`RobotModel.visuals`)."""
    out = {}
    for link, vis in visuals.items():
        parts = [v.mesh for v in vis if v.mesh is not None and len(v.mesh.faces)]
        if parts:
            out[link] = trimesh.util.concatenate(parts)
    return out


class RobotModel:
    """Kinematic tree, arm joints, limits, TCP, gripper and link geometry of one robot.

    Args:
        name: a label, e.g. "builtin:agilex_piper" or the URDF path.
        joints: every joint of the tree (fixed ones included).
        arm_joints: names of the actuated arm joints, in the order of the joint vector ``q``.
        tcp_link, T_link_tcp: the tool centre point as a pose (4, 4) in ``tcp_link``.
        gripper: the parallel gripper, or None.
        visuals: link name -> geometry (may be empty for links without any).
    """

    def __init__(
        self,
        name: str,
        joints: Sequence[Joint],
        arm_joints: Sequence[str],
        tcp_link: str,
        T_link_tcp: np.ndarray,
        gripper: Gripper | None = None,
        visuals: dict[str, list[Visual]] | None = None,
    ) -> None:
        self.name = name
        self.joints = tuple(joints)
        self.joint_map = {j.name: j for j in self.joints}
        if len(self.joint_map) != len(self.joints):
            raise RobotModelError(f"{name}: duplicate joint names")
        self.link_names = _topological_links(name, self.joints)
        self.arm_joint_names = tuple(arm_joints)
        self.tcp_link = tcp_link
        self.T_link_tcp = np.asarray(T_link_tcp, dtype=np.float64)
        self.gripper = gripper
        self.visuals = dict(visuals or {})
        self._check()
        self._cache: dict[tuple[torch.dtype, torch.device], _Compiled] = {}

    # ----------------------------------------------------------------- description
    @property
    def dof(self) -> int:
        """Number of arm joints (the length of ``q``)."""
        return len(self.arm_joint_names)

    def _arm_limits(self) -> list[JointLimits]:
        return [self.joint_map[n].limits for n in self.arm_joint_names]  # type: ignore[misc]

    @property
    def lower(self) -> np.ndarray:
        """(dof,) lower position limits."""
        return np.array([lim.lower for lim in self._arm_limits()])

    @property
    def upper(self) -> np.ndarray:
        """(dof,) upper position limits."""
        return np.array([lim.upper for lim in self._arm_limits()])

    @property
    def velocity_limits(self) -> np.ndarray:
        """(dof,) maximum joint speeds (rad/s or m/s). Raises if the description lacks one."""
        return self._required("velocity")

    @property
    def acceleration_limits(self) -> np.ndarray:
        """(dof,) maximum joint accelerations. Raises if the description lacks one."""
        return self._required("acceleration")

    def _required(self, what: str) -> np.ndarray:
        values = []
        for joint_name, lim in zip(self.arm_joint_names, self._arm_limits()):
            value = getattr(lim, what)
            if value is None or not value > 0:
                raise RobotModelError(
                    f"{self.name}: the {what} limit of {joint_name} is unknown (the description gives "
                    f"{value!r}); pass {what} limits explicitly when loading the model"
                )
            values.append(value)
        return np.array(values)

    def link_index(self, link: str) -> int:
        """Position of ``link`` in :attr:`link_names` (the FK output order)."""
        try:
            return self.link_names.index(link)
        except ValueError:
            raise RobotModelError(f"{self.name}: no link named {link!r}; links: {list(self.link_names)}") from None

    # ----------------------------------------------------------------- inputs
    def check_joints(self, q, *, dtype: torch.dtype | None = None) -> torch.Tensor:
        """``q`` as a tensor [..., dof]; raises on a wrong last dimension or NaN/Inf."""
        q = _to_tensor(q, dtype)
        if q.ndim == 0 or q.shape[-1] != self.dof:
            raise RobotModelError(f"{self.name}: joint vectors must have {self.dof} values, got shape {tuple(q.shape)}")
        if not bool(torch.isfinite(q).all()):
            raise RobotModelError(f"{self.name}: joint values contain NaN or Inf")
        return q

    def within_limits(self, q, tol: float = 1e-9) -> torch.Tensor:
        """Bool [...]: every joint of ``q`` [..., dof] within its position limits (+- ``tol``)."""
        q = self.check_joints(q)
        lo = torch.as_tensor(self.lower, dtype=q.dtype, device=q.device)
        hi = torch.as_tensor(self.upper, dtype=q.dtype, device=q.device)
        return ((q >= lo - tol) & (q <= hi + tol)).all(dim=-1)

    def clamp(self, q: torch.Tensor) -> torch.Tensor:
        """``q`` [..., dof] clamped into the position limits."""
        lo = torch.as_tensor(self.lower, dtype=q.dtype, device=q.device)
        hi = torch.as_tensor(self.upper, dtype=q.dtype, device=q.device)
        return torch.maximum(torch.minimum(q, hi), lo)

    def sample_configurations(
        self, n: int, *, generator: torch.Generator | None = None, dtype: torch.dtype = DEFAULT_DTYPE
    ) -> torch.Tensor:
        """``n`` joint vectors [n, dof] uniform within the position limits."""
        u = torch.rand(n, self.dof, generator=generator, dtype=dtype)
        lo, hi = torch.as_tensor(self.lower, dtype=dtype), torch.as_tensor(self.upper, dtype=dtype)
        return lo + u * (hi - lo)

    # ----------------------------------------------------------------- kinematics
    def forward_kinematics(self, q, gripper=None) -> torch.Tensor:
        """Poses ``T_base_link`` [..., L, 4, 4] of all links (order :attr:`link_names`).

        Args:
            q: [..., dof] arm joint positions; numpy or lists become float64 tensors.
            gripper: [...] gripper opening width (m); None means closed (0).
        """
        q = self.check_joints(q)
        return self._compiled(q).forward(q, self._gripper_width(q, gripper))[0]

    def link_pose(self, q, link: str, gripper=None) -> torch.Tensor:
        """``T_base_link`` [..., 4, 4] of one link."""
        return self.forward_kinematics(q, gripper)[..., self.link_index(link), :, :]

    def tcp_pose(self, q) -> torch.Tensor:
        """``T_base_tcp`` [..., 4, 4]."""
        q = self.check_joints(q)
        c = self._compiled(q)
        poses, _ = c.forward(q, torch.zeros(q.shape[:-1], dtype=q.dtype, device=q.device))
        return poses[..., c.tcp_index, :, :] @ c.T_link_tcp

    def jacobian(self, q) -> tuple[torch.Tensor, torch.Tensor]:
        """Geometric Jacobian of the TCP in the base frame and the TCP pose.

        Returns:
            J: [..., 6, dof], rows (linear velocity, angular velocity) per unit joint velocity.
            T_base_tcp: [..., 4, 4].
        """
        q = self.check_joints(q)
        c = self._compiled(q)
        poses, frames = c.forward(q, torch.zeros(q.shape[:-1], dtype=q.dtype, device=q.device))
        T_tcp = poses[..., c.tcp_index, :, :] @ c.T_link_tcp
        axes = (frames[..., :3, :3] @ c.arm_axes[..., None])[..., 0]  # [..., dof, 3] world axes
        origins = frames[..., :3, 3]  # [..., dof, 3]
        lever = T_tcp[..., None, :3, 3] - origins
        revolute = c.arm_revolute[:, None]
        linear = torch.where(revolute, torch.linalg.cross(axes, lever, dim=-1), axes)
        angular = torch.where(revolute, axes, torch.zeros_like(axes))
        J = torch.cat([linear, angular], dim=-1) * c.arm_moves_tcp[:, None]  # [..., dof, 6]
        return J.transpose(-1, -2), T_tcp

    # ----------------------------------------------------------------- internals
    def _gripper_width(self, q: torch.Tensor, gripper) -> torch.Tensor:
        batch = q.shape[:-1]
        if gripper is None:
            return torch.zeros(batch, dtype=q.dtype, device=q.device)
        width = _to_tensor(gripper, q.dtype).to(q.device)
        if not bool(torch.isfinite(width).all()):
            raise RobotModelError(f"{self.name}: gripper width contains NaN or Inf")
        return width.expand(batch)

    def _compiled(self, q: torch.Tensor) -> "_Compiled":
        key = (q.dtype, q.device)
        if key not in self._cache:
            self._cache[key] = _Compiled(self, q.dtype, q.device)
        return self._cache[key]

    def _check(self) -> None:
        links = set(self.link_names)
        for name in self.arm_joint_names:
            joint = self.joint_map.get(name)
            if joint is None or joint.kind not in ("revolute", "prismatic") or joint.mimic is not None:
                raise RobotModelError(f"{self.name}: arm joint {name!r} is not an independent revolute/prismatic joint")
            if joint.limits is None or not joint.limits.lower <= joint.limits.upper:
                raise RobotModelError(f"{self.name}: arm joint {name!r} needs finite position limits")
        if self.tcp_link not in links:
            raise RobotModelError(f"{self.name}: TCP link {self.tcp_link!r} is not in the model")
        if self.T_link_tcp.shape != (4, 4) or not np.isfinite(self.T_link_tcp).all():
            raise RobotModelError(f"{self.name}: T_link_tcp must be a finite 4x4 matrix")
        for name, _ in self.gripper.finger_joints if self.gripper else ():
            if name not in self.joint_map:
                raise RobotModelError(f"{self.name}: gripper finger joint {name!r} is not in the model")
        for joint in self.joints:
            if joint.mimic is None:
                continue
            source = self.joint_map.get(joint.mimic[0])
            if source is None or source.kind == "fixed":
                raise RobotModelError(
                    f"{self.name}: joint {joint.name!r} mimics {joint.mimic[0]!r}, which is not a movable joint"
                )
        unknown = set(self.visuals) - links
        if unknown:
            raise RobotModelError(f"{self.name}: geometry given for unknown links {sorted(unknown)}")

    def __repr__(self) -> str:
        return f"RobotModel({self.name!r}, dof={self.dof}, links={len(self.link_names)}, tcp={self.tcp_link!r})"


def _to_tensor(x, dtype: torch.dtype | None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x if dtype is None else x.to(dtype)
    return torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=dtype or DEFAULT_DTYPE)


def _topological_links(name: str, joints: Sequence[Joint]) -> tuple[str, ...]:
    """Links ordered parents-first from the single root; raises on cycles, forests, two parents."""
    children: dict[str, list[str]] = {}
    parent_of: dict[str, str] = {}
    for j in joints:
        if j.child in parent_of:
            raise RobotModelError(f"{name}: link {j.child!r} has two parent joints")
        parent_of[j.child] = j.parent
        children.setdefault(j.parent, []).append(j.child)
    roots = sorted({j.parent for j in joints} - set(parent_of)) if joints else []
    if len(roots) != 1:
        raise RobotModelError(f"{name}: the joints must form one tree with one root link, found roots {roots}")
    order, stack = [], [roots[0]]
    while stack:
        link = stack.pop()
        order.append(link)
        stack.extend(reversed(children.get(link, [])))
    if len(order) != len(parent_of) + 1:
        raise RobotModelError(f"{name}: the joint graph has a cycle")
    return tuple(order)


class _Compiled:
    """Tensors of a model for one dtype/device, laid out for a loop over joints in tree order."""

    def __init__(self, model: RobotModel, dtype: torch.dtype, device: torch.device) -> None:
        def t(x) -> torch.Tensor:
            return torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=dtype, device=device)

        link_pos = {link: i for i, link in enumerate(model.link_names)}
        by_child = {j.child: j for j in model.joints}
        arm_pos = {n: i for i, n in enumerate(model.arm_joint_names)}
        finger = dict(model.gripper.finger_joints) if model.gripper else {}
        self.steps = []  # (child idx, parent idx, origin, kind, K, K2, axis, source)
        for link in model.link_names[1:]:
            j = by_child[link]
            axis = np.asarray(j.axis, dtype=np.float64)
            axis = axis / np.linalg.norm(axis)
            K = hat(t(axis))
            self.steps.append((link_pos[link], link_pos[j.parent], t(j.origin), j.kind, K, K @ K, t(axis), _source(j, model, arm_pos, finger)))
        self.tcp_index = link_pos[model.tcp_link]
        self.T_link_tcp = t(model.T_link_tcp)
        self.n_links = len(model.link_names)
        arm = [model.joint_map[n] for n in model.arm_joint_names]
        self.arm_child = [link_pos[j.child] for j in arm]
        self.arm_axes = t(np.stack([np.asarray(j.axis, float) / np.linalg.norm(j.axis) for j in arm]))
        self.arm_revolute = torch.tensor([j.kind == "revolute" for j in arm], device=device)
        ancestors = _ancestor_links(model, model.tcp_link)
        self.arm_moves_tcp = t([1.0 if j.child in ancestors else 0.0 for j in arm])

    def forward(self, q: torch.Tensor, width: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """All link poses [..., L, 4, 4] and the arm joint frames [..., dof, 4, 4] (before motion)."""
        batch = q.shape[:-1]
        eye = torch.eye(4, dtype=q.dtype, device=q.device).expand(*batch, 4, 4)
        poses: list[torch.Tensor | None] = [None] * self.n_links
        poses[0] = eye
        joint_frames: dict[int, torch.Tensor] = {}
        for child, parent, origin, kind, K, K2, axis, source in self.steps:
            frame = poses[parent] @ origin  # [..., 4, 4]
            joint_frames[child] = frame
            if kind == "fixed":
                poses[child] = frame
                continue
            value = source(q, width)[..., None, None]  # [..., 1, 1]
            motion = eye.clone()
            if kind == "revolute":
                motion[..., :3, :3] = torch.eye(3, dtype=q.dtype, device=q.device) + torch.sin(value) * K + (1 - torch.cos(value)) * K2
            else:
                motion[..., :3, 3] = value[..., 0] * axis
            poses[child] = frame @ motion
        frames = torch.stack([joint_frames[c] for c in self.arm_child], dim=-3)
        return torch.stack(poses, dim=-3), frames  # type: ignore[arg-type]


def _source(joint: Joint, model: RobotModel, arm_pos: dict[str, int], finger: dict[str, float]):
    """A function (q [..., dof], width [...]) -> joint position [...] for ``joint``."""
    if joint.kind == "fixed":
        return None
    if joint.mimic is not None:
        src_name, multiplier, offset = joint.mimic
        src = _source(model.joint_map[src_name], model, arm_pos, finger)
        return lambda q, w: multiplier * src(q, w) + offset
    if joint.name in arm_pos:
        i = arm_pos[joint.name]
        return lambda q, w: q[..., i]
    if joint.name in finger:
        factor = finger[joint.name]
        return lambda q, w: factor * w
    return lambda q, w: torch.zeros_like(w)


def _ancestor_links(model: RobotModel, link: str) -> set[str]:
    parent_of = {j.child: j.parent for j in model.joints}
    out = {link}
    while link in parent_of:
        link = parent_of[link]
        out.add(link)
    return out
