"""An episode loaded for reconstruction: images, masks, depth, the camera in the rasterizer's
convention, every link pose by forward kinematics, and which mask labels are which node."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from manisplat.episode import CameraInfo, Episode
from manisplat.episode.format import GRIPPER_EFFORT_COLUMN, V1_ARM, WORLD_MOUNT
from manisplat.episode.images import StoredChroma, describe_chroma
from manisplat.geometry import matrix_to_quat
from manisplat.reconstruct.lens import undistortion_for
from manisplat.robot import RobotModel, load_robot
from manisplat.robot.arms import ArmSet
from manisplat.splat import opencv_to_splat_K
from manisplat.twin.commands import CommandRelation, command_relation
from manisplat.twin.rig import TwinArm, one_arm
from manisplat.twin.twin import resolve_description

log = logging.getLogger(__name__)


class ReconstructionInputError(ValueError):
    """The episode lacks something reconstruction needs (a calibrated camera, a pinhole model...)."""


@dataclass
class Labels:
    """Mask label values by role: robot links, manipulated objects, and everything static."""

    robot: dict[int, str] = field(default_factory=dict)  # value -> link name
    objects: dict[int, str] = field(default_factory=dict)  # value -> object name
    static: list[int] = field(default_factory=list)

    @property
    def moving(self) -> list[int]:
        """The label values of what moves (robot links and manipulated objects), sorted."""
        return sorted({*self.robot, *self.objects})

    @classmethod
    def from_meta(cls, labels: dict[int, str], objects: list[str]) -> "Labels":
        out = cls()
        for value, name in labels.items():
            if name.startswith("robot/"):
                out.robot[value] = name[len("robot/"):]
            elif name.startswith("object/") and name[len("object/"):] in objects:
                out.objects[value] = name[len("object/"):]
            else:
                out.static.append(value)  # background, table, distractors that never move
        return out


@dataclass
class JointStream:
    """The raw joint stream (``joints.csv``): t [N] s, q [N, dof] rad, gripper [N] m."""

    t: np.ndarray
    q: np.ndarray
    gripper: np.ndarray

    def at(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(q [M, dof], gripper [M]) linearly interpolated at ``times`` [M] (held at the ends)."""
        q = np.stack([np.interp(times, self.t, self.q[:, j]) for j in range(self.q.shape[1])], 1)
        return q, np.interp(times, self.t, self.gripper)


