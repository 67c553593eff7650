"""The trained twin: the scene graph, its arms and cameras and the source demonstration; it
renders any state (arms' joints, objects' poses) from any of its cameras or a free one, without
the source episode's images. :mod:`manisplat.twin.files` writes and reads it as a folder."""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np
import torch

from manisplat.episode.format import V1_ARM
from manisplat.robot import RobotModel
from manisplat.robot.arms import ArmSet
from manisplat.scene import SceneGraph
from manisplat.scene.render import render_graph
from manisplat.splat import opencv_to_splat_K
from manisplat.twin.commands import CommandRelation
from manisplat.twin.rig import BASE_FRAME, TwinArm, TwinCamera
from manisplat.twin.support import SupportMap


class TwinFormatError(ValueError):
    """A twin folder that is missing, incomplete or of another format (the file and key named)."""


@dataclass(frozen=True)
class Phase:
    """Frames [start, end) of one Motion ("motion") or Skill ("skill") segment, e.g. "S_pick"."""

    kind: str
    name: str
    start: int
    end: int


@dataclass
class TwinView:
    """One rendered state: ``rgb`` [H, W, 3] uint8, ``depth`` [H, W] float32 z-depth in metres (0 where
    nothing was rendered), ``labels`` [H, W] uint8 mask values of the episode's ``labels``."""

    rgb: np.ndarray
    depth: np.ndarray
    labels: np.ndarray


@dataclass(frozen=True)
class Demonstration:
    """One recorded demonstration the twin was trained on (its source episode's part of the twin).

    Attributes:
        episode: the source episode's folder name; fps, task: its own.
        t, q, gripper: per frame: [T] s, [T, dof] rad (every arm's joints in arm order), [T] m
            (one arm) or [T, A] m (per arm).
        object_poses: name -> [T, 4, 4] float64 ``T_base_obj`` per frame (trained poses, in the
            twin's frame; the objects' canonical frames are the twin's, shared by every demonstration).
        pose_sources: name -> per frame "static", "attached" or "tracked".
        phases: name -> the Motion/Skill segments of the demonstration for that object.
        commands: how its commands led and pressed its joints (:class:`CommandRelation`, press
            [T, dof]; None where it recorded no commands): augmentation commands new joints so.
    """

    episode: str
    fps: float
    t: np.ndarray
    q: np.ndarray
    gripper: np.ndarray
    object_poses: dict[str, np.ndarray]
    pose_sources: dict[str, list[str]]
    phases: dict[str, list[Phase]]
    task: str | None = None
    commands: CommandRelation | None = None

    def __post_init__(self) -> None:
        for name in ("t", "q", "gripper"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), np.float64))
        object.__setattr__(self, "object_poses", {k: np.asarray(v, np.float64) for k, v in self.object_poses.items()})
        object.__setattr__(self, "fps", float(self.fps))
        if self.commands is not None and self.commands.press.shape != self.q.shape:
            raise ValueError(f"{self.episode}: command press {self.commands.press.shape} does not match q {self.q.shape}")
        bad = {k: v.shape for k, v in self.object_poses.items() if v.shape != (len(self.t), 4, 4)}
        if bad:
            raise ValueError(f"{self.episode}: object poses {bad} do not match its {len(self.t)} frames")


