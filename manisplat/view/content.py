"""What ``manisplat-view PATH`` shows: the folder read into named arms, named cameras and
demonstrations (every arm's joints, object poses, images) and, where there is one, the twin. PATH
is an episode (format version 1 or 2), a reconstruction (``twin.json``) or an augmentation output
(``augment_report.json`` beside ``episode_*`` folders).

Everything is placed in one world frame: a version 2 episode's own (each arm at its
``T_world_base``); for a version 1 episode and a twin, the one arm's base frame (named
:data:`~manisplat.episode.format.V1_ARM`, ``T_world_base`` the identity)."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from manisplat.augment.writer import OBJECT_POSES_FILE
from manisplat.episode.format import V1_ARM, VERSION, WORLD_MOUNT, EpisodeFormatError
from manisplat.episode.reader import Episode
from manisplat.robot import RobotModel, RobotModelError, load_robot
from manisplat.twin.rig import TwinCamera

log = logging.getLogger(__name__)


class ViewInputError(ValueError):
    """PATH is not something the viewer shows, or a part it needs is missing (named)."""


@dataclass(frozen=True)
class ArmTrack:
    """One arm over a demonstration: ``q`` [T, 6] rad and ``gripper`` [T] m (finger-pad gap)."""

    q: np.ndarray
    gripper: np.ndarray


@dataclass
class Demo:
    """One demonstration to play.

    Attributes:
        name: shown in the list ("demo_episode", "episode_0003").
        t: [T] s.
        arms: arm name -> its :class:`ArmTrack` (one arm, :data:`V1_ARM`, for version 1 and twins).
        object_poses: name -> [T, 4, 4] float64 ``T_base_obj`` (empty when unknown).
        episode: the episode folder, for its images and depth (None for a twin without its episode).
        validation: the augmentation's validation record (augmented demonstrations only).
    """

    name: str
    t: np.ndarray
    arms: dict[str, ArmTrack]
    object_poses: dict[str, np.ndarray] = field(default_factory=dict)
    episode: Episode | None = None
    validation: dict[str, Any] | None = None

    def __len__(self) -> int:
        return len(self.t)

    @property
    def fps(self) -> float:
        """Frames per second over the demonstration (10 when it has one frame or no duration)."""
        t = self.t
        return (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else 10.0

    def _one_arm(self) -> ArmTrack:
        if len(self.arms) != 1:
            raise ValueError(f"{self.name} has arms {', '.join(self.arms)}; a twin is made of one arm")
        return next(iter(self.arms.values()))

    @property
    def q(self) -> np.ndarray:
        """[T, 6] rad: the joints of the one arm (a twin's demonstration); ValueError with several."""
        return self._one_arm().q

    @property
    def gripper(self) -> np.ndarray:
        """[T] m: the gripper of the one arm (a twin's demonstration); ValueError with several."""
        return self._one_arm().gripper


@dataclass(frozen=True)
class ViewArm:
    """An arm as shown: its robot model (with visual meshes) and ``T_world_base`` [4, 4] float64 (m)."""

    name: str
    robot: RobotModel
    T_world_base: np.ndarray


@dataclass(frozen=True)
class ViewCamera(TwinCamera):
    """A camera as shown: a :class:`~manisplat.twin.rig.TwinCamera` whose ``mount`` is ``"world"``
    (``T_mount_cam`` is then ``T_world_cam``) or ``"<arm>/<link>"`` (a wrist camera riding on that
    arm's link)."""

    @property
    def arm_link(self) -> tuple[str, str] | None:
        """(arm, link) the camera rides on, or None for a camera fixed in the world."""
        return None if self.mount == WORLD_MOUNT else tuple(self.mount.split("/", 1))  # type: ignore[return-value]


@dataclass
class ViewContent:
    """Everything the viewer and ``--video`` need.

    Attributes:
        kind: "episode", "reconstruction" or "augmentation".
        arms: arm name -> :class:`ViewArm` (one for version 1 and twins).
        cameras: camera name -> :class:`ViewCamera` (one for version 1 and twins).
        demos: the demonstrations (one except for an augmentation folder: the source first).
        twin: the reconstructed twin (None for an episode alone).
        notes: what is missing and therefore not shown, said to the user.
    """

    kind: str
    arms: dict[str, ViewArm]
    cameras: dict[str, ViewCamera]
    demos: list[Demo]
    twin: Any = None
    notes: list[str] = field(default_factory=list)

    @property
    def robot(self) -> RobotModel:
        """The robot model of the one arm (a twin's, or a one-arm episode's); ValueError with several."""
        if len(self.arms) != 1:
            raise ValueError(f"arms {', '.join(self.arms)}: no one robot")
        return next(iter(self.arms.values())).robot

    def object_poses_at(self, demo: Demo, i: int) -> dict[str, np.ndarray]:
        """Each of the twin's objects at frame ``i`` of ``demo``: [4, 4] ``T_base_obj`` from the
        demonstration's own track, else where the source demonstration starts it (empty without a twin)."""
        if self.twin is None:
            return {}
        return {name: demo.object_poses[name][i] if name in demo.object_poses else track[0]
                for name, track in self.twin.object_poses.items()}

    def twin_render(self, demo: Demo, i: int, T_base_cam: np.ndarray | None = None) -> np.ndarray:
        """[H, W, 3] uint8: the twin at frame ``i`` of ``demo`` (every arm's joints, the objects of
        :meth:`object_poses_at`) from its reference camera, or from ``T_base_cam`` [4, 4]."""
        q, gripper = self.twin.joint_state({name: (track.q[i], track.gripper[i]) for name, track in demo.arms.items()})
        return self.twin.render(q, gripper, self.object_poses_at(demo, i), T_base_cam=T_base_cam).rgb

    def link_poses(self, arm: str, demo: Demo, i: int | slice | np.ndarray) -> np.ndarray:
        """[..., L, 4, 4] ``T_base_link`` of ``arm``'s links (order ``robot.link_names``) at frame(s) ``i``."""
        import torch

        track = demo.arms[arm]
        return self.arms[arm].robot.forward_kinematics(torch.as_tensor(track.q[i], dtype=torch.float64),
                                                       torch.as_tensor(track.gripper[i], dtype=torch.float64)).numpy()

    def tcp_paths(self, demo: Demo) -> dict[str, np.ndarray]:
        """Arm name -> [T, 3] its TCP position at every frame of ``demo`` (m, world frame)."""
        import torch

        paths = {}
        for name, arm in self.arms.items():
            tcp = arm.robot.tcp_pose(torch.as_tensor(demo.arms[name].q, dtype=torch.float64)).numpy()[:, :3, 3]
            paths[name] = tcp @ arm.T_world_base[:3, :3].T + arm.T_world_base[:3, 3]
        return paths

    def camera_pose(self, camera: str, demo: Demo, i: int) -> np.ndarray:
        """[4, 4] ``T_world_cam`` of ``camera`` at frame ``i`` of ``demo``: ``T_mount_cam`` for a camera
        in the world, ``T_world_base @ FK(q_arm[i])[link] @ T_mount_cam`` for one on an arm's link."""
        cam = self.cameras[camera]
        if cam.arm_link is None:
            return cam.T_mount_cam
        arm_name, link = cam.arm_link
        arm = self.arms[arm_name]
        T_base_link = self.link_poses(arm_name, demo, i)[arm.robot.link_index(link)]
        return arm.T_world_base @ T_base_link @ cam.T_mount_cam


def _episode_demo(ep: Episode, name: str | None = None) -> Demo:
    arms = {arm: ArmTrack(f.q, f.gripper) for arm, f in ((a, ep.arm_frames(a)) for a in ep.arms)}
    return Demo(name=name or ep.path.name, t=ep.arm_frames(next(iter(ep.arms))).t, arms=arms, episode=ep)


def _episode_arms(ep: Episode) -> dict[str, ViewArm]:
    """Each arm of ``ep`` with its robot (one model per description) and base; raises naming the
    arms whose base is not calibrated."""
    uncalibrated = [name for name, info in ep.arms.items() if info.T_world_base is None]
    if uncalibrated:
        raise ViewInputError(f"{ep.path}: arm {', '.join(uncalibrated)} has no T_world_base (base not calibrated); "
                             "run manisplat-calibrate and `manisplat-calibrate apply`, so every arm stands in one world")
    robots: dict[str, RobotModel] = {}
    for info in ep.arms.values():
        if info.description not in robots:
            robots[info.description] = load_robot(info.description, ep.path)
    return {name: ViewArm(name, robots[info.description], np.asarray(info.T_world_base, np.float64))
            for name, info in ep.arms.items()}


def _world_mount(mount: str, version: int) -> str:
    """A camera's mount in version 2 terms (version 1's ``base`` is the world, a link is on the one arm)."""
    if version != VERSION:
        return mount
    return WORLD_MOUNT if mount == "base" else f"{V1_ARM}/{mount}"


def _episode_cameras(ep: Episode, arms: dict[str, ViewArm]) -> dict[str, ViewCamera]:
    """Each camera of ``ep``; raises naming the cameras without ``T_mount_cam`` and a mount on a
    link the arm's robot does not have."""
    uncalibrated = [name for name, info in ep.cameras.items() if info.T_mount_cam is None]
    if uncalibrated:
        raise ViewInputError(f"{ep.path}: camera {', '.join(uncalibrated)} has no T_mount_cam (uncalibrated); run "
                             "manisplat-calibrate and `manisplat-calibrate apply`, so the robot and depth can be "
                             "placed in one frame")
    cameras = {}
    for name, info in ep.cameras.items():
        mount = _world_mount(info.mount, ep.meta.version)
        if mount != WORLD_MOUNT:
            arm, link = mount.split("/", 1)
            try:
                arms[arm].robot.link_index(link)
            except RobotModelError as exc:
                raise ViewInputError(f"{ep.path}: camera {name} rides on {info.mount!r}: {exc}") from None
        cameras[name] = ViewCamera(name, np.asarray(info.K, np.float64), info.width, info.height, mount,
                                   np.asarray(info.T_mount_cam, np.float64))
    return cameras


def _load_episode(path: Path) -> ViewContent:
    ep = Episode.open(path)
    arms = _episode_arms(ep)
    cameras = _episode_cameras(ep, arms)
    has_depth = any(ep.has_images("depth", name) for name in cameras)
    notes = [] if has_depth else ["the episode has no depth: no point cloud"]
    return ViewContent("episode", arms, cameras, [_episode_demo(ep)], notes=notes)


def _twin_parts(twin: Any) -> tuple[dict[str, ViewArm], dict[str, ViewCamera]]:
    """The twin's arms (a one-arm twin's base is the world) and cameras."""
    arms = {arm.name: ViewArm(arm.name, load_robot(arm.description), arm.T_world_base) for arm in twin.arms}
    one_arm = twin.frame == "base"
    cameras = {cam.name: ViewCamera(cam.name, cam.K, cam.width, cam.height,
                                    WORLD_MOUNT if cam.fixed else f"{V1_ARM}/{cam.mount}" if one_arm else cam.mount,
                                    cam.T_mount_cam) for cam in twin.cameras.values()}
    return arms, cameras


def _find_episode(name: str, near: list[Path]) -> Path | None:
    for base in near:
        candidate = base / name
        if (candidate / "episode.json").is_file():
            return candidate
    return None


def _load_twin(path: Path, episode: Path | None) -> tuple[Any, Demo, list[str]]:
    from manisplat.twin import Twin, TwinFormatError

    try:
        twin = Twin.load(path)
    except TwinFormatError as exc:  # a missing or damaged twin.pt, a twin.json that does not match it
        raise ViewInputError(str(exc)) from exc
    notes = []
    found = episode or _find_episode(twin.episode, [path.parent, Path.cwd()])
    ep = None
    if found is not None:
        ep = Episode.open(found)
        if len(ep) != twin.n_frames:
            raise ViewInputError(f"{found}: {len(ep)} frames, but the twin was made from {twin.n_frames}; pass the "
                                 "episode it was reconstructed from with --episode")
        if twin.camera_name not in ep.cameras:
            raise ViewInputError(f"{found}: cameras {', '.join(ep.cameras)}, but the twin was made from camera "
                                 f"{twin.camera_name!r}; pass the episode it was reconstructed from with --episode")
    else:
        notes.append(f"the source episode {twin.episode!r} was not found beside {path} or here: no recorded images "
                     "(pass --episode EP to show them)")
    demo = Demo(name=twin.episode, t=twin.t, arms={name: ArmTrack(q, gripper) for name, (q, gripper)
                                                   in twin.arm_tracks().items()},
                object_poses=twin.object_poses, episode=ep)
    return twin, demo, notes


def _load_reconstruction(path: Path, episode: Path | None) -> ViewContent:
    twin, demo, notes = _load_twin(path, episode)
    return ViewContent("reconstruction", *_twin_parts(twin), [demo], twin=twin, notes=notes)


def _augmented_demo(folder: Path, notes: list[str]) -> Demo:
    ep = Episode.open(folder)
    demo = _episode_demo(ep)
    record_path = folder / "augmentation.json"
    if record_path.is_file():
        demo.validation = json.loads(record_path.read_text()).get("validation")
    poses = folder / OBJECT_POSES_FILE
    if poses.is_file():
        with np.load(poses) as data:
            demo.object_poses = {k: data[k] for k in data.files}
    else:
        notes.append(f"{folder.name}: no {OBJECT_POSES_FILE} (made before the viewer existed): objects stay where "
                     "the source demonstration had them")
    return demo


def _load_augmentation(path: Path, twin_path: Path | None, episode: Path | None) -> ViewContent:
    report = json.loads((path / "augment_report.json").read_text())
    recon = twin_path
    if recon is None:
        recon_name = Path(report.get("recon", ""))
        for base in (path.parent, Path.cwd()):
            candidate = recon_name if recon_name.is_absolute() else base / recon_name
            if (candidate / "twin.json").is_file():
                recon = candidate
                break
    if recon is None:
        raise ViewInputError(f"{path}: the twin it was made from ({report.get('recon')!r}) was not found beside it or "
                             "here; pass --twin RECON_DIR")
    twin, source, notes = _load_twin(recon, episode)
    demos = [source]
    for sample in report.get("samples", []):
        folder = path / str(sample.get("episode", ""))
        if sample.get("valid") and (folder / "episode.json").is_file():
            demos.append(_augmented_demo(folder, notes))
    if len(demos) == 1:
        notes.append(f"{path}: no augmented demonstration written")
    return ViewContent("augmentation", *_twin_parts(twin), demos, twin=twin, notes=notes)


def load_content(path: str | Path, *, twin: str | Path | None = None, episode: str | Path | None = None) -> ViewContent:
    """Read PATH (an episode, a reconstruction or an augmentation output) for viewing.

    Args:
        path: the folder.
        twin: the reconstruction an augmentation folder was made from (default: its report's ``recon``).
        episode: the episode a reconstruction was made from (default: its name beside it or here).

    Raises:
        ViewInputError: PATH is none of the three, or a part is missing (named, with what to pass).
    """
    path = Path(path)
    if not path.is_dir():
        raise ViewInputError(f"{path}: no such folder")
    episode_path = None if episode is None else Path(episode)
    try:
        if (path / "augment_report.json").is_file():
            return _load_augmentation(path, None if twin is None else Path(twin), episode_path)
        if (path / "twin.json").is_file():
            return _load_reconstruction(path, episode_path)
        if (path / "episode.json").is_file():
            return _load_episode(path)
    except EpisodeFormatError as exc:
        raise ViewInputError(str(exc)) from exc
    if (path / "metrics.json").is_file():
        raise ViewInputError(f"{path}: a reconstruction folder without twin.json (interrupted before the end?); "
                             "rerun manisplat-reconstruct or --resume it")
    raise ViewInputError(f"{path}: neither an episode (episode.json), a reconstruction (twin.json) nor an "
                         "augmentation output (augment_report.json)")
