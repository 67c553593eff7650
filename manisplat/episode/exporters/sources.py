"""What every exporter checks before it writes: the episodes open, are complete, and can share one
dataset (the same arms, the same cameras at one image size each, one fps, every image present);
where each came from; and their state and action as one vector over every arm."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from manisplat.episode.format import DEPTH_DIR, RGB_DIR, EpisodeFormatError
from manisplat.episode.images import find_image
from manisplat.episode.meta import CameraInfo
from manisplat.episode.reader import Episode

PROVENANCE_FILE = "augmentation.json"
"""Name of the provenance side file (in an augmented episode, and in every export)."""
SIM_SOURCES = ("simulation", "augmentation")


class ExportDestinationError(FileExistsError):
    """``--out`` exists and holds files, and ``overwrite`` was not given (a usage error, exit 2)."""


@dataclass(frozen=True)
class ExportSource:
    """One episode to export, with its provenance.

    Attributes:
        episode: the opened episode.
        parent: the episode an augmented one was made from (None for a recording).
        seed: the augmentation seed, when recorded.
    """

    episode: Episode
    parent: str | None
    seed: Any

    @property
    def augmented(self) -> bool:
        return self.episode.meta.source == "augmentation"

    @property
    def sim(self) -> bool:
        """Whether the images were rendered, not recorded (simulation, augmentation, a sim ACT import)."""
        meta = self.episode.meta
        imported = meta.extra.get("import")
        if meta.source.startswith("import:") and isinstance(imported, dict):
            return bool(imported.get("sim", False))
        return meta.source in SIM_SOURCES

    def provenance(self) -> dict[str, Any]:
        """The fields every exporter records for this episode."""
        ep = self.episode
        return {"episode": str(ep.path.resolve()), "source": ep.meta.source, "augmented": self.augmented,
                "parent": self.parent, "seed": self.seed, "sim": self.sim}


def _parent_of(ep: Episode) -> tuple[str | None, Any]:
    """``parent`` and ``seed`` of an augmented episode: its augmentation.json, else episode.json."""
    record: dict[str, Any] = {}
    path = ep.path / PROVENANCE_FILE
    if path.is_file():
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise EpisodeFormatError(f"{path}: cannot read: {exc}") from exc
        if not isinstance(record, dict):
            raise EpisodeFormatError(f"{path}: expected a JSON object")
    parent = record.get("parent", ep.meta.extra.get("parent"))
    return (None if parent is None else str(parent)), record.get("seed")


def _missing_frames(folder: Path, count: int) -> list[int]:
    return [i for i in range(count) if find_image(folder, i) is None]


def _listing(sources: Sequence[ExportSource], value: Callable[[Episode], str]) -> str:
    return ", ".join(f"{s.episode.path.name} {value(s.episode)}" for s in sources)


def open_sources(episodes: Sequence[str | Path], layout: str, *, same_fps: bool = True) -> list[ExportSource]:
    """Open every episode and check that they can share one export: complete, not empty, the same
    arms in the same order (so that state and action columns mean one thing), one fps (with
    ``same_fps``); raises before anything is written.

    Args:
        episodes: episode folders.
        layout: the export's name, for messages ("ACT", "LeRobot").
        same_fps: require one fps for all (False when the exporter checks rates itself).

    Raises:
        EpisodeFormatError: an episode is incomplete or empty, or the episodes differ in arms or fps.
    """
    if not episodes:
        raise ValueError("no episodes to export")
    sources = []
    for path in episodes:
        ep = Episode.open(path)
        if not ep.meta.complete:
            raise EpisodeFormatError(f"{ep.path}: incomplete episode (its writer stopped or crashed); run "
                                     f"`manisplat-episode recover {ep.path}` first")
        if len(ep) == 0:
            raise EpisodeFormatError(f"{ep.path}: no frames")
        sources.append(ExportSource(ep, *_parent_of(ep)))
    if len({tuple(s.episode.arms) for s in sources}) > 1:
        raise EpisodeFormatError(f"episodes with different arms cannot share one {layout} export (the state and "
                                 f"action columns must mean the same joints): "
                                 f"{_listing(sources, lambda ep: ', '.join(ep.arms))}")
    if same_fps and len({src.episode.meta.fps for src in sources}) > 1:
        raise EpisodeFormatError(f"episodes of different fps cannot share one {layout} export (one control "
                                 f"rate per dataset): {_listing(sources, lambda ep: f'{ep.meta.fps:g}')}")
    return sources


def _image_size(ep: Episode, camera: str, place: int) -> str:
    """``WxH`` of the episode's camera of that name, else of its camera at that place (so that a
    size that differs is reported before a name that differs, as for one-camera episodes)."""
    cam = ep.cameras.get(camera) or list(ep.cameras.values())[min(place, len(ep.cameras) - 1)]
    return f"{cam.width}x{cam.height}"


def export_cameras(sources: Sequence[ExportSource], cameras: str | Sequence[str] | None,
                   layout: str) -> list[CameraInfo]:
    """The cameras to export, as the first episode describes them: ``cameras`` (one name or several),
    or every camera of the first episode; each episode must have each of them at one image size,
    with an image for every frame.

    Raises:
        EpisodeFormatError: an episode lacks one of the cameras, has it at another size, or lacks an image.
    """
    names = list(sources[0].episode.cameras) if cameras is None else (
        [cameras] if isinstance(cameras, str) else list(cameras))
    if not names or len(set(names)) != len(names):
        raise ValueError(f"cameras must be distinct names; got {names}")
    for k, name in enumerate(names):
        sizes = [_image_size(s.episode, name, k) for s in sources]
        if len(set(sizes)) > 1:
            listing = ", ".join(f"{s.episode.path.name} {size}" for s, size in zip(sources, sizes))
            raise EpisodeFormatError(f"episodes of different image sizes cannot share one {layout} export "
                                     f"(camera {name}): {listing}")
        for src in sources:
            ep = src.episode
            if name not in ep.cameras:
                have = ", ".join(repr(c) for c in ep.cameras)
                raise EpisodeFormatError(f"{ep.path}: no camera {name!r}; the episode's camera"
                                         f"{'s are' if len(ep.cameras) > 1 else ' is'} {have} (every episode of "
                                         "one export needs the same cameras)")
            rgb = ep.path / ep.layout.camera(name).folder(RGB_DIR)  # rgb/, or rgb/<camera>/ in version 2
            missing = _missing_frames(rgb, len(ep))
            if missing:
                raise EpisodeFormatError(f"{rgb}: no image for {len(missing)} of {len(ep)} frames "
                                         f"(first: frame {missing[0]})")
    return [sources[0].episode.cameras[name] for name in names]


def depth_cameras(sources: Sequence[ExportSource], cameras: Sequence[str]) -> list[str]:
    """Those of ``cameras`` that have depth images in any of the episodes."""
    return [c for c in cameras if any(s.episode.has_images(DEPTH_DIR, c) for s in sources)]


def check_depth(sources: Sequence[ExportSource], cameras: Sequence[str]) -> None:
    """Raise :class:`EpisodeFormatError` unless every frame of every episode has a depth image from
    each of ``cameras``."""
    for camera in cameras:
        for src in sources:
            ep = src.episode
            depth = ep.path / ep.layout.camera(camera).folder(DEPTH_DIR)  # depth/, or depth/<camera>/
            missing = _missing_frames(depth, len(ep)) if ep.has_images(DEPTH_DIR, camera) else list(range(len(ep)))
            if missing:
                raise EpisodeFormatError(f"{depth}: no depth for {len(missing)} of {len(ep)} frames "
                                         f"(first: frame {missing[0]}); export without depth (--no-depth) or drop "
                                         "this episode")


def resample_indices(t: np.ndarray, fps: float) -> np.ndarray:
    """Frames to export at ``fps``: for each ``k``, the recorded frame nearest ``t[0] + k / fps``.

    Args:
        t: (T,) increasing frame times in seconds.
        fps: export rate in Hz, at most the recording's (a higher one would repeat frames).

    Returns:
        (K,) int64 frame indices, increasing; the targets run to the last frame's time plus half a
        recorded period (so 16 -> 8 fps keeps every second frame of 16, and 16 -> 16 all of them).

    Raises:
        ValueError: ``fps`` is above the recording's rate, so frames would repeat.
    """
    t = np.asarray(t, dtype=np.float64)
    if len(t) == 1:
        return np.zeros(1, dtype=np.int64)
    recorded = (len(t) - 1) / (t[-1] - t[0])
    count = int(np.floor((t[-1] - t[0] + 0.5 / recorded) * fps)) + 1
    targets = t[0] + np.arange(count) / fps
    right = np.clip(np.searchsorted(t, targets), 1, len(t) - 1)
    nearer_left = targets - t[right - 1] <= t[right] - targets
    indices = np.where(nearer_left, right - 1, right).astype(np.int64)
    if np.any(np.diff(indices) == 0):
        raise ValueError(f"cannot export at {fps:g} fps: the episode was recorded at {recorded:.4g} fps and "
                         "frames would repeat; choose an fps at most the recording's")
    return indices


def export_frames(episode: Episode, fps: float) -> np.ndarray:
    """(K,) frame indices of ``episode`` exported at ``fps``: all of them at the episode's own rate,
    else :func:`resample_indices`; raises :class:`EpisodeFormatError` when ``fps`` is above its rate."""
    if abs(episode.meta.fps - fps) < 1e-9:
        return np.arange(len(episode))
    if episode.meta.fps < fps:
        raise EpisodeFormatError(f"{episode.path}: recorded at {episode.meta.fps:g} fps, below the export's {fps:g} "
                                 "fps (frames would repeat); pass a lower --fps")
    try:
        return resample_indices(frame_times(episode), fps)
    except ValueError as exc:
        raise EpisodeFormatError(f"{episode.path}: {exc}") from exc


def frame_times(episode: Episode) -> np.ndarray:
    """(T,) float64 seconds: ``frames.csv`` ``t``, which every arm's table shares."""
    return episode.arm_frames(next(iter(episode.arms))).t


def state_names(episode: Episode) -> list[str]:
    """Names of the state and action columns: every arm's ``frames.csv`` state columns in the
    episode's arm order (version 1: ``q1..q6, gripper``; version 2: ``left.q1..left.gripper, right.q1..``)."""
    return [c for arm in episode.layout.arms for c in arm.state]


def state_and_action(episode: Episode, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """(state [K, 7 A], action [K, 7 A], recorded) at ``frames`` for the episode's A arms in order:
    each arm's ``[q1..q6 rad, gripper m]``; action each arm's ``a1..a6, a_gripper`` (``recorded``
    True when every arm has them) or else the next exported frame's state (the last one repeated)."""
    tables = [episode.arm_frames(arm) for arm in episode.arms]
    state = np.concatenate([np.column_stack([f.q, f.gripper]) for f in tables], axis=1)[frames]
    actions = [f.actions for f in tables]
    if all(a is not None for a in actions):
        return state, np.concatenate(actions, axis=1)[frames], True
    return state, np.concatenate([state[1:], state[-1:]], axis=0), False