class Twin:
    """A reconstructed scene: Gaussians of the background, the robot's links and the objects, the
    light that casts the moving parts' shadows, the cameras, and the source demonstrations.

    Everything is in the twin's :attr:`frame`: one arm's base (``"base"``, a version 1 episode) or
    the episode's world (``"world"``, several arms or cameras); ``T_base_*`` names mean that frame.

    Attributes:
        graph: the scene graph (links in link frames, objects in canonical frames).
        robot: the kinematics (no meshes): one arm's :class:`RobotModel`, or an
            :class:`~manisplat.robot.arms.ArmSet` (links ``<arm>/<link>``).
        arms: the :class:`TwinArm` of each arm, in the order of ``q`` (descriptions, bases).
        cameras: camera name -> :class:`TwinCamera`, the reference camera (fixed; the one the
            scene was anchored in and the renders default to) first.
        labels: mask value -> name ("background", "robot/<link>", "object/<name>", ...).
        demonstrations: episode name -> :class:`Demonstration`, every one the twin was trained on
            (one; several for a twin fused from several episodes of one scene), in order.
        demonstration: the one :attr:`t`, :attr:`q`, :attr:`gripper`, :attr:`object_poses`,
            :attr:`pose_sources`, :attr:`phases`, :attr:`fps`, :attr:`episode`, :attr:`task` and
            :attr:`commands` are (the first; :meth:`source` gives the twin with another).
        support: the support surfaces' height map, measured from the recording's depth (None
            without depth): where objects can be set down.
    """

    def __init__(self, *, graph: SceneGraph, background_rgb: torch.Tensor, robot: RobotModel | ArmSet,
                 arms: list[TwinArm], cameras: list[TwinCamera], labels: dict[int, str],
                 demonstrations: list[Demonstration], backend: str = "auto",
                 support: SupportMap | None = None) -> None:
        if [a.name for a in arms] != list(_arm_names(robot)):
            raise ValueError(f"twin arms {[a.name for a in arms]} do not match the robot's {list(_arm_names(robot))}")
        if not cameras or not cameras[0].fixed:
            raise ValueError("a twin needs a reference camera fixed in its frame, listed first")
        for cam in cameras:
            if not cam.fixed and cam.mount not in robot.link_names:
                raise ValueError(f"camera {cam.name} rides on {cam.mount!r}, no link of {robot.name}")
        if not demonstrations:
            raise ValueError("a twin needs at least one source demonstration")
        names = [d.episode for d in demonstrations]
        if len(set(names)) != len(names):
            raise ValueError(f"demonstrations with the same episode name: {names}")
        for demo in demonstrations:
            if set(demo.object_poses) != set(graph.objects):
                raise ValueError(f"{demo.episode}: object poses for {sorted(demo.object_poses)}, the twin has "
                                 f"objects {sorted(graph.objects)}")
        self.graph, self.background_rgb, self.robot = graph, background_rgb.float(), robot
        self.arms, self.cameras = list(arms), {cam.name: cam for cam in cameras}
        self.labels = dict(labels)
        self.demonstrations = {d.episode: d for d in demonstrations}
        self.demonstration = demonstrations[0]
        self.backend, self.support = backend, support
        self.device = graph.device  # where it renders: the Gaussians' device
        self.background_rgb = self.background_rgb.to(self.device)
        self._node_labels = self._label_of_nodes()

    # ------------------------------------------------------------------ the source demonstration
    def source(self, episode: str) -> "Twin":
        """The twin with ``episode``'s demonstration as its source (the same Gaussians, shared)."""
        if episode not in self.demonstrations:
            raise ValueError(f"the twin has no demonstration {episode!r}; it has {', '.join(self.demonstrations)}")
        return self.with_demonstration(self.demonstrations[episode])

    def with_demonstration(self, demonstration: Demonstration) -> "Twin":
        """A shallow copy of the twin whose source is ``demonstration`` (e.g. one of
        :attr:`demonstrations`, or one of them with other commands)."""
        twin = copy.copy(self)
        twin.demonstration = demonstration
        return twin

    @property
    def t(self) -> np.ndarray:
        """[T] s: the source demonstration's frame times."""
        return self.demonstration.t

    @property
    def q(self) -> np.ndarray:
        """[T, dof] rad: its joints (every arm's, in arm order)."""
        return self.demonstration.q

    @property
    def gripper(self) -> np.ndarray:
        """[T] m (one arm) or [T, A] m: its gripper openings."""
        return self.demonstration.gripper

    @property
    def object_poses(self) -> dict[str, np.ndarray]:
        """name -> [T, 4, 4] float64 ``T_base_obj`` per frame (trained poses)."""
        return self.demonstration.object_poses

    @property
    def pose_sources(self) -> dict[str, list[str]]:
        """name -> per frame "static", "attached" or "tracked"."""
        return self.demonstration.pose_sources

    @property
    def phases(self) -> dict[str, list[Phase]]:
        """name -> its Motion/Skill segments."""
        return self.demonstration.phases

    @property
    def fps(self) -> float:
        return self.demonstration.fps

    @property
    def episode(self) -> str:
        """The source episode's folder name."""
        return self.demonstration.episode

    @property
    def task(self) -> str | None:
        return self.demonstration.task

    @property
    def commands(self) -> CommandRelation | None:
        """How the source's commands led and pressed its joints (None: not recorded)."""
        return self.demonstration.commands

    # ------------------------------------------------------------------ the rig
    @property
    def frame(self) -> str:
        """``"base"`` (one arm's base frame) or ``"world"`` (an arm set's world frame)."""
        return "world" if isinstance(self.robot, ArmSet) else BASE_FRAME

    @property
    def arm_names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.arms)

    @property
    def reference(self) -> TwinCamera:
        """The reference camera: fixed, the scene's anchor, the one renders default to."""
        return next(iter(self.cameras.values()))

    @property
    def camera_name(self) -> str:
        return self.reference.name

    @property
    def K(self) -> np.ndarray:
        """[3, 3] the reference camera's OpenCV intrinsics."""
        return self.reference.K

    @property
    def width(self) -> int:
        return self.reference.width

    @property
    def height(self) -> int:
        return self.reference.height

    @property
    def T_base_cam(self) -> np.ndarray:
        """[4, 4] float64 the reference camera in the twin's frame (refined in training when it was)."""
        return self.reference.T_mount_cam

    def _one_arm(self) -> TwinArm:
        if len(self.arms) != 1:
            raise ValueError(f"the twin has arms {', '.join(self.arm_names)}; this needs a twin of one arm")
        return self.arms[0]

    @property
    def robot_description(self) -> str:
        """The one arm's robot description (ValueError for a twin of several arms)."""
        return self._one_arm().description

    @property
    def robot_info(self) -> dict:
        """The one arm's ``model`` and ``joint_names`` (ValueError for a twin of several arms)."""
        arm = self._one_arm()
        return {"model": arm.model, "joint_names": list(arm.joint_names)}

    def arm_tracks(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Arm name -> (q [T, dof_arm] rad, gripper [T] m) of the source demonstration."""
        if not isinstance(self.robot, ArmSet):
            return {self.arms[0].name: (self.q, self.gripper)}
        return {name: (self.robot.arm_q(self.q, name).numpy(), self.gripper[:, k])
                for k, name in enumerate(self.arm_names)}

    def arm_commands(self) -> dict[str, CommandRelation | None]:
        """Arm name -> its part of :attr:`commands` (press [T, dof_arm], gripper [T, 1]; None for
        every arm without it)."""
        if self.commands is None or not isinstance(self.robot, ArmSet):
            return {name: self.commands for name in self.arm_names}
        gripper = self.commands.gripper
        return {name: CommandRelation(self.commands.lead, self.robot.arm_q(self.commands.press, name).numpy(),
                                      None if gripper is None else gripper[:, [k]])
                for k, name in enumerate(self.arm_names)}

    def joint_state(self, arms: Mapping[str, tuple[np.ndarray, float]]) -> tuple[np.ndarray, np.ndarray | float]:
        """(q [dof], gripper) as :meth:`render` takes them, from each arm's (q [dof_arm], gripper m)."""
        missing = [name for name in self.arm_names if name not in arms]
        if missing:
            raise ValueError(f"no joint state for arms {missing}")
        q = np.concatenate([np.asarray(arms[name][0], np.float64) for name in self.arm_names])
        gripper = np.array([float(arms[name][1]) for name in self.arm_names])
        return q, (float(gripper[0]) if not isinstance(self.robot, ArmSet) else gripper)

    # ------------------------------------------------------------------ rendering
    @property
    def n_frames(self) -> int:
        return len(self.t)

    @property
    def objects(self) -> list[str]:
        return list(self.graph.objects)

    def camera_pose(self, camera: str, link_poses: torch.Tensor) -> np.ndarray:
        """[4, 4] float64 ``T_base_cam`` of ``camera`` given the links' poses [L, 4, 4] (a riding camera
        moves with its link)."""
        cam = self.cameras[camera]
        if cam.fixed:
            return cam.T_mount_cam
        T_link = link_poses[self.robot.link_names.index(cam.mount)].double().cpu().numpy()
        return T_link @ cam.T_mount_cam

    @torch.no_grad()
    def render(self, q: np.ndarray, gripper: float | np.ndarray, object_poses: dict[str, np.ndarray], *,
               camera: str | None = None, T_base_cam: np.ndarray | None = None) -> TwinView:
        """The twin with the arms at joints ``q`` [dof] (rad; every arm's, in arm order) and gripper
        opening ``gripper`` (m; one per arm for several), each object at ``object_poses[name]``
        [4, 4] ``T_base_obj``, seen by ``camera`` (default the reference camera; a wrist camera
        where its link is at ``q``), or from ``T_base_cam`` [4, 4] (camera-to-frame) with that
        camera's intrinsics (:meth:`joint_state` assembles ``q`` and ``gripper`` per arm)."""
        missing = set(self.graph.objects) - set(object_poses)
        if missing:
            raise ValueError(f"render: no pose for objects {sorted(missing)}")
        name = self.camera_name if camera is None else camera
        if name not in self.cameras:
            raise ValueError(f"render: no camera {name!r}; cameras: {', '.join(self.cameras)}")
        cam = self.cameras[name]
        q = torch.as_tensor(np.asarray(q, np.float64))
        width = torch.as_tensor(np.asarray(gripper, np.float64))
        link_poses = self.robot.forward_kinematics(q, width)
        T = self.camera_pose(name, link_poses) if T_base_cam is None else np.asarray(T_base_cam, np.float64)
        poses = {k: torch.as_tensor(np.asarray(v, np.float64)).to(self.device) for k, v in object_poses.items()
                 if k in self.graph.objects}
        view = render_graph(self.graph, link_poses.to(self.device), poses,
                            viewmat=torch.as_tensor(np.linalg.inv(T)).float().to(self.device),
                            K=opencv_to_splat_K(torch.as_tensor(cam.K)).float().to(self.device), width=cam.width,
                            height=cam.height, background=self.background_rgb, backend=self.backend, depth=True,
                            groups_per_node=True)
        rgb = (view.rgb.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
        strongest, node = view.group_alphas.cpu().max(-1)
        labels = self._node_labels[node]
        labels[strongest < 0.5] = self._node_labels[0] if self.graph.background is not None else 0
        return TwinView(rgb=rgb, depth=view.depth.cpu().numpy().astype(np.float32), labels=labels.numpy().astype(np.uint8))

    def render_frame(self, i: int, camera: str | None = None) -> TwinView:
        """The twin in the source demonstration's state at frame ``i``, seen by ``camera`` (default
        the reference; a wrist camera at the joints of the reference camera's frame time)."""
        if not 0 <= i < self.n_frames:
            raise IndexError(f"frame {i} outside 0..{self.n_frames - 1}")
        return self.render(self.q[i], self.gripper[i], {k: v[i] for k, v in self.object_poses.items()}, camera=camera)

    def _label_of_nodes(self) -> torch.Tensor:
        """[nodes] the mask value of each node of :meth:`SceneGraph.nodes` (static nodes: "background")."""
        by_name = {name: value for value, name in self.labels.items()}
        static = by_name.get("background", 0)
        values = []
        for node in self.graph.nodes():
            kind, _, name = node.name.partition("/")
            values.append(static if kind == "background" else by_name.get(node.name, static))
        return torch.tensor(values, dtype=torch.long)

    # ------------------------------------------------------------------ files
    def save(self, folder: str | Path) -> None:
        """Write ``twin.json`` and ``twin.pt`` into ``folder`` (:mod:`manisplat.twin.files`)."""
        from manisplat.twin.files import save_twin

        save_twin(self, Path(folder))

    @classmethod
    def load(cls, folder: str | Path, *, backend: str = "auto", device: torch.device | str = "cpu") -> "Twin":
        """The twin a reconstruction folder holds (``manisplat-reconstruct --out``), its Gaussians on
        ``device`` ("cpu", "cuda"; where it renders, with ``backend`` "auto" picking gsplat on CUDA),
        whichever device it was trained on (:func:`manisplat.twin.files.load_twin`).

        Raises:
            TwinFormatError: ``twin.json`` or ``twin.pt`` missing, unreadable, or inconsistent.
            RobotModelError, FileNotFoundError: a robot description cannot be loaded.
        """
        from manisplat.twin.files import load_twin

        return load_twin(Path(folder), backend=backend, device=device)


def _arm_names(robot: RobotModel | ArmSet) -> tuple[str, ...]:
    return robot.arm_names if isinstance(robot, ArmSet) else (V1_ARM,)


def resolve_description(description: str, episode_dir: Path) -> str:
    """``robot.description`` made independent of the episode folder: a built-in name as it is, a
    relative URDF path made absolute against the episode folder."""
    if description.startswith("builtin:"):
        return description
    path = Path(description)
    return str(path if path.is_absolute() else (episode_dir / path).resolve())
