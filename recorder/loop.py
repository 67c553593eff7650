"""The frame loop of one episode, for one arm and camera or named ones alike.

The frames are the reference camera's (the first camera): a frame's time ``t`` is its stamp
minus that camera's latency. Each other camera gives its image nearest to ``t`` within
``max_skew_s``; a frame waits (up to ``max_wait_s``) for the other cameras' images around it and
for every arm's joint sample and gripper frame after it, then every arm's state at ``t`` is
interpolated (:meth:`~.armfeed.ArmFeed.sync`), counted (:class:`~.stats.RigStats`) and the frame
the recorder's layout makes of it goes to the writer queue (bounded: a full queue drops and
counts the frame). A reference frame without an image of another camera near enough is skipped
and counted.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np

from manisplat.drivers.base import CameraFrame
from manisplat.recorder.armfeed import JOINT_TAIL_S
from manisplat.recorder.clock import RealDeadline
from manisplat.recorder.result import Status
from manisplat.recorder.stats import RigStats
from manisplat.recorder.sync import FLAG_NAMES
from manisplat.recorder.writer import EpisodeSink

if TYPE_CHECKING:
    from manisplat.recorder.rig import RigRecorder

log = logging.getLogger(__name__)


@dataclass
class ArmSync:
    """One arm's state at a frame: (7,) q1..q6 rad and gripper m, the gap interpolated across
    (s), the sync flags, the action ((7,), None without actions) and the gripper's effort (N*m)."""

    values: np.ndarray
    gap: float
    flags: int
    action: np.ndarray | None
    gripper_effort: float


