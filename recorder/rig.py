"""A recording session with named arms and cameras: e.g. a Cobot Magic, two PiPERs with a head
camera and a camera on each gripper, into version 2 episodes; one arm and one camera into a
version 1 episode are its special case (:class:`~.session.Recorder`).

    >>> rec = RigRecorder([RigArm("left", arm_l, ArmInfo(name="left")), ...],
    ...                   [RigCamera("cam_high", oak, CameraInfo(...)), ...], SystemClock(), RecorderConfig())
    >>> rec.wait_for_arms()
    >>> result = rec.record_episode(Path("out/episode_0000"), duration=30.0)

Every arm is an :class:`~.armfeed.ArmFeed` (``joints_<arm>.csv``, ``can_<arm>.asc``, its own
CAN-stamp check, leader commands) and every camera a :class:`~.camfeed.CameraFeed` read on its
own thread; one writer thread (:class:`~.writer.EpisodeSink`) writes the episode, crash safe.

* The frames are the reference camera's (the first camera), matched by :class:`~.loop.EpisodeLoop`:
  a frame's time ``t`` is its stamp minus that camera's latency. Each other camera gives its image
  nearest to ``t`` within ``max_skew_s`` (default half a frame period), its own time going to
  ``<camera>.t``; a frame waits (up to ``max_wait_s``) for the other cameras' images around it
  and for every arm's joint sample and gripper frame after it, then every arm's state at ``t``
  is interpolated (never extrapolated; ``<arm>.sync_gap``, ``<arm>.sync_flags``) and the frame
  goes to the writer queue (bounded: a full queue drops and counts the frame).
* A reference frame for which another camera has no image within ``max_skew_s`` is not
  written: counted as that camera's ``unmatched`` and in ``skipped``. Every camera also counts
  its own drops (sequence gaps), stale and out-of-order frames, stalls and images no frame took
  (``unused``); every arm its joint samples, CAN frames logged and dropped, flagged frames
  (:class:`~.stats.RigStats`, in ``episode.json`` ``stats``).
* What is written, version 1 or 2, is the recorder's :mod:`.layout`.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable, Sequence

from manisplat.drivers.base import Camera, DriverError
from manisplat.drivers.piper import PiperArm
from manisplat.episode import RobotInfo
from manisplat.episode.images import chroma_keys
from manisplat.episode.infos import CameraInfo
from manisplat.recorder.armfeed import JOINT_TAIL_S, ArmFeed
from manisplat.recorder.camfeed import CameraFeed
from manisplat.recorder.canlog import can_log_name
from manisplat.recorder.clock import Clock, ClockMap
from manisplat.recorder.config import DEPTH_SCALE, RecorderConfig
from manisplat.recorder.layout import VersionOne, VersionTwo
from manisplat.recorder.loop import EpisodeLoop
from manisplat.recorder.result import EpisodeResult, Status, close_episode, remove_empty
from manisplat.recorder.stats import ArmStats, RigStats
from manisplat.recorder.writer import EpisodeSink, describe_write_error

log = logging.getLogger(__name__)


@dataclass
class RigArm:
    """An arm of the rig: its ``name`` (None: the one arm of a version 1 episode), the PiperArm on
    its bus (read-only is enough) and its ``info`` for ``episode.json`` (an ``ArmInfo`` with
    ``T_world_base`` for a named arm, the ``RobotInfo`` of a version 1 episode)."""

    name: str | None
    arm: PiperArm
    info: RobotInfo


@dataclass
class RigCamera:
    """A camera of the rig: its ``name``, the camera, its ``info`` for ``episode.json`` (K, size,
    mount ``world`` or ``<arm>/<link>``, ``T_mount_cam``), its latency (s; a frame's time is its
    stamp minus this) and whether its depth is recorded."""

    name: str
    camera: Camera
    info: CameraInfo
    latency_s: float = 0.0
    depth: bool = False


def _with_stored_colour(cam: RigCamera, image_format: str) -> RigCamera:
    """``cam`` whose ``episode.json`` entry says how its source kept the frames' colour, where the
    recorder stores them as PNG, which would lose it (JPEG files say it in their header)."""
    stored = cam.camera.chroma_subsampling
    if image_format != "png" or stored is None:
        return cam
    return replace(cam, info=replace(cam.info, extra={**cam.info.extra, **chroma_keys(stored)}))


class RigRecorder:
    """Records episodes from named ``arms`` and ``cameras``; see the module docstring.

    Args:
        arms: the arms, in the order of their ``frames.csv`` columns (names distinct).
        cameras: the cameras; the first is the reference whose frames are the episode's.
        clock: the host clocks (:class:`~.clock.SystemClock` outside tests).
        config: :class:`~.config.RecorderConfig` (``latency_s`` and ``depth`` are per camera here).
        source_info: free-form description of the devices for ``episode.json``.
        nominal_fps: the reference camera's configured rate (used when ``config.fps`` is None).
        layout: what is written (:mod:`.layout`): a version 2 episode unless told otherwise.
    """

    def __init__(self, arms: Sequence[RigArm], cameras: Sequence[RigCamera], clock: Clock,
                 config: RecorderConfig | None = None, *, source_info: dict[str, Any] | None = None,
                 nominal_fps: float | None = None, layout: VersionOne | VersionTwo | None = None) -> None:
        names = [a.name for a in arms] + [c.name for c in cameras]
        if not arms or not cameras or len(set(names)) != len(names):
            raise ValueError(f"a rig needs at least one arm and one camera, all names distinct; got {names}")
        self.layout = layout if layout is not None else VersionTwo()
        self.layout.check(arms, cameras)
        self.config = config if config is not None else RecorderConfig()
        self.clock = clock
        self.clock_map = ClockMap(clock)
        self.arms = list(arms)
        self.cameras = [_with_stored_colour(cam, self.config.image_format) for cam in cameras]
        self.source_info = dict(source_info or {})
        self.nominal_fps = nominal_fps
        c = self.config
        self.feeds = {a.name: ArmFeed(a.arm, clock, self.clock_map, c.max_action_age_s, name=a.name) for a in arms}
        self.camera_feeds = {cam.name: CameraFeed(cam.name, cam.camera, clock, latency_s=cam.latency_s,
                                                  depth=cam.depth, poll_s=c.camera_poll_s,
                                                  stall_after_s=c.stall_after_s) for cam in cameras}

    @property
    def reference(self) -> str:
        """The camera whose frames are the episode's frames."""
        return self.cameras[0].name

    def wait_for_arms(self, timeout: float = 3.0) -> None:
        """Wait for complete joint samples of every arm (DriverError naming the arm that sends
        none within ``timeout`` s), warning about an arm whose CAN stamps are not wall-clock."""
        for feed in self.feeds.values():
            warning = feed.wait(timeout)
            if warning:
                log.warning("%s", warning)

    def _episode_meta(self, t0: float, t0_wall: float, with_actions: bool, max_skew_s: float) -> dict[str, Any]:
        c, layout = self.config, self.layout
        meta: dict[str, Any] = {
            "recording": {"tool": "manisplat-record", **self.source_info},
            "clock": {**self.clock_map.describe(since=t0), "t0_monotonic": t0, "t0_wall": t0_wall,
                      "can_timestamps": layout.each({name: f.describe_stamps() for name, f in self.feeds.items()}),
                      "camera_timestamps": "camera stamps (host monotonic clock, mid-exposure where known)",
                      "camera_latency_s": layout.each({cam.name: cam.latency_s for cam in self.cameras})},
            "sync": {**layout.sync_head(self, max_skew_s), "max_gap_s": c.max_gap_s, "max_wait_s": c.max_wait_s,
                     "columns": layout.column_notes},
            "can_log": {**layout.can_log(self), "time_zero_wall": t0_wall, "note": layout.can_note},
        }
        if c.task:
            meta["task"] = c.task
        if with_actions:
            meta["actions"] = {"source": layout.actions_source,
                               "rule": "the latest command at or before the frame time; stale after "
                                       f"{c.max_action_age_s} s (then the measured state, flag action_stale)"}
        return meta

    def _new_stats(self, stop_reason: str = "") -> RigStats:
        return RigStats(stop_reason=stop_reason, arms={name: ArmStats() for name in self.feeds})

    def record_episode(self, path: Path, *, duration: float | None = None, stop: threading.Event | None = None,
                       on_status: Callable[[Status], None] | None = None, status_every_s: float = 0.5) -> EpisodeResult:
        """Record one episode into the new folder ``path``; see the module docstring.

        Ends after ``duration`` s (on the clock), when ``stop`` is set, when a camera ends or
        fails, or at the first write error. Returns an :class:`~.result.EpisodeResult` (its
        stats as the layout gives them; ``error`` says why an episode is incomplete); raises
        DriverError when an arm has never been heard.
        """
        c = self.config
        stop = stop if stop is not None else threading.Event()
        for feed in self.feeds.values():
            if feed.history.last_t is None:
                raise DriverError(f"{feed.label}: no joint sample yet: call wait_for_arms() first")
        with_actions = c.actions == "on" or (c.actions == "auto" and any(f.leader.seen for f in self.feeds.values()))
        fps = c.fps or self.nominal_fps or 30.0
        max_skew_s = c.max_skew_s if c.max_skew_s is not None else 0.5 / fps
        self.clock_map.remeasure()
        t0 = self.clock.monotonic()
        t0_wall = t0 + self.clock_map.offset
        created = not path.exists()
        writer = None
        try:
            writer = self.layout.open_writer(
                self, path, fps, with_actions, source="recorder",
                depth_scale=DEPTH_SCALE if any(cam.depth for cam in self.cameras) else None,
                image_format=c.image_format, extra_meta=self._episode_meta(t0, t0_wall, with_actions, max_skew_s),
                fsync_every=c.fsync_every)
            for feed in self.feeds.values():
                feed.can_log.open(path / can_log_name(feed.name), t0_wall)
        except OSError as exc:
            for feed in self.feeds.values():
                feed.can_log.abandon()
            if writer is not None:
                writer.__exit__(type(exc), exc, exc.__traceback__)
            error = f"{path}: cannot start the episode: {describe_write_error(exc)}"
            log.error("%s", error)
            result = EpisodeResult(path, self.layout.stats(self._new_stats("write error")), error)
            return remove_empty(result) if created else result
        sink = EpisodeSink(writer, [feed.can_log for feed in self.feeds.values()], queue_frames=c.queue_frames)
        stats = self._new_stats()
        for feed in self.feeds.values():
            feed.activate(t0, sink, until=t0 + duration + JOINT_TAIL_S if duration else math.inf)
        for cam in self.camera_feeds.values():
            cam.start(t0)
        loop = EpisodeLoop(self, t0, sink, stats, with_actions, max_skew_s)
        log.info("%s: recording %d arms and %d cameras (%s)", path, len(self.arms), len(self.cameras),
                 f"{duration} s" if duration else "until stopped")
        try:
            stats.stop_reason = loop.run(duration, stop, on_status, status_every_s)
        finally:
            loop.flush_pending()
            for cam in self.camera_feeds.values():
                cam.stop()
            loop.resolve(force=True, until=loop.end)
            for name, feed in self.feeds.items():
                stats.arms[name].joint_samples = feed.deactivate()
                feed.can_log.seal()
        stats.duration_s = loop.end - t0
        stats.dropped_queue = sink.frames_dropped
        for name, cam in self.camera_feeds.items():
            cam.drop_waiting()
            stats.cameras[name] = cam.stats
        for name, feed in self.feeds.items():
            stats.arms[name].can_frames_dropped = feed.can_log.dropped
            stats.arms[name].can_frames_logged = feed.can_log.received - feed.can_log.dropped
        stats.count_frames(loop.queued)  # all of them are on disk once the sink finishes
        extra = {"stats": asdict(self.layout.stats(stats)),
                 "clock": {**writer.meta.extra["clock"], **self.clock_map.describe(since=t0)}}
        if with_actions:
            extra["actions"] = {**writer.meta.extra["actions"], "gripper_from_state_frames": self.layout.each(
                {name: a.gripper_action_from_state for name, a in stats.arms.items()})}
        result = close_episode(path, sink, stats, extra, loop.camera_error, created)
        result.stats = self.layout.stats(stats)
        if not result.removed:
            log.info("%s: %d frames, %d joint samples, %d lost, %d flagged, stop: %s%s", path, stats.frames,
                     stats.joint_samples, stats.frames_lost, stats.flagged, stats.stop_reason,
                     f"; ERROR: {result.error}" if result.error else "")
        return result
