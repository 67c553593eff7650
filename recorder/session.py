"""A recording session: one arm and one camera, any number of episodes.

    >>> rec = Recorder(arm, camera, SystemClock(), RecorderConfig(latency_s=0.012))
    >>> rec.wait_for_arm()
    >>> result = rec.record_episode(Path("out/episode_0000"), duration=30.0)

Per episode (:meth:`Recorder.record_episode`):
1. ``episode.json`` (``complete: false``, the clock mapping, the sync settings), ``frames.csv``
   and ``can.asc`` are created; a writer thread (:class:`~.writer.EpisodeSink`) takes over.
2. Every joint sample the arm completes (reader thread) is mapped onto the monotonic timeline
   (:class:`~.clock.ClockMap`), kept for sync (:class:`~.sync.JointHistory`) and queued for
   ``joints.csv``; every CAN frame goes to the CAN log; leader commands to :mod:`.actions`.
3. The camera is read on its own thread (:class:`~.camfeed.CameraFeed`, which counts its
   drops, stale and out-of-order frames and stalls). A frame's time is its stamp minus the
   camera latency (``latency_s``); it waits until a joint sample and a gripper frame after it have arrived (or
   ``max_wait_s`` has passed), then gets the joints interpolated from the joint samples and the
   gripper from the gripper's own frames (:mod:`.sync`, :mod:`.gripper`), the action, its flags,
   and goes to the writer queue (bounded: a full queue drops and counts the frame).
4. At the end (duration, stop event, a camera that ended, a write error) the pending frames are
   resolved, everything queued is written, the statistics are added to ``episode.json`` and
   ``complete: true`` is written last. A write error instead leaves the episode incomplete with
   everything written before it (:class:`~.writer.StorageError`). An episode that ends before
   its first frame was written holds nothing to keep: its folder is removed (and said so).
"""

from __future__ import annotations

import collections
import logging
import math
import shutil
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from manisplat.drivers.base import Camera, DriverError
from manisplat.drivers.piper import PiperArm
from manisplat.episode import ACTION_COLUMNS, CameraInfo, EpisodeWriter, RobotInfo, validate
from manisplat.recorder.armfeed import ArmFeed
from manisplat.recorder.camfeed import CameraFeed
from manisplat.recorder.canlog import CAN_LOG_NAME
from manisplat.recorder.clock import Clock, ClockMap, RealDeadline
from manisplat.recorder.sync import FLAG_NAMES
from manisplat.recorder.writer import EpisodeSink, FrameItem, StorageError, describe_write_error

if TYPE_CHECKING:
    from manisplat.recorder.rig import RigStats

log = logging.getLogger(__name__)

DEPTH_SCALE = 0.001  # metres per depth unit: millimetres, the OAK's own unit
SYNC_COLUMNS = ("seq", "sync_gap", "sync_flags")