class EpisodeLoop:
    """The matching loop of one episode (kept apart from :class:`~.rig.RigRecorder` for readability)."""

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
        self.end: float | None = None  # set when the episode ends: frames exposed from then on are not its own
        self.queued = 0
        self.last_gap = 0.0
        self.recent: collections.deque[float] = collections.deque()
        self._can_frames = (self._can_total(), rec.clock.monotonic())

    def _can_total(self) -> int:
        return sum(feed.arm.stats().frames for feed in self.rec.feeds.values())

    def run(self, duration: float | None, stop: threading.Event, on_status: Callable[[Status], None] | None,
            status_every_s: float) -> str:
        """Match and queue frames until the episode ends; returns why it ended."""
        clock = self.rec.clock
        next_status = clock.monotonic() + status_every_s
        while True:
            now = clock.monotonic()
            if stop.is_set():
                self.end = now
                return "stopped"
            if duration is not None and now - self.t0 >= duration:
                self.end = self.t0 + duration
                return "duration"
            failure = self._failure()
            if failure is not None:
                self.end = now
                return failure
            self.resolve(force=False, until=now)
            self.rec.clock_map.maybe_remeasure()
            if on_status is not None and now >= next_status:
                next_status = now + status_every_s
                on_status(self.status(now))
            clock.sleep_until(clock.monotonic() + 0.005, RealDeadline(0.01, stop))

    def _failure(self) -> str | None:
        """Why the episode must end now (the writer or a camera failed, a camera ended), or None."""
        if self.sink.failed.is_set():
            return "write error"
        failed = [cam.error for cam in self.rec.camera_feeds.values() if cam.error]
        if failed:
            self.camera_error = "; ".join(failed)
            return "camera error"
        if any(cam.ended for cam in self.rec.camera_feeds.values()):
            return "camera ended"
        return None

    def resolve(self, force: bool, until: float) -> None:
        """Write the reference frames exposed before ``until`` (monotonic s) whose partner images
        and arm states are known (or waited long enough). Bounded by ``until``, one call ends even
        when the cameras deliver faster than frames are written (a lock-step clock on a loaded
        machine) and never writes a frame exposed after the episode's end."""
        rec, c = self.rec, self.rec.config
        while (head := self.reference.oldest()) is not None and head[0] < until:
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

    def _sync(self, t: float) -> dict[str | None, ArmSync]:
        """Every arm's state (and action) at ``t``, counted in its :class:`~.stats.ArmStats`."""
        synced = {}
        for name, feed in self.rec.feeds.items():
            values, gap, flags, gripper_effort = feed.sync(t, self.rec.config.max_gap_s)
            arm_stats = self.stats.arms[name]
            action = None
            if self.with_actions:
                action, from_state, action_flags = feed.leader.action_at(t, values)
                flags |= action_flags
                arm_stats.gripper_action_from_state += int(from_state)
            if flags:
                arm_stats.flagged += 1
                for bit, flag in FLAG_NAMES.items():
                    if flags & bit:
                        arm_stats.flag_counts[flag] = arm_stats.flag_counts.get(flag, 0) + 1
            arm_stats.max_sync_gap_s = max(arm_stats.max_sync_gap_s, gap)
            synced[name] = ArmSync(values, gap, flags, action, gripper_effort)
        return synced

    def _write(self, t: float, images: dict[str, tuple[float, CameraFrame]]) -> None:
        synced = self._sync(t)
        self.last_gap = max(arm.gap for arm in synced.values())
        self.stats.flagged += int(any(arm.flags for arm in synced.values()))
        item = self.rec.layout.frame_item(self.rec, self.t0, t, images, synced, self.with_actions)
        if self.sink.put_frame(item):
            self.queued += 1
            self.recent.append(self.rec.clock.monotonic())

    def flush_pending(self) -> None:
        """At the end: give every camera up to ``max_wait_s`` (on the clock, at most that +
        ``flush_grace_s`` of real time) to deliver its frames exposed before the episode's end (a camera thread may lag, or another
        camera's recording ended first) and the pending frames their partner images and arm
        states; :meth:`resolve` with force then writes what is left."""
        rec = self.rec
        if self.end is None:  # the loop did not end normally (an exception)
            self.end = rec.clock.monotonic()
        t_stop = self.end
        for feed in rec.feeds.values():  # the episode's joints end with it (a stopped one's too)
            feed.end_at(t_stop + JOINT_TAIL_S)
        deadline = rec.clock.monotonic() + rec.config.max_wait_s
        real_deadline = time.monotonic() + rec.config.max_wait_s + rec.config.flush_grace_s
        while not self.sink.failed.is_set():
            self.resolve(force=False, until=t_stop)
            caught_up = all(cam.caught_up(t_stop) for cam in rec.camera_feeds.values())
            pending = self.reference.oldest()
            if ((caught_up and (pending is None or pending[0] >= t_stop)) or rec.clock.monotonic() >= deadline
                    or time.monotonic() >= real_deadline):
                break
            rec.clock.sleep_until(min(deadline, rec.clock.monotonic() + 0.005), RealDeadline(0.01))

    def status(self, now: float) -> Status:
        """The live status at ``now`` (monotonic s)."""
        rec = self.rec
        while self.recent and self.recent[0] < now - 1.0:
            self.recent.popleft()
        frames_before, t_before = self._can_frames
        frames_now = self._can_total()
        can_fps = (frames_now - frames_before) / max(now - t_before, 1e-9)
        self._can_frames = (frames_now, now)
        lost = (self.stats.skipped + self.sink.frames_dropped
                + sum(cam.stats.dropped_camera for cam in rec.camera_feeds.values()))
        health = [(name, feed.arm.health().state) for name, feed in rec.feeds.items()]
        return Status(elapsed_s=now - self.t0, fps=float(len(self.recent)), can_fps=can_fps,
                      frames=self.sink.frames_written, lost=lost, sync_gap_ms=self.last_gap * 1e3,
                      flagged=self.stats.flagged, queue=self.sink.queued_frames,
                      camera_silent_s=max(cam.silent_s() for cam in rec.camera_feeds.values()),
                      arm=", ".join(state if name is None else f"{name} {state}" for name, state in health))