@dataclass
class ArmStreams:
    """The raw joint streams of several arms (``joints_<arm>.csv``), each at its own times."""

    streams: dict[str, JointStream]

    def at(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(q [M, sum of dof], gripper [M, A]) at ``times`` [M]: the arms' joints concatenated in
        order, each arm's read from its own stream."""
        read = [stream.at(times) for stream in self.streams.values()]
        return np.concatenate([q for q, _ in read], 1), np.stack([g for _, g in read], 1)


@dataclass
class EpisodeData:
    """Everything reconstruction reads from one episode, as tensors.

    Attributes:
        rgb: [T, H, W, 3] uint8. depth: [T, H, W] float32 metres (0 invalid) or None.
        masks: [T, H, W] uint8 labels or None. t: [T] s. q: [T, dof] rad. gripper: [T] m.
        K: [3, 3] intrinsics in the rasterizer's half-pixel convention. viewmat: [4, 4] base-to-camera,
            or [T, 4, 4] per frame for a camera riding on a link (:attr:`mount`; :meth:`view_at`).
        link_poses: [T, L, 4, 4] T_base_link. link_quats: [T, L, 4] their rotations as quaternions.
        tcp: [T, 4, 4] T_base_tcp.
        robot: one arm's :class:`RobotModel` (format version 1: everything is in its base frame),
            or an :class:`~manisplat.robot.arms.ArmSet` (version 2: several arms, everything in
            the episode's world frame, which the names ``T_base_*`` then mean; ``q`` [T, sum of
            dof] the arms' joints in order, ``gripper`` [T, A], ``tcp`` [T, A, 4, 4]; per arm
            :meth:`arm_tcp`, :meth:`arm_gripper`).
        frame: what the poses are in: ``"base"`` (one arm) or ``"world"`` (an arm set); ground
            truth names object poses ``T_<frame>_<object>``.
        mount: where the camera is: ``"base"`` / ``"world"`` (fixed), or the link it rides on, as
            the robot names it (``"link6"``, ``"left/link6"``); T_mount_cam: [4, 4] float64 the
            camera in that link's frame (None for a fixed camera).
        arms: each arm's robot description (independent of the episode folder: a built-in name or
            an absolute URDF path), model, joint names and base, in the order of ``q``
            (:class:`~manisplat.twin.rig.TwinArm`; one arm at the identity for version 1).
        label_names: mask value -> name of ``masks`` (the episode's ``labels``, or the drawn ones).
        fps, camera_name, task: the episode's.
        mask_source: where ``masks`` came from ("episode", or what :mod:`manisplat.reconstruct.masks` drew).
        eval_masks, eval_labels: the episode's own masks and labels when reconstruction ignores
            them (region metrics still use them).
        valid: [H, W] bool, the pixels the recording covers after undistortion
            (:mod:`manisplat.reconstruct.lens`), or None when every pixel is valid; losses and
            metrics read only valid pixels.
        dist: the episode's distortion coefficients, removed on load (the images, depth and masks
            here are the pinhole camera's with ``K_opencv``).
        joints: the raw joint stream, or None without ``joints.csv``.
        recorded_latency_s: the camera latency the recorder compensated when it paired joints
            with frames (episode.json ``clock.camera_latency_s``; 0 when unknown).
        time_offset_s: frame f shows the robot at joint time ``t[f] + time_offset_s``; ``q``,
            ``gripper`` and the poses are read there (:func:`retime`).
        commands: how ``frames.csv``'s commands relate to its joints (:func:`recorded_commands`,
            before any retiming), or None where the episode records no commands.
        chroma_subsampling: how the recording kept the images' colour
            (:meth:`~manisplat.episode.reader.Episode.chroma_subsampling`), or None where unknown:
            renders are compared with the images after the same (:mod:`manisplat.reconstruct.chroma`;
            after undistortion, an approximation of it).
        gripper_effort: arm -> its gripper's effort [T] at the frames' joint times as recorded
            (``frames.csv``'s ``gripper_effort`` column, before any retiming), for the arms that
            record one; read through :meth:`arm_gripper_effort`.
        riding_cameras: the episode's cameras that ride on a link, whether trained or not: name ->
            (the link as the robot names it, ``T_link_cam`` [4, 4] float64); their bodies are
            looked for in this camera's depth (:mod:`manisplat.reconstruct.camera_bodies`).
    """

    path: Path
    robot: RobotModel | ArmSet
    rgb: torch.Tensor
    depth: torch.Tensor | None
    masks: torch.Tensor | None
    t: torch.Tensor
    q: torch.Tensor
    gripper: torch.Tensor
    K: torch.Tensor
    K_opencv: torch.Tensor
    viewmat: torch.Tensor
    link_poses: torch.Tensor
    link_quats: torch.Tensor
    tcp: torch.Tensor
    labels: Labels
    objects: list[str]
    arms: tuple[TwinArm, ...] = ()
    label_names: dict[int, str] = field(default_factory=dict)
    fps: float = 0.0
    camera_name: str = "camera"
    task: str | None = None
    mask_source: str = "episode"
    eval_masks: torch.Tensor | None = None
    eval_labels: Labels | None = None
    valid: torch.Tensor | None = None
    dist: tuple[float, ...] = ()
    joints: JointStream | ArmStreams | None = None
    recorded_latency_s: float = 0.0
    time_offset_s: float = 0.0
    frame: str = "base"
    mount: str = "base"
    T_mount_cam: torch.Tensor | None = None
    commands: CommandRelation | None = None
    chroma_subsampling: StoredChroma | None = None
    riding_cameras: dict[str, tuple[str, torch.Tensor]] = field(default_factory=dict)
    gripper_effort: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return len(self.t)

    @property
    def device(self) -> torch.device:
        """Where the images (and every other tensor, after :meth:`to`) are."""
        return self.rgb.device

    def to(self, device: torch.device | str) -> "EpisodeData":
        """A copy with every tensor on ``device`` (dtypes kept: images stay uint8, poses float64
        where they were); the robot model, labels and ground truth (numpy) stay as they are."""
        device = torch.device(device)
        moved = {f.name: getattr(self, f.name).to(device) for f in fields(self)
                 if isinstance(getattr(self, f.name), torch.Tensor)}
        return replace(self, **moved)

    @property
    def riding(self) -> bool:
        """Whether the camera rides on a link (a wrist camera): ``viewmat`` is per frame."""
        return self.T_mount_cam is not None

    def view_at(self, f: int) -> torch.Tensor:
        """[4, 4] float32 base-to-camera of frame ``f``."""
        return self.viewmat[f] if self.riding else self.viewmat

    @property
    def arm_names(self) -> tuple[str, ...]:
        """The arms, in the order of ``q``, ``gripper`` and ``tcp`` (one arm: ``("arm",)``)."""
        return self.robot.arm_names if isinstance(self.robot, ArmSet) else (V1_ARM,)

    def arm_tcp(self, arm: str) -> torch.Tensor:
        """[T, 4, 4] ``T_base_tcp`` of ``arm`` (world frame for an arm set)."""
        return self.tcp[:, self.arm_names.index(arm)] if isinstance(self.robot, ArmSet) else self.tcp

    def arm_gripper(self, arm: str) -> torch.Tensor:
        """[T] the gripper opening of ``arm`` (m)."""
        return self.gripper[:, self.arm_names.index(arm)] if isinstance(self.robot, ArmSet) else self.gripper

    def arm_gripper_effort(self, arm: str) -> np.ndarray | None:
        """[T] float64 the gripper effort of ``arm`` at each frame's joint time (``t + time_offset_s``,
        as ``gripper``), or None where the episode records none."""
        effort = self.gripper_effort.get(arm)
        if effort is None or self.time_offset_s == 0.0:
            return effort
        t = self.t.cpu().numpy()
        return np.interp(t + self.time_offset_s, t, effort)

    def tcp_poses(self) -> torch.Tensor:
        """[T, A, 4, 4] every arm's TCP (one arm: A = 1)."""
        return self.tcp if isinstance(self.robot, ArmSet) else self.tcp[:, None]

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.rgb.shape[2], self.rgb.shape[1]

    def image(self, i: int) -> torch.Tensor:
        """Frame ``i`` as [H, W, 3] float32 in [0, 1]."""
        return self.rgb[i].float() / 255.0

    def region(self, i: int, values) -> torch.Tensor:
        """[H, W] bool: pixels of frame ``i`` whose label is in ``values`` (False without masks)."""
        if self.masks is None:
            return torch.zeros(self.rgb.shape[1:3], dtype=torch.bool, device=self.device)
        return torch.isin(self.masks[i], torch.tensor(sorted(values), dtype=torch.uint8).to(self.device))

    def eval_region(self, i: int, role: str) -> torch.Tensor:
        """[H, W] bool: the ground-truth ``role`` ("robot" or "object") region of frame ``i``, from the
        episode's own masks when it has them (even when reconstruction ignored them), else ``masks``."""
        masks, labels = (self.eval_masks, self.eval_labels) if self.eval_masks is not None else (self.masks, self.labels)
        if masks is None:
            return torch.zeros(self.rgb.shape[1:3], dtype=torch.bool, device=self.device)
        values = labels.robot if role == "robot" else labels.objects
        return torch.isin(masks[i], torch.tensor(sorted(values), dtype=torch.uint8).to(masks.device))


def load_episode_data(path: str | Path, *, robot: str | None = None, camera: str | None = None,
                      load_meshes: bool = True, use_depth: bool = True, use_masks: bool = True,
                      progress: bool = False) -> EpisodeData:
    """Read an episode for reconstruction.

    Args:
        robot: a robot description overriding the episode's (every arm's) ``description``.
        camera: the camera to reconstruct from, by name (default: the episode's one camera, or
            its one world-fixed camera when it has several).
        use_depth, use_masks: False ignores the episode's depth (monocular reconstruction) or masks
            (drawn and segmented instead; the episode's are kept in ``eval_masks`` for metrics).
        progress: show a progress bar while the images load.

    Raises:
        ReconstructionInputError: the camera is not calibrated (no ``T_mount_cam``), rides on an
            arm, or is not one of the episode's; an arm of several has no ``T_world_base``.

    An episode with several arms or cameras (format version 2) is read in its world frame with
    an :class:`~manisplat.robot.arms.ArmSet`; a version 1 episode in its arm's base frame. Lens
    distortion (``camera.dist``) is removed on load: images, depth and masks are resampled to the
    pinhole camera with the same ``K`` (:mod:`manisplat.reconstruct.lens`).
    """
    episode = Episode.open(path)
    several = len(episode.arms) > 1 or len(episode.cameras) > 1
    cam = _camera_of(episode, camera) if several else episode.camera
    if cam.T_mount_cam is None:
        raise ReconstructionInputError(
            f"{episode.path}: camera {cam.name}: T_mount_cam is null; calibrate the camera (manisplat-calibrate) first"
        )
    try:
        lens = undistortion_for(cam.K, cam.dist, cam.width, cam.height)
    except ValueError as exc:
        raise ReconstructionInputError(f"{episode.path}: {exc}") from None
    if lens is not None:
        log.info("undistorting %s: dist %s, pixels moved up to %.1f px, %.1f %% of the pinhole image covered",
                 episode.path, cam.dist.tolist(), lens.shift_px, 100 * lens.valid_fraction)
    _check_ground_truth(episode)  # refused before training; the evaluation reads it again
    view = cam.name if several else None  # the one-camera view of a version 1 episode takes no name
    n = len(episode)
    has_depth = episode.has_images("depth", view) if several else episode.has_depth
    has_masks = episode.has_images("masks", view) if several else episode.has_masks
    rgb = torch.empty(n, cam.height, cam.width, 3, dtype=torch.uint8)
    depth = torch.empty(n, cam.height, cam.width) if has_depth and use_depth else None
    masks = torch.empty(n, cam.height, cam.width, dtype=torch.uint8) if has_masks else None
    for i in tqdm(range(n), desc="loading frames", unit="frame", leave=False, disable=not progress):
        image = episode.rgb(i, view)
        z = episode.depth(i, view) if depth is not None else None
        label_image = episode.mask(i, view) if masks is not None else None
        if lens is not None:
            image = lens.rgb(image)
            z = None if z is None else lens.depth(z)
            label_image = None if label_image is None else lens.labels(label_image)
        rgb[i] = torch.from_numpy(image)
        if depth is not None:
            depth[i] = torch.from_numpy(z)
        if masks is not None:
            masks[i] = torch.from_numpy(label_image)
    if several:
        model, t, q, gripper, stream, effort = _arms_of(episode, robot, load_meshes, episode.camera_times(view))
        arms = tuple(TwinArm(name, resolve_description(robot or arm.description, episode.path), arm.model,
                             tuple(arm.joint_names), arm.T_world_base) for name, arm in episode.arms.items())
    else:
        description = robot or episode.meta.robot.description
        model = load_robot(description, base_dir=episode.path, load_meshes=load_meshes)
        frames = episode.frames
        t, q, gripper = frames.t, frames.q, frames.gripper
        effort = {V1_ARM: frames.extra[GRIPPER_EFFORT_COLUMN]} if GRIPPER_EFFORT_COLUMN in frames.extra else {}
        joints = episode.joints()
        stream = None if joints is None else JointStream(joints.t, joints.q, joints.gripper)
        arms = (one_arm(resolve_description(description, episode.path), episode.meta.robot.model,
                        episode.meta.robot.joint_names),)
    q = torch.as_tensor(q, dtype=torch.float64)
    gripper = torch.as_tensor(gripper, dtype=torch.float64)
    link_poses = model.forward_kinematics(q, gripper).float()
    K = torch.as_tensor(cam.K, dtype=torch.float64)
    T_mount_cam = torch.as_tensor(cam.T_mount_cam, dtype=torch.float64)
    fixed = cam.mount in ("base", WORLD_MOUNT)
    if not fixed and cam.mount not in model.link_names:
        raise ReconstructionInputError(f"{episode.path}: camera {cam.name} is mounted on {cam.mount!r}, which is no "
                                       f"link of the robot ({', '.join(model.link_names)})")
    labels = Labels.from_meta(episode.meta.labels, episode.meta.objects)
    eval_masks = None
    if masks is not None and not use_masks:
        eval_masks, masks, labels = masks, None, Labels()
    chroma = episode.chroma_subsampling(view)
    log.info("loaded %s: %d frames of camera %s %dx%d (chroma %s), depth %s, masks %s, robot %s", episode.path, n,
             cam.name, cam.width, cam.height, describe_chroma(chroma), depth is not None,
             masks is not None, model.name)
    clock = episode.meta.extra.get("clock")
    recorded_latency = float(clock.get("camera_latency_s") or 0.0) if isinstance(clock, dict) else 0.0
    data = EpisodeData(
        path=episode.path, robot=model, rgb=rgb, depth=depth, masks=masks,
        t=torch.as_tensor(t, dtype=torch.float64), q=q, gripper=gripper,
        K=opencv_to_splat_K(K).float(), K_opencv=K, viewmat=torch.linalg.inv(T_mount_cam).float(),
        link_poses=link_poses, link_quats=matrix_to_quat(link_poses[..., :3, :3].double()).float(),
        tcp=_tcp_of(model, q).float(), labels=labels,
        objects=list(episode.meta.objects), eval_masks=eval_masks,
        arms=arms, fps=float(episode.meta.fps), camera_name=cam.name, task=episode.meta.extra.get("task"),
        label_names={} if eval_masks is not None else dict(episode.meta.labels),
        eval_labels=Labels.from_meta(episode.meta.labels, episode.meta.objects) if eval_masks is not None else None,
        valid=None if lens is None or lens.valid.all() else torch.from_numpy(lens.valid),
        dist=tuple(float(d) for d in cam.dist) if lens is not None else (),
        joints=stream, recorded_latency_s=recorded_latency, frame="world" if several else "base",
        mount=cam.mount, T_mount_cam=None if fixed else T_mount_cam, commands=recorded_commands(episode),
        chroma_subsampling=chroma,
        riding_cameras={c.name: (c.mount, torch.as_tensor(c.T_mount_cam, dtype=torch.float64))
                        for c in episode.cameras.values() if c.mount not in ("base", WORLD_MOUNT)
                        and c.T_mount_cam is not None and c.mount in model.link_names} if several else {},
        gripper_effort=effort,
    )
    if not fixed:
        _place_riding_camera(data, q, gripper)
    latency = cam.extra.get("latency_s")
    if isinstance(latency, (int, float)) and abs(latency - recorded_latency) > 1e-6:
        retime(data, -(latency - recorded_latency))
        log.info("camera latency %.1f ms (episode.json camera.latency_s) where the recorder paired joints with %.1f ms: "
                 "joints re-read %.1f ms earlier", 1e3 * latency, 1e3 * recorded_latency, 1e3 * (latency - recorded_latency))
    return data


def _camera_of(episode: Episode, name: str | None) -> CameraInfo:
    """The camera ``name`` of an episode with several, or (None) its one world-fixed camera."""
    cameras = episode.cameras
    if name is not None:
        if name not in cameras:
            raise ReconstructionInputError(f"{episode.path}: no camera {name!r}; cameras: {', '.join(cameras)}")
        return cameras[name]
    fixed = [c for c in cameras.values() if c.mount == WORLD_MOUNT]
    if len(fixed) != 1:
        raise ReconstructionInputError(
            f"{episode.path}: cameras {', '.join(f'{c.name} ({c.mount})' for c in cameras.values())}: "
            "say which to reconstruct from with --camera NAME")
    return fixed[0]


def _arms_of(episode: Episode, robot: str | None, load_meshes: bool, camera_times: np.ndarray):
    """(ArmSet, t [T], q [T, sum of dof], gripper [T, A], joint streams or None, arm -> gripper
    effort [T] where recorded) of an episode with several arms or cameras, seen by a camera whose
    frames were exposed at ``camera_times`` [T] s: where they are not the frames' times (a camera
    of a rig, stamped on its own), the joints are read at them, from the joint streams or between
    the frames (the efforts between the frames)."""
    models, bases = {}, {}
    for name, arm in episode.arms.items():
        if arm.T_world_base is None:
            raise ReconstructionInputError(f"{episode.path}: arm {name}: T_world_base is null; calibrate the rig "
                                           "(manisplat-calibrate solve-rig, then apply) first")
        models[name] = load_robot(robot or arm.description, base_dir=episode.path, load_meshes=load_meshes)
        bases[name] = arm.T_world_base
    tables = {name: episode.arm_frames(name) for name in episode.arms}
    t = next(iter(tables.values())).t
    q = np.concatenate([table.q for table in tables.values()], 1)
    gripper = np.stack([table.gripper for table in tables.values()], 1)
    effort = {name: table.extra[GRIPPER_EFFORT_COLUMN] for name, table in tables.items()
              if GRIPPER_EFFORT_COLUMN in table.extra}
    joints = {name: episode.joints(name) for name in episode.arms}
    stream = None if any(j is None for j in joints.values()) else \
        ArmStreams({name: JointStream(j.t, j.q, j.gripper) for name, j in joints.items()})
    if np.abs(camera_times - t).max(initial=0.0) > 1e-9:
        if stream is not None:
            q, gripper = stream.at(camera_times)
        else:
            q = np.stack([np.interp(camera_times, t, q[:, j]) for j in range(q.shape[1])], 1)
            gripper = np.stack([np.interp(camera_times, t, gripper[:, a]) for a in range(gripper.shape[1])], 1)
        effort = {name: np.interp(camera_times, t, values) for name, values in effort.items()}
        t = camera_times
    return ArmSet(models, bases), t, q, gripper, stream, effort


def _place_riding_camera(data: EpisodeData, q: torch.Tensor, gripper: torch.Tensor) -> None:
    """Set ``data.viewmat`` [T, 4, 4] of a camera riding on a link: ``inv(T_base_link(q) @
    T_mount_cam)`` per frame, from float64 forward kinematics."""
    link = data.robot.link_names.index(data.mount)
    T_link = data.robot.forward_kinematics(q.double(), gripper.double())[:, link]
    data.viewmat = torch.linalg.inv(T_link @ data.T_mount_cam.to(T_link)).float().to(data.device)


def _tcp_of(robot: RobotModel | ArmSet, q: torch.Tensor) -> torch.Tensor:
    """[T, 4, 4] the one arm's TCP, or [T, A, 4, 4] every arm's (an arm set)."""
    return robot.tcp_poses(q) if isinstance(robot, ArmSet) else robot.tcp_pose(q)


def joints_at(data: EpisodeData, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(q [M, dof] rad, gripper [M] m) at joint-stream times ``times`` [M] s: from ``joints.csv``,
    or, without one, interpolated between the frames' own joints (frame f's at ``t[f] + time_offset_s``)."""
    if data.joints is not None:
        return data.joints.at(times)
    when = data.t.cpu().numpy() + data.time_offset_s
    q, gripper = data.q.cpu().numpy(), data.gripper.cpu().numpy()
    if gripper.ndim == 1:
        return np.stack([np.interp(times, when, q[:, j]) for j in range(q.shape[1])], 1), np.interp(times, when, gripper)
    return (np.stack([np.interp(times, when, q[:, j]) for j in range(q.shape[1])], 1),
            np.stack([np.interp(times, when, gripper[:, a]) for a in range(gripper.shape[1])], 1))


def retime(data: EpisodeData, offset_s: float) -> None:
    """Pair frame f with the joints at ``t[f] + offset_s`` (in place; absolute, relative to
    frames.csv): ``q``, ``gripper``, link poses and TCP re-read by :func:`joints_at`."""
    if not math.isfinite(offset_s) or abs(offset_s) > 1.0:
        raise ValueError(f"time offset {offset_s} s: expected a finite offset within 1 s")
    q, gripper = joints_at(data, data.t.cpu().numpy() + offset_s)
    device = data.q.device
    data.q = torch.as_tensor(q, dtype=torch.float64)
    data.gripper = torch.as_tensor(gripper, dtype=torch.float64)
    data.link_poses = data.robot.forward_kinematics(data.q, data.gripper).float()
    data.link_quats = matrix_to_quat(data.link_poses[..., :3, :3].double()).float()
    data.tcp = _tcp_of(data.robot, data.q).float()
    for name in ("q", "gripper", "link_poses", "link_quats", "tcp"):
        setattr(data, name, getattr(data, name).to(device))
    if data.riding:
        _place_riding_camera(data, data.q, data.gripper)
    data.time_offset_s = offset_s


def recorded_commands(episode: Episode) -> CommandRelation | None:
    """How ``frames.csv``'s commands ``a1..a6`` relate to its joints ``q`` (every arm's, in arm
    order; both as recorded at each frame): their lead and press, with the commanded ``a_gripper``
    of every arm. None where an arm records no commands."""
    tables = [episode.arm_frames(name) for name in episode.arms]
    if any(table.actions is None for table in tables):
        return None
    return command_relation(np.concatenate([table.q for table in tables], axis=1),
                            np.concatenate([table.actions[:, :6] for table in tables], axis=1),
                            np.stack([table.actions[:, 6] for table in tables], axis=1))


def load_ground_truth(path: str | Path) -> dict[str, np.ndarray] | None:
    """The episode's ``gt.npz`` (None without one), checked against its frames. Only evaluation
    reads it: nothing that trains sees ground truth (:class:`EpisodeData` does not carry it)."""
    episode = Episode.open(path)
    return _check_ground_truth(episode)


def _check_ground_truth(episode: Episode) -> dict[str, np.ndarray] | None:
    """``gt.npz``, or a refusal of object poses in it that do not match the frames (e.g. an
    episode recovered with frames dropped but gt.npz left as it was): metrics would fail after it."""
    gt = episode.gt()
    if gt is None:
        return None
    n = len(episode)
    for key in (f"T_{frame}_{name}" for name in episode.meta.objects for frame in ("base", "world")):
        poses = gt.get(key)
        if poses is not None and poses.shape != (n, 4, 4):
            raise ReconstructionInputError(
                f"{episode.path / 'gt.npz'}: {key} has shape {tuple(poses.shape)} but frames.csv has {n} "
                f"frames (expected ({n}, 4, 4)); run `manisplat-episode validate {episode.path}`, and fix or "
                "remove gt.npz (without it the pose error is not measured)")
    return gt

