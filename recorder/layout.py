"""What a recording writes: the episode layouts a :class:`~.rig.RigRecorder` records into.

:class:`VersionOne`: one unnamed arm and one camera, a version 1 episode (``episode.json``
``robot``/``camera``, ``frames.csv`` q1..q6, gripper, ``seq``, ``sync_gap``, the actions,
``sync_flags``; ``joints.csv``, ``can.asc``; the flat :class:`~.stats.EpisodeStats`).
:class:`VersionTwo`: named arms and cameras, a version 2 episode (:class:`EpisodeWriterV2`,
``joints_<arm>.csv``, ``can_<arm>.asc``, ``<camera>.seq``, ``<arm>.sync_gap``,
``<arm>.sync_flags``; :class:`~.stats.RigStats`). Everything else (the feeds, the matching
loop, the writer thread) is the same for both.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from manisplat.drivers.base import CameraFrame
from manisplat.episode import ACTION_COLUMNS, EpisodeWriter
from manisplat.episode.format import GRIPPER_EFFORT_COLUMN
from manisplat.episode.writer_v2 import EpisodeWriterV2
from manisplat.recorder.canlog import CAN_LOG_NAME, can_log_name
from manisplat.recorder.stats import EpisodeStats, RigStats
from manisplat.recorder.sync import FLAG_NAMES
from manisplat.recorder.writer import FrameItem, RigFrameItem, Writer

if TYPE_CHECKING:
    from manisplat.recorder.loop import ArmSync
    from manisplat.recorder.rig import RigArm, RigCamera, RigRecorder

SYNC_COLUMNS = ("seq", "sync_gap", "sync_flags")
FLAGS = {str(k): v for k, v in FLAG_NAMES.items()}
GRIPPER_EFFORT_NOTE = "N*m, the gripper motor's effort (0x2A8), interpolated like the gripper's width"
Images = dict[str, tuple[float, CameraFrame]]


class VersionOne:
    """A version 1 episode of one arm (named None) and one camera; see the module docstring."""

    column_notes = {"seq": "camera sequence number", "sync_gap": "s between the joint samples interpolated across",
                    "sync_flags": FLAGS, GRIPPER_EFFORT_COLUMN: GRIPPER_EFFORT_NOTE}
    can_note = "timestamps in the file are s since time_zero_wall = episode t 0"
    actions_source = "leader-arm commands seen on the bus (0x155-0x157 joints, 0x159 gripper)"

    def check(self, arms: Sequence[RigArm], cameras: Sequence[RigCamera]) -> None:
        if len(arms) != 1 or len(cameras) != 1 or arms[0].name is not None:
            raise ValueError("a version 1 episode has one arm (named None) and one camera")

    def each(self, values: dict[Any, Any]) -> Any:
        """A per-arm or per-camera value as ``episode.json`` gives it: the one arm's or camera's."""
        return next(iter(values.values()))

    def sync_head(self, rec: RigRecorder, max_skew_s: float) -> dict[str, Any]:
        return {"method": "linear interpolation between the joint samples around each frame time "
                          "(frame time = camera stamp - camera_latency_s); never extrapolated"}

    def can_log(self, rec: RigRecorder) -> dict[str, Any]:
        return {"file": CAN_LOG_NAME}

    def open_writer(self, rec: RigRecorder, path: Path, fps: float, with_actions: bool, **common: Any) -> Writer:
        columns = SYNC_COLUMNS + (GRIPPER_EFFORT_COLUMN,) + (ACTION_COLUMNS if with_actions else ())
        return EpisodeWriter(path, rec.cameras[0].info, rec.arms[0].info, fps, extra_frame_columns=columns, **common)

    def frame_item(self, rec: RigRecorder, t0: float, t: float, images: Images, synced: dict[Any, ArmSync],
                   with_actions: bool) -> FrameItem:
        """The frame at ``t`` (monotonic s; the episode started at ``t0``): the camera's image, the
        arm's state and action."""
        ((_, frame),) = images.values()
        (arm,) = synced.values()
        extra = {"seq": float(frame.seq), "sync_gap": arm.gap, GRIPPER_EFFORT_COLUMN: arm.gripper_effort}
        if arm.action is not None:
            extra.update(zip(ACTION_COLUMNS, arm.action.tolist()))
        extra["sync_flags"] = float(arm.flags)
        return FrameItem(t - t0, arm.values[:6], float(arm.values[6]), frame.rgb,
                         frame.depth if rec.cameras[0].depth else None, extra)

    def stats(self, stats: RigStats) -> EpisodeStats:
        return EpisodeStats.of(stats)


