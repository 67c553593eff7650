"""A recording session with named arms and cameras, into version 2 episodes: e.g. a Cobot Magic,
two PiPERs with a head camera and a camera on each gripper.

    >>> rec = RigRecorder([RigArm("left", arm_l, ArmInfo(name="left")), ...],
    ...                   [RigCamera("cam_high", oak, CameraInfo(...)), ...], SystemClock(), RecorderConfig())
    >>> rec.wait_for_arms()
    >>> result = rec.record_episode(Path("out/episode_0000"), duration=30.0)

An episode is recorded as :class:`~.session.Recorder` records one arm and one camera (the same
writer thread, crash safety, clock mapping and sync), with every arm an
:class:`~.armfeed.ArmFeed` (``joints_<arm>.csv``, ``can_<arm>.asc``, its own CAN-stamp check,
leader commands) and every camera a :class:`~.camfeed.CameraFeed` read on its own thread:

* The frames are the reference camera's (the first camera): a frame's time ``t`` is its stamp
  minus that camera's latency. Each other camera gives its image nearest to ``t`` within
  ``max_skew_s`` (default half a frame period), its own time going to ``<camera>.t``; a frame
  waits (up to ``max_wait_s``) for the other cameras' images around it and for every arm's
  joint sample and gripper frame after it, then every arm's state at ``t`` is interpolated
  (never extrapolated; ``<arm>.sync_gap``, ``<arm>.sync_flags``) and the frame goes to the
  writer queue (bounded: a full queue drops and counts the frame).
* A reference frame for which another camera has no image within ``max_skew_s`` is not
  written: counted as that camera's ``unmatched`` and in ``skipped``. Every camera also counts
  its own drops (sequence gaps), stale and out-of-order frames, stalls and images no frame took
  (``unused``); every arm its joint samples, CAN frames logged and dropped, flagged frames
  (:class:`RigStats`, in ``episode.json`` ``stats``).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from manisplat.drivers.base import Camera, CameraFrame, DriverError
from manisplat.drivers.piper import PiperArm
from manisplat.episode.infos import ArmInfo, CameraInfo
from manisplat.episode.writer_v2 import EpisodeWriterV2
from manisplat.recorder.armfeed import ArmFeed
from manisplat.recorder.camfeed import CameraFeed, CameraStats
from manisplat.recorder.canlog import can_log_name
from manisplat.recorder.clock import Clock, ClockMap, RealDeadline
from manisplat.recorder.session import (DEPTH_SCALE, EpisodeResult, RecorderConfig, Status, remove_empty,
                                        close_episode)
from manisplat.recorder.sync import FLAG_NAMES
from manisplat.recorder.writer import EpisodeSink, RigFrameItem, describe_write_error

log = logging.getLogger(__name__)


@dataclass
class RigArm:
    """An arm of the rig: its ``name``, the PiperArm on its bus (read-only is enough) and its
    ``info`` for ``episode.json`` (``T_world_base``, robot description)."""

    name: str
    arm: PiperArm
    info: ArmInfo


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


@dataclass
class ArmStats:
    """What one arm did in one episode (``episode.json`` ``stats.arms.<arm>``): joint samples
    written, CAN frames logged and dropped, frames written with a sync flag of this arm
    (``flag_counts`` by flag name), the largest gap interpolated across (s), gripper actions
    taken from the measured state."""

    joint_samples: int = 0
    can_frames_logged: int = 0
    can_frames_dropped: int = 0
    flagged: int = 0
    flag_counts: dict[str, int] = field(default_factory=dict)
    max_sync_gap_s: float = 0.0
    gripper_action_from_state: int = 0


@dataclass
class RigStats:
    """What happened in one episode with named arms and cameras (``episode.json`` ``stats``).

    ``frames`` written; ``skipped`` reference frames not written because a camera had no image
    near enough (each counted in that camera's ``unmatched``); ``dropped_queue`` frames lost
    because the writer fell behind; ``flagged`` frames with a sync flag of any arm; per camera
    :class:`~.camfeed.CameraStats`, per arm :class:`ArmStats`.
    """

    frames: int = 0
    skipped: int = 0
    dropped_queue: int = 0
    flagged: int = 0
    duration_s: float = 0.0
    stop_reason: str = ""
    cameras: dict[str, CameraStats] = field(default_factory=dict)
    arms: dict[str, ArmStats] = field(default_factory=dict)

    @property
    def frames_lost(self) -> int:
        """Frames lost: dropped by a camera, skipped without a partner image, or dropped by the writer."""
        return self.dropped_queue + self.skipped + sum(c.dropped_camera for c in self.cameras.values())

    @property
    def max_sync_gap_s(self) -> float:
        return max((a.max_sync_gap_s for a in self.arms.values()), default=0.0)

    @property
    def joint_samples(self) -> int:
        return sum(a.joint_samples for a in self.arms.values())

    @property
    def can_frames_logged(self) -> int:
        return sum(a.can_frames_logged for a in self.arms.values())


class RigRecorder:
    """Records version 2 episodes from named ``arms`` and ``cameras``; see the module docstring.

    Args:
        arms: the arms, in the order of their ``frames.csv`` columns (names distinct).
        cameras: the cameras; the first is the reference whose frames are the episode's.
        clock: the host clocks (:class:`~.clock.SystemClock` outside tests).
        config: :class:`~.session.RecorderConfig` (``latency_s`` is per camera here).
        source_info: free-form description of the devices for ``episode.json``.
        nominal_fps: the reference camera's configured rate (used when ``config.fps`` is None).
    """

    def __init__(self, arms: Sequence[RigArm], cameras: Sequence[RigCamera], clock: Clock,
                 config: RecorderConfig | None = None, *, source_info: dict[str, Any] | None = None,
                 nominal_fps: float | None = None) -> None:
        names = [a.name for a in arms] + [c.name for c in cameras]
        if not arms or not cameras or len(set(names)) != len(names):
            raise ValueError(f"a rig needs at least one arm and one camera, all names distinct; got {names}")
        self.config = config if config is not None else RecorderConfig()
        self.clock = clock
        self.clock_map = ClockMap(clock)
        self.arms = list(arms)
        self.cameras = list(cameras)
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

    def _columns(self) -> tuple[str, ...]:
        """The extra ``frames.csv`` columns: every camera's ``seq``, every arm's sync gap and flags."""
        return (*(f"{cam.name}.seq" for cam in self.cameras),
                *(f"{a.name}.{col}" for a in self.arms for col in ("sync_gap", "sync_flags")))

    def _episode_meta(self, t0: float, t0_wall: float, with_actions: bool, max_skew_s: float) -> dict[str, Any]:
        c = self.config
        meta: dict[str, Any] = {
            "recording": {"tool": "manisplat-record", **self.source_info},
            "clock": {**self.clock_map.describe(since=t0), "t0_monotonic": t0, "t0_wall": t0_wall,
                      "can_timestamps": {name: feed.describe_stamps() for name, feed in self.feeds.items()},
                      "camera_timestamps": "camera stamps (host monotonic clock, mid-exposure where known)",
                      "camera_latency_s": {cam.name: cam.latency_s for cam in self.cameras}},
            "sync": {"method": "linear interpolation of every arm between its joint samples around each frame time "
                               "(frame time = the reference camera's stamp - its camera_latency_s); never extrapolated",
                     "reference_camera": self.reference,
                     "cameras": "each other camera's image nearest to the frame time within max_skew_s (its own "
                                "time in <camera>.t); a frame without one is not written (stats: unmatched)",
                     "max_skew_s": max_skew_s, "max_gap_s": c.max_gap_s, "max_wait_s": c.max_wait_s,
                     "columns": {"<camera>.seq": "the camera's sequence number",
                                 "<arm>.sync_gap": "s between the arm's joint samples interpolated across",
                                 "<arm>.sync_flags": {str(k): v for k, v in FLAG_NAMES.items()}}},
            "can_log": {"files": {name: can_log_name(name) for name in self.feeds}, "time_zero_wall": t0_wall,
                        "note": "timestamps in the files are s since time_zero_wall = episode t 0"},
        }
        if c.task:
            meta["task"] = c.task
        if with_actions:
            meta["actions"] = {"source": "each arm's leader-arm commands seen on its bus (0x155-0x157 joints, 0x159 "
                                         "gripper)",
                               "rule": "the latest command at or before the frame time; stale after "
                                       f"{c.max_action_age_s} s (then the measured state, flag action_stale)"}
        return meta

    def record_episode(self, path: Path, *, duration: float | None = None, stop: threading.Event | None = None,
                       on_status: Callable[[Status], None] | None = None, status_every_s: float = 0.5) -> EpisodeResult:
        """Record one episode into the new folder ``path``; see the module docstring.

        Ends after ``duration`` s, when ``stop`` is set, when a camera ends or fails, or at the
        first write error. Returns an :class:`~.session.EpisodeResult` (stats :class:`RigStats`;
        ``error`` says why an episode is incomplete); raises DriverError when an arm has never
        been heard.
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
        writer: EpisodeWriterV2 | None = None
        try:
            writer = EpisodeWriterV2(
                path, [a.info for a in self.arms], [cam.info for cam in self.cameras], fps, source="recorder",
                depth_scale=DEPTH_SCALE if any(cam.depth for cam in self.cameras) else None,
                image_format=c.image_format, actions=with_actions,
                camera_times=[cam.name for cam in self.cameras[1:]], extra_frame_columns=self._columns(),
                extra_meta=self._episode_meta(t0, t0_wall, with_actions, max_skew_s), fsync_every=c.fsync_every)
            for name, feed in self.feeds.items():
                feed.can_log.open(path / can_log_name(name), t0_wall)
        except OSError as exc:
            for feed in self.feeds.values():
                feed.can_log.abandon()
            if writer is not None:
                writer.__exit__(type(exc), exc, exc.__traceback__)
            error = f"{path}: cannot start the episode: {describe_write_error(exc)}"
            log.error("%s", error)
            result = EpisodeResult(path, RigStats(stop_reason="write error"), error)
            return remove_empty(result) if created else result
        sink = EpisodeSink(writer, [feed.can_log for feed in self.feeds.values()], queue_frames=c.queue_frames)
        stats = RigStats(arms={name: ArmStats() for name in self.feeds})
        for feed in self.feeds.values():
            feed.activate(t0, sink)
        for cam in self.camera_feeds.values():
            cam.start(t0)
        loop = _RigLoop(self, t0, sink, stats, with_actions, max_skew_s)
        log.info("%s: recording %d arms and %d cameras (%s)", path, len(self.arms), len(self.cameras),
                 f"{duration} s" if duration else "until stopped")
        try:
            stats.stop_reason = loop.run(duration, stop, on_status, status_every_s)
        finally:
            loop.flush_pending()
            for cam in self.camera_feeds.values():
                cam.stop()
            loop.resolve(force=True)
            for name, feed in self.feeds.items():
                stats.arms[name].joint_samples = feed.deactivate()
                feed.can_log.seal()
        stats.duration_s = self.clock.monotonic() - t0
        stats.dropped_queue = sink.frames_dropped
        for name, cam in self.camera_feeds.items():
            cam.drop_waiting()
            stats.cameras[name] = cam.stats
        for name, feed in self.feeds.items():
            stats.arms[name].can_frames_dropped = feed.can_log.dropped
            stats.arms[name].can_frames_logged = feed.can_log.received - feed.can_log.dropped
        stats.frames = loop.queued  # all of them are on disk once the sink finishes
        for cam_stats in stats.cameras.values():
            cam_stats.frames = stats.frames
        extra = {"stats": asdict(stats), "clock": {**writer.meta.extra["clock"], **self.clock_map.describe(since=t0)}}
        if with_actions:
            extra["actions"] = {**writer.meta.extra["actions"], "gripper_from_state_frames":
                                {name: a.gripper_action_from_state for name, a in stats.arms.items()}}
        result = close_episode(path, sink, stats, extra, loop.camera_error, created)
        for cam_stats in stats.cameras.values():
            cam_stats.frames = stats.frames
        if not result.removed:
            log.info("%s: %d frames, %d joint samples, %d lost, %d flagged, stop: %s%s", path, stats.frames,
                     stats.joint_samples, stats.frames_lost, stats.flagged, stats.stop_reason,
                     f"; ERROR: {result.error}" if result.error else "")
        return result


class _RigLoop:
    """The matching loop of one episode (kept apart from :class:`RigRecorder` for readability)."""

    def __init__(self, rec: RigRecorder, t0: float, sink: EpisodeSink, stats: RigStats, with_actions: bool,
                 max_skew_s: float) -> None:
        self.rec = rec
        self.t0 = t0
        self.sink = sink
        self.stats = stats
        self.with_actions = with_actions
        self.max_skew_s = max_skew_s
        self.reference = rec.camera_feeds[rec.reference]
        self.others = [feed for name, feed in rec.camera_feeds.items() if name != rec.reference]
        self.camera_error: str | None = None
        self.queued = 0
        self.last_gap = 0.0
        self.recent: collections.deque[float] = collections.deque()
        self._can_frames = (self._can_total(), rec.clock.monotonic())

    def _can_total(self) -> int:
        return sum(feed.arm.stats().frames for feed in self.rec.feeds.values())

    def run(self, duration: float | None, stop: threading.Event, on_status: Callable[[Status], None] | None,
            status_every_s: float) -> str:
        clock = self.rec.clock
        next_status = clock.monotonic() + status_every_s
        while True:
            now = clock.monotonic()
            if stop.is_set():
                return "stopped"
            if duration is not None and now - self.t0 >= duration:
                return "duration"
            if self.sink.failed.is_set():
                return "write error"
            failed = [cam.error for cam in self.rec.camera_feeds.values() if cam.error]
            if failed:
                self.camera_error = "; ".join(failed)
                return "camera error"
            if any(cam.ended for cam in self.rec.camera_feeds.values()):
                return "camera ended"
            self.resolve(force=False)
            self.rec.clock_map.maybe_remeasure()
            if on_status is not None and now >= next_status:
                next_status = now + status_every_s
                on_status(self.status(now))
            clock.sleep_until(clock.monotonic() + 0.005, RealDeadline(0.01, stop))

    def resolve(self, force: bool) -> None:
        """Write the reference frames whose partner images and arm states are known (or waited long enough)."""
        rec, c = self.rec, self.rec.config
        while (head := self.reference.oldest()) is not None:
            t, frame = head
            decide = force or rec.clock.monotonic() - t >= c.max_wait_s
            if not (decide or all(feed.known_at(t) for feed in rec.feeds.values())):
                return
            found = {}
            for cam in self.others:
                decided, index = cam.find(t, self.max_skew_s, decide=decide)
                if not decided:
                    return
                found[cam.name] = index
            self.reference.pop_oldest()
            missing = [name for name, index in found.items() if index is None]
            if missing:
                self._skip(frame, missing)
                continue
            images = {self.reference.name: (t, frame)}
            images.update((cam.name, cam.take(found[cam.name], t)) for cam in self.others)
            self._write(t, images)

    def _skip(self, frame: CameraFrame, missing: list[str]) -> None:
        self.stats.skipped += 1
        for name in missing:
            self.rec.camera_feeds[name].stats.unmatched += 1
        if self.stats.skipped == 1:
            log.warning("frame %d of %s skipped: no image of %s within %.1f ms (counted; stats.skipped)", frame.seq,
                        self.reference.name, ", ".join(missing), self.max_skew_s * 1e3)

    def _write(self, t: float, images: dict[str, tuple[float, CameraFrame]]) -> None:
        rec, c = self.rec, self.rec.config
        arms: dict[str, np.ndarray] = {}
        actions: dict[str, np.ndarray] | None = {} if self.with_actions else None
        extra = {f"{name}.seq": float(f.seq) for name, (_, f) in images.items()}
        any_flag, frame_gap = 0, 0.0
        for name, feed in rec.feeds.items():
            values, gap, flags = feed.sync(t, c.max_gap_s)
            arm_stats = self.stats.arms[name]
            if actions is not None:
                action, from_state, action_flags = feed.leader.action_at(t, values)
                flags |= action_flags
                arm_stats.gripper_action_from_state += int(from_state)
                actions[name] = action
            arms[name] = values
            extra[f"{name}.sync_gap"] = gap
            extra[f"{name}.sync_flags"] = float(flags)
            if flags:
                arm_stats.flagged += 1
                for bit, flag in FLAG_NAMES.items():
                    if flags & bit:
                        arm_stats.flag_counts[flag] = arm_stats.flag_counts.get(flag, 0) + 1
            arm_stats.max_sync_gap_s = max(arm_stats.max_sync_gap_s, gap)
            frame_gap = max(frame_gap, gap)
            any_flag |= flags
        self.last_gap = frame_gap
        self.stats.flagged += int(bool(any_flag))
        depth = {cam.name: images[cam.name][1].depth for cam in rec.cameras if cam.depth}
        item = RigFrameItem(t - self.t0, arms, {name: f.rgb for name, (_, f) in images.items()}, depth, actions,
                            {name: ct - self.t0 for name, (ct, _) in images.items() if name != self.reference.name},
                            extra)
        if self.sink.put_frame(item):
            self.queued += 1
            self.recent.append(rec.clock.monotonic())

    def flush_pending(self) -> None:
        """At the end: give every camera up to ``max_wait_s`` (on the clock, at most that + 1 s of
        real time) to deliver its frames exposed before now (a camera thread may lag, or another
        camera's recording ended first) and the pending frames their partner images and arm
        states; :meth:`resolve` with force then writes what is left."""
        rec = self.rec
        t_stop = rec.clock.monotonic()
        deadline = t_stop + rec.config.max_wait_s
        real_deadline = time.monotonic() + rec.config.max_wait_s + 1.0
        while not self.sink.failed.is_set():
            self.resolve(force=False)
            caught_up = all(cam.caught_up(t_stop) for cam in rec.camera_feeds.values())
            if ((caught_up and self.reference.oldest() is None) or rec.clock.monotonic() >= deadline
                    or time.monotonic() >= real_deadline):
                break
            rec.clock.sleep_until(min(deadline, rec.clock.monotonic() + 0.005), RealDeadline(0.01))

    def status(self, now: float) -> Status:
        rec = self.rec
        while self.recent and self.recent[0] < now - 1.0:
            self.recent.popleft()
        frames_before, t_before = self._can_frames
        frames_now = self._can_total()
        can_fps = (frames_now - frames_before) / max(now - t_before, 1e-9)
        self._can_frames = (frames_now, now)
        lost = (self.stats.skipped + self.sink.frames_dropped
                + sum(cam.stats.dropped_camera for cam in rec.camera_feeds.values()))
        return Status(elapsed_s=now - self.t0, fps=float(len(self.recent)), can_fps=can_fps,
                      frames=self.sink.frames_written, lost=lost, sync_gap_ms=self.last_gap * 1e3,
                      flagged=self.stats.flagged, queue=self.sink.queued_frames,
                      camera_silent_s=max(cam.silent_s() for cam in rec.camera_feeds.values()),
                      arm=", ".join(f"{name} {feed.arm.health().state}" for name, feed in rec.feeds.items()))
