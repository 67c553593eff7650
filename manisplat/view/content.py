"""What ``manisplat-view PATH`` shows: the folder read into demonstrations (joints, object poses,
images) and, where there is one, the twin. PATH is an episode, a reconstruction (``twin.json``) or
an augmentation output (``augment_report.json`` beside ``episode_*`` folders)."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from manisplat.augment.writer import OBJECT_POSES_FILE
from manisplat.episode.format import EpisodeFormatError
from manisplat.episode.reader import Episode
from manisplat.robot import RobotModel, load_robot

log = logging.getLogger(__name__)



class ViewInputError(ValueError):
    """PATH is not something the viewer shows, or a part it needs is missing (named)."""


@dataclass
class Demo:
    """One demonstration to play.

    Attributes:
        name: shown in the list ("demo_episode", "episode_0003").
        t: [T] s; q: [T, dof] rad; gripper: [T] m.
        object_poses: name -> [T, 4, 4] float64 ``T_base_obj`` (empty when unknown).
        episode: the episode folder, for its images and depth (None for a twin without its episode).
        validation: the augmentation's validation record (augmented demonstrations only).
    """

    name: str
    t: np.ndarray
    q: np.ndarray
    gripper: np.ndarray
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


@dataclass
class ViewContent:
    """Everything the viewer and ``--video`` need.

    Attributes:
        kind: "episode", "reconstruction" or "augmentation".
        robot: the robot model with its visual meshes.
        demos: the demonstrations (one except for an augmentation folder: the source first).
        K: [3, 3] intrinsics (px); width, height: image size.
        T_mount_cam: [4, 4] camera-to-mount; mount: "base" or the link a wrist camera rides on.
        twin: the reconstructed twin (None for an episode alone).
        notes: what is missing and therefore not shown, said to the user.
    """

    kind: str
    robot: RobotModel
    demos: list[Demo]
    K: np.ndarray
    width: int
    height: int
    T_mount_cam: np.ndarray
    mount: str = "base"
    twin: Any = None
    notes: list[str] = field(default_factory=list)

    def object_poses_at(self, demo: Demo, i: int) -> dict[str, np.ndarray]:
        """Each of the twin's objects at frame ``i`` of ``demo``: [4, 4] ``T_base_obj`` from the
        demonstration's own track, else where the source demonstration starts it (empty without a twin)."""
        if self.twin is None:
            return {}
        return {name: demo.object_poses[name][i] if name in demo.object_poses else track[0]
                for name, track in self.twin.object_poses.items()}

    def tcp_path(self, demo: Demo) -> np.ndarray:
        """[T, 3] the TCP position of every frame of ``demo`` (m, base frame)."""
        import torch

        return self.robot.tcp_pose(torch.as_tensor(demo.q, dtype=torch.float64)).numpy()[:, :3, 3]

    def camera_pose(self, q: np.ndarray, gripper: float) -> np.ndarray:
        """[4, 4] ``T_base_cam`` at joints ``q`` (a wrist camera moves with its link)."""
        if self.mount == "base":
            return self.T_mount_cam
        import torch

        link = self.robot.link_pose(torch.as_tensor(q, dtype=torch.float64), self.mount,
                                    torch.as_tensor(float(gripper), dtype=torch.float64)).numpy()
        return link @ self.T_mount_cam


def _episode_demo(ep: Episode, name: str | None = None) -> Demo:
    return Demo(name=name or ep.path.name, t=ep.frames.t, q=ep.frames.q, gripper=ep.frames.gripper, episode=ep)


def _load_episode(path: Path) -> ViewContent:
    ep = Episode.open(path)
    cam = ep.camera
    notes = []
    if cam.T_mount_cam is None:
        raise ViewInputError(f"{path}: the camera has no T_mount_cam (uncalibrated); run manisplat-calibrate and "
                             "`manisplat-calibrate apply`, so the robot and depth can be placed in one frame")
    if not ep.has_depth:
        notes.append("the episode has no depth: no point cloud")
    robot = load_robot(ep.meta.robot.description, ep.path)
    return ViewContent("episode", robot, [_episode_demo(ep)], np.asarray(cam.K), cam.width, cam.height,
                       np.asarray(cam.T_mount_cam), cam.mount, notes=notes)


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
    else:
        notes.append(f"the source episode {twin.episode!r} was not found beside {path} or here: no recorded images "
                     "(pass --episode EP to show them)")
    demo = Demo(name=twin.episode, t=twin.t, q=twin.q, gripper=twin.gripper, object_poses=twin.object_poses,
                episode=ep)
    return twin, demo, notes


def _load_reconstruction(path: Path, episode: Path | None) -> ViewContent:
    twin, demo, notes = _load_twin(path, episode)
    robot = load_robot(twin.robot_description)
    return ViewContent("reconstruction", robot, [demo], twin.K, twin.width, twin.height, twin.T_base_cam, "base",
                       twin=twin, notes=notes)


def _augmented_demo(folder: Path, sample: dict[str, Any], notes: list[str]) -> Demo:
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
            demos.append(_augmented_demo(folder, sample, notes))
    if len(demos) == 1:
        notes.append(f"{path}: no augmented demonstration written")
    robot = load_robot(twin.robot_description)
    return ViewContent("augmentation", robot, demos, twin.K, twin.width, twin.height, twin.T_base_cam, "base",
                       twin=twin, notes=notes)


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