@dataclass
class RecorderConfig:
    """Settings of a recording (the CLI flags).

    Attributes:
        fps: the camera rate declared in ``episode.json`` (None: the camera's nominal rate).
        latency_s: camera latency from calibration, s: the frame's true time is its stamp minus this.
        max_gap_s: a frame interpolated across a longer gap between joint samples is flagged, s
            (the PiPER samples every 5 ms; default 3 samples).
        max_wait_s: how long a frame waits for a joint sample after it before it is written
            with the last state held (flagged), s.
        image_format: ``"png"`` or ``"jpg"``.
        depth: record depth (the camera must give it); False drops any depth the camera gives.
        task: the task text for ``episode.json``.
        actions: ``"auto"`` (record leader commands as actions when seen before the episode
            starts), ``"on"`` or ``"off"``.
        max_action_age_s: a leader command older than this at a frame is stale, s.
        queue_frames: frames the writer queue holds.
        fsync_every: fsync the episode's files every this many rows.
        camera_poll_s: the loop waits at most this long for a camera frame, s.
        max_skew_s: several cameras (:mod:`.rig`): the most another camera's image may be from
            the reference camera's frame time, s (None: half a frame period).
        stall_after_s: a camera silent for longer counts as stalled, s.
    """

    fps: float | None = None
    latency_s: float = 0.0
    max_gap_s: float = 0.015
    max_wait_s: float = 0.25
    image_format: str = "png"
    depth: bool = False
    task: str | None = None
    actions: str = "auto"
    max_action_age_s: float = 0.1
    queue_frames: int = 64
    fsync_every: int = 200
    camera_poll_s: float = 0.05
    stall_after_s: float = 0.5
    max_skew_s: float | None = None

    def __post_init__(self) -> None:
        if self.actions not in ("auto", "on", "off"):
            raise ValueError(f"actions must be auto, on or off; got {self.actions!r}")
        if self.image_format not in ("png", "jpg"):
            raise ValueError(f"image_format must be png or jpg; got {self.image_format!r}")
        for name in ("max_gap_s", "max_wait_s", "camera_poll_s", "stall_after_s", "max_action_age_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.max_skew_s is not None and not self.max_skew_s > 0:
            raise ValueError(f"max_skew_s must be > 0, got {self.max_skew_s}")
        if self.fps is not None and not self.fps > 0:
            raise ValueError(f"fps must be > 0, got {self.fps}")
        if not math.isfinite(self.latency_s) or abs(self.latency_s) > 1.0:
            raise ValueError(f"latency_s must be within +-1 s, got {self.latency_s}")


@dataclass
class EpisodeStats:
    """What happened in one episode (also written to ``episode.json`` ``stats``).

    Counts of frames: ``frames`` written; ``dropped_camera`` missing in the camera's sequence
    numbers; ``dropped_queue`` lost because the writer fell behind; ``stale`` read after the
    start but exposed before it; ``out_of_order`` with a time not after the previous frame's;
    ``flagged`` written with a sync flag (``flag_counts`` by flag name).
    """

    frames: int = 0
    dropped_camera: int = 0
    dropped_queue: int = 0
    stale: int = 0
    out_of_order: int = 0
    flagged: int = 0
    flag_counts: dict[str, int] = field(default_factory=dict)
    joint_samples: int = 0
    can_frames_logged: int = 0
    can_frames_dropped: int = 0
    duration_s: float = 0.0
    max_sync_gap_s: float = 0.0
    camera_stalls: int = 0
    longest_camera_gap_s: float = 0.0
    gripper_action_from_state: int = 0
    stop_reason: str = ""

    @property
    def frames_lost(self) -> int:
        return self.dropped_camera + self.dropped_queue


@dataclass
class EpisodeResult:
    """The outcome of :meth:`Recorder.record_episode`.

    Attributes:
        path: the episode folder.
        stats: :class:`EpisodeStats` (:class:`~.rig.RigStats` for named arms and cameras).
        error: why the episode could not be completed (None when complete).
        valid: whether ``validate`` (quick) found no error (False when incomplete).
        removed: the folder was removed because no frame had been written (``error`` says so).
    """

    path: Path
    stats: EpisodeStats | RigStats
    error: str | None = None
    valid: bool = False
    removed: bool = False


@dataclass
class Status:
    """A snapshot for the live status line.

    Attributes: ``elapsed_s``; ``fps`` (frames written in the last second); ``can_fps`` (CAN
    frames received per s); ``frames``; ``lost`` (camera + queue drops); ``sync_gap_ms`` (of the
    last frame); ``flagged``; ``queue`` (frames waiting for the writer); ``camera_silent_s``;
    ``arm`` (arm health state).
    """

    elapsed_s: float
    fps: float
    can_fps: float
    frames: int
    lost: int
    sync_gap_ms: float
    flagged: int
    queue: int
    camera_silent_s: float
    arm: str


class Recorder:
    """Records episodes from ``arm`` and ``camera``; see the module docstring.

    Args:
        arm: a PiperArm (read-only is enough) on the bus.
        camera: any :class:`~manisplat.drivers.base.Camera`.
        clock: the host clocks (:class:`~.clock.SystemClock` outside tests).
        config: :class:`RecorderConfig`.
        camera_name: ``episode.json`` camera name.
        source_info: free-form description of the arm and camera for ``episode.json``.
        nominal_fps: the camera's configured rate (used when ``config.fps`` is None).
    """

    def __init__(self, arm: PiperArm, camera: Camera, clock: Clock, config: RecorderConfig | None = None, *,
                 camera_name: str = "ego", source_info: dict[str, Any] | None = None,
                 nominal_fps: float | None = None) -> None:
        self.arm = arm
        self.camera = camera
        self.clock = clock
        self.config = config if config is not None else RecorderConfig()
        self.camera_name = camera_name
        self.source_info = dict(source_info or {})
        self.nominal_fps = nominal_fps
        self.clock_map = ClockMap(clock)
        self.feed = ArmFeed(arm, clock, self.clock_map, self.config.max_action_age_s)
        c = self.config
        self.camera_feed = CameraFeed(camera_name, camera, clock, latency_s=c.latency_s, depth=c.depth,
                                      poll_s=c.camera_poll_s, stall_after_s=c.stall_after_s)

    def wait_for_arm(self, timeout: float = 3.0) -> None:
        """Wait for complete joint samples of the arm (:meth:`.armfeed.ArmFeed.wait`; DriverError
        when none comes within ``timeout`` s), warning when its CAN stamps are not wall-clock."""
        warning = self.feed.wait(timeout)
        if warning:
            log.warning("%s", warning)

    def _episode_meta(self, t0: float, t0_wall: float, with_actions: bool) -> dict[str, Any]:
        c = self.config
        meta: dict[str, Any] = {
            "recording": {"tool": "manisplat-record", **self.source_info},
            "clock": {**self.clock_map.describe(since=t0), "t0_monotonic": t0, "t0_wall": t0_wall,
                      "can_timestamps": self.feed.describe_stamps(),
                      "camera_timestamps": "camera stamps (host monotonic clock, mid-exposure where known)",
                      "camera_latency_s": c.latency_s},
            "sync": {"method": "linear interpolation between the joint samples around each frame time "
                               "(frame time = camera stamp - camera_latency_s); never extrapolated",
                     "max_gap_s": c.max_gap_s, "max_wait_s": c.max_wait_s,
                     "columns": {"seq": "camera sequence number",
                                 "sync_gap": "s between the joint samples interpolated across",
                                 "sync_flags": {str(k): v for k, v in FLAG_NAMES.items()}}},
            "can_log": {"file": CAN_LOG_NAME, "time_zero_wall": t0_wall,
                        "note": "timestamps in the file are s since time_zero_wall = episode t 0"},
        }
        if c.task:
            meta["task"] = c.task
        if with_actions:
            meta["actions"] = {"source": "leader-arm commands seen on the bus (0x155-0x157 joints, 0x159 gripper)",
                               "rule": "the latest command at or before the frame time; stale after "
                                       f"{c.max_action_age_s} s (then the measured state, flag action_stale)"}
        return meta

    # -- one episode --------------------------------------------------------------------------

    def record_episode(self, path: Path, *, duration: float | None = None, stop: threading.Event | None = None,
                       on_status: Callable[[Status], None] | None = None, status_every_s: float = 0.5) -> EpisodeResult:
        """Record one episode into the new folder ``path``; see the module docstring.

        Ends after ``duration`` s (on the clock), when ``stop`` is set, when the camera ends,
        or at the first write error. Returns an :class:`EpisodeResult` (its ``error`` says why
        an episode is incomplete); raises DriverError when the arm has never been heard.
        """
        c = self.config
        stop = stop if stop is not None else threading.Event()
        feed = self.feed
        if feed.history.last_t is None:
            raise DriverError("no joint sample yet: call wait_for_arm() first")
        with_actions = c.actions == "on" or (c.actions == "auto" and feed.leader.seen)
        columns = SYNC_COLUMNS + (ACTION_COLUMNS if with_actions else ())
        self.clock_map.remeasure()
        t0 = self.clock.monotonic()
        t0_wall = t0 + self.clock_map.offset
        cam = CameraInfo(name=self.camera_name, width=self.camera.width, height=self.camera.height, K=self.camera.K,
                         dist=opencv_dist(self.camera.dist), mount="base", T_mount_cam=None)
        fps = c.fps or self.nominal_fps or 30.0
        created = not path.exists()
        writer: EpisodeWriter | None = None
        try:
            writer = EpisodeWriter(path, cam, RobotInfo(), fps, source="recorder",
                                   depth_scale=DEPTH_SCALE if c.depth else None, image_format=c.image_format,
                                   extra_frame_columns=columns,
                                   extra_meta=self._episode_meta(t0, t0_wall, with_actions), fsync_every=c.fsync_every)
            feed.can_log.open(path / CAN_LOG_NAME, t0_wall)
        except OSError as exc:
            if writer is not None:
                writer.__exit__(type(exc), exc, exc.__traceback__)
            error = f"{path}: cannot start the episode: {describe_write_error(exc)}"
            log.error("%s", error)
            result = EpisodeResult(path, EpisodeStats(stop_reason="write error"), error)
            return remove_empty(result) if created else result
        sink = EpisodeSink(writer, [feed.can_log], queue_frames=c.queue_frames)
        feed.activate(t0, sink)
        self.camera_feed.start(t0)
        stats = EpisodeStats()
        loop = _EpisodeLoop(self, t0, sink, stats, with_actions)
        log.info("%s: recording (%s)", path, f"{duration} s" if duration else "until stopped")
        try:
            stats.stop_reason = loop.run(duration, stop, on_status, status_every_s)
        finally:
            loop.flush_pending()
            self.camera_feed.stop()
            loop.resolve(force=True)
            stats.joint_samples = feed.deactivate()
            feed.can_log.seal()
        camera = self.camera_feed.stats
        stats.dropped_camera, stats.stale, stats.out_of_order = camera.dropped_camera, camera.stale, camera.out_of_order
        stats.camera_stalls, stats.longest_camera_gap_s = camera.stalls, camera.longest_gap_s
        stats.frames = loop.queued  # all of them are on disk once finish() succeeds
        stats.duration_s = self.clock.monotonic() - t0
        stats.dropped_queue = sink.frames_dropped
        stats.can_frames_dropped = feed.can_log.dropped
        stats.can_frames_logged = feed.can_log.received - feed.can_log.dropped
        extra = {"stats": {k: v for k, v in asdict(stats).items()},
                 "clock": {**writer.meta.extra["clock"], **self.clock_map.describe(since=t0)}}
        if with_actions:
            extra["actions"] = {**writer.meta.extra["actions"],
                                "gripper_from_state_frames": stats.gripper_action_from_state}
        result = close_episode(path, sink, stats, extra, loop.camera_error, created)
        if result.removed:
            return result
        log.info("%s: %d frames, %d joint samples, %d lost, %d flagged, stop: %s%s", path, stats.frames,
                 stats.joint_samples, stats.frames_lost, stats.flagged, stats.stop_reason,
                 f"; ERROR: {result.error}" if result.error else "")
        return result


class _EpisodeLoop:
    """The frame loop of one episode (kept apart from :class:`Recorder` for readability): the
    camera is read on its own thread (:class:`~.camfeed.CameraFeed`, which counts its drops)."""

    def __init__(self, rec: Recorder, t0: float, sink: EpisodeSink, stats: EpisodeStats, with_actions: bool) -> None:
        self.rec = rec
        self.t0 = t0
        self.sink = sink
        self.stats = stats
        self.with_actions = with_actions
        self.camera = rec.camera_feed
        self.camera_error: str | None = None
        self.queued = 0
        self.last_gap = 0.0
        self.recent: collections.deque[float] = collections.deque()
        self._can_frames = (rec.arm.stats().frames, rec.clock.monotonic())

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
            if self.camera.error is not None:
                self.camera_error = self.camera.error
                return "camera error"
            if self.camera.ended:
                return "camera ended"
            self.resolve(force=False)
            self.rec.clock_map.maybe_remeasure()
            if on_status is not None and now >= next_status:
                next_status = now + status_every_s
                on_status(self.status(now))
            clock.sleep_until(clock.monotonic() + 0.005, RealDeadline(0.01, stop))

    def resolve(self, force: bool) -> None:
        """Sync and queue the frames read whose joint state is known (or waited long enough)."""
        rec, c = self.rec, self.rec.config
        while (head := self.camera.oldest()) is not None:
            t, frame = head
            waited = rec.clock.monotonic() - t
            if not (force or rec.feed.known_at(t) or waited >= c.max_wait_s):
                return
            self.camera.pop_oldest()
            values, gap, flags = rec.feed.sync(t, c.max_gap_s)
            extra = {"seq": float(frame.seq), "sync_gap": gap}
            if self.with_actions:
                action, from_state, aflags = rec.feed.leader.action_at(t, values)
                flags |= aflags
                self.stats.gripper_action_from_state += int(from_state)
                extra.update(zip(ACTION_COLUMNS, action.tolist()))
            extra["sync_flags"] = float(flags)
            if flags:
                self.stats.flagged += 1
                for bit, name in FLAG_NAMES.items():
                    if flags & bit:
                        self.stats.flag_counts[name] = self.stats.flag_counts.get(name, 0) + 1
            self.stats.max_sync_gap_s = max(self.stats.max_sync_gap_s, gap)
            self.last_gap = gap
            item = FrameItem(t - self.t0, values[:6], float(values[6]), frame.rgb,
                             frame.depth if c.depth else None, extra)
            if self.sink.put_frame(item):
                self.queued += 1
                self.recent.append(rec.clock.monotonic())

    def flush_pending(self) -> None:
        """At the end: give the frames read up to ``max_wait_s`` (on the clock, at most that + 1 s
        of real time) for a joint sample after them; :meth:`resolve` with force writes the rest."""
        rec = self.rec
        deadline = rec.clock.monotonic() + rec.config.max_wait_s
        real_deadline = time.monotonic() + rec.config.max_wait_s + 1.0
        while self.camera.oldest() is not None and not self.sink.failed.is_set():
            self.resolve(force=False)
            if self.camera.oldest() is None or rec.clock.monotonic() >= deadline or time.monotonic() >= real_deadline:
                break
            rec.clock.sleep_until(min(deadline, rec.clock.monotonic() + 0.005), RealDeadline(0.01))

    def status(self, now: float) -> Status:
        rec = self.rec
        while self.recent and self.recent[0] < now - 1.0:
            self.recent.popleft()
        frames_before, t_before = self._can_frames
        frames_now = rec.arm.stats().frames
        can_fps = (frames_now - frames_before) / max(now - t_before, 1e-9)
        self._can_frames = (frames_now, now)
        sink = self.sink
        return Status(elapsed_s=now - self.t0, fps=float(len(self.recent)), can_fps=can_fps,
                      frames=sink.frames_written, lost=self.camera.stats.dropped_camera + sink.frames_dropped,
                      sync_gap_ms=self.last_gap * 1e3, flagged=self.stats.flagged, queue=sink.queued_frames,
                      camera_silent_s=self.camera.silent_s(), arm=rec.arm.health().state)


def close_episode(path: Path, sink: EpisodeSink, stats: Any, extra: dict[str, Any], error: str | None,
                  created: bool) -> EpisodeResult:
    """Finish the episode ``sink`` writes (``extra`` into ``episode.json``, ``complete: true``
    last), then validate it; an episode without a frame in a folder this run ``created`` is removed.
    ``stats`` gets the frames written; ``error``: why the episode ended early, or None."""
    try:
        sink.finish(extra)
    except StorageError as exc:
        error = str(exc)
    stats.frames = sink.frames_written
    result = EpisodeResult(path, stats, error)
    if not stats.frames and created:
        return remove_empty(result)
    if sink.complete:
        report = validate(path, decode_images=False)
        result.valid = report.ok
        if not report.ok:
            result.error = (result.error + "; " if result.error else "") + f"validation failed:\n{report}"
    return result


def remove_empty(result: EpisodeResult) -> EpisodeResult:
    """Remove the folder of an episode in which no frame was written (the joint samples and CAN
    frames before a first frame are no episode), saying so in ``result.error``; a folder that
    cannot be removed stays."""
    try:
        shutil.rmtree(result.path)
    except OSError as exc:
        note = f"no frame was recorded; the episode folder could not be removed: {exc}"
    else:
        result.removed = True
        note = f"no frame was recorded: removed the episode folder {result.path}"
    result.error = f"{result.error.rstrip('.')}; {note}" if result.error else note
    log.error("%s", note)
    return result


def opencv_dist(dist: np.ndarray) -> np.ndarray:
    """Distortion coefficients in a length OpenCV (and the episode format) accepts."""
    d = np.asarray(dist, dtype=np.float64).reshape(-1)
    for n in (0, 4, 5, 8, 12, 14):
        if len(d) <= n:
            return np.concatenate([d, np.zeros(n - len(d))]) if len(d) else d
    raise ValueError(f"{len(d)} distortion coefficients: more than OpenCV's 14")