class VersionTwo:
    """A version 2 episode of named arms and cameras; see the module docstring."""

    column_notes = {"<camera>.seq": "the camera's sequence number",
                    "<arm>.sync_gap": "s between the arm's joint samples interpolated across",
                    "<arm>.sync_flags": FLAGS, f"<arm>.{GRIPPER_EFFORT_COLUMN}": GRIPPER_EFFORT_NOTE}
    can_note = "timestamps in the files are s since time_zero_wall = episode t 0"
    actions_source = "each arm's leader-arm commands seen on its bus (0x155-0x157 joints, 0x159 gripper)"

    def check(self, arms: Sequence[RigArm], cameras: Sequence[RigCamera]) -> None:
        if any(a.name is None for a in arms):
            raise ValueError("every arm of a version 2 episode has a name")

    def each(self, values: dict[Any, Any]) -> Any:
        return values

    def sync_head(self, rec: RigRecorder, max_skew_s: float) -> dict[str, Any]:
        return {"method": "linear interpolation of every arm between its joint samples around each frame time "
                          "(frame time = the reference camera's stamp - its camera_latency_s); never extrapolated",
                "reference_camera": rec.reference,
                "cameras": "each other camera's image nearest to the frame time within max_skew_s (its own "
                           "time in <camera>.t); a frame without one is not written (stats: unmatched)",
                "max_skew_s": max_skew_s}

    def can_log(self, rec: RigRecorder) -> dict[str, Any]:
        return {"files": {name: can_log_name(name) for name in rec.feeds}}

    def open_writer(self, rec: RigRecorder, path: Path, fps: float, with_actions: bool, **common: Any) -> Writer:
        columns = (*(f"{cam.name}.seq" for cam in rec.cameras),
                   *(f"{a.name}.{col}" for a in rec.arms for col in ("sync_gap", "sync_flags", GRIPPER_EFFORT_COLUMN)))
        return EpisodeWriterV2(path, [a.info for a in rec.arms], [cam.info for cam in rec.cameras], fps,
                               actions=with_actions, camera_times=[cam.name for cam in rec.cameras[1:]],
                               extra_frame_columns=columns, **common)

    def frame_item(self, rec: RigRecorder, t0: float, t: float, images: Images, synced: dict[Any, ArmSync],
                   with_actions: bool) -> RigFrameItem:
        """The frame at ``t`` (monotonic s; the episode started at ``t0``): every camera's image,
        every arm's state and action."""
        extra = {f"{name}.seq": float(f.seq) for name, (_, f) in images.items()}
        for name, arm in synced.items():
            extra[f"{name}.sync_gap"] = arm.gap
            extra[f"{name}.sync_flags"] = float(arm.flags)
            extra[f"{name}.{GRIPPER_EFFORT_COLUMN}"] = arm.gripper_effort
        actions: dict[str, np.ndarray] | None = ({name: arm.action for name, arm in synced.items()}
                                                 if with_actions else None)
        depth = {cam.name: images[cam.name][1].depth for cam in rec.cameras if cam.depth}
        return RigFrameItem(t - t0, {name: arm.values for name, arm in synced.items()},
                            {name: f.rgb for name, (_, f) in images.items()}, depth, actions,
                            {name: ct - t0 for name, (ct, _) in images.items() if name != rec.reference}, extra)

    def stats(self, stats: RigStats) -> RigStats:
        return stats


def opencv_dist(dist: np.ndarray) -> np.ndarray:
    """Distortion coefficients in a length OpenCV (and the episode format) accepts."""
    d = np.asarray(dist, dtype=np.float64).reshape(-1)
    for n in (0, 4, 5, 8, 12, 14):
        if len(d) <= n:
            return np.concatenate([d, np.zeros(n - len(d))]) if len(d) else d
    raise ValueError(f"{len(d)} distortion coefficients: more than OpenCV's 14")
