"""The writer thread of one episode: frames arrive through a bounded queue, joint samples and
CAN frames through their own unbounded buffers, and one thread writes them all with the
episode's writer (:class:`~manisplat.episode.EpisodeWriter` for one arm and camera,
:class:`~manisplat.episode.writer_v2.EpisodeWriterV2` for named arms and cameras; images then
row, each flushed as it goes) and the episode's :class:`~.canlog.CanLogSink` (one per arm).

A frame that finds the queue full is dropped and counted (the recording loop never blocks on
the disk). The first write error (a full disk, a file size limit, an I/O error) stops the
thread: nothing more is written, the files are closed with ``complete: false``, and
:attr:`EpisodeSink.error` says what failed; everything written before stays on disk.
"""

from __future__ import annotations

import collections
import errno
import logging
import queue
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Sequence, Union

import numpy as np

from manisplat.episode import EpisodeWriter
from manisplat.episode.writer_v2 import EpisodeWriterV2
from manisplat.recorder.canlog import CanLogSink

Writer = Union[EpisodeWriter, EpisodeWriterV2]

log = logging.getLogger(__name__)

DISK_FULL_ERRNOS = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is exceeded",
                    errno.EFBIG: "a file reached the size limit"}


class StorageError(RuntimeError):
    """Writing the episode failed (disk full, I/O error, or an unexpected error in the writer);
    what was written before is kept. The message gives the advice that fits the error."""


def describe_write_error(exc: BaseException) -> str:
    """A sentence for a write error, naming a full disk as such."""
    if isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS:
        where = f" ({exc.filename})" if exc.filename else ""
        return f"{DISK_FULL_ERRNOS[exc.errno]}{where}: {exc.strerror}"
    return f"{type(exc).__name__}: {exc}"


@dataclass
class FrameItem:
    """One synced frame for the writer.

    Attributes:
        t: seconds since the episode's start.
        q: (6,) rad; gripper: m.
        rgb: (H, W, 3) uint8; depth: (H, W) float32 m or None.
        extra: values of the episode's extra ``frames.csv`` columns.
    """

    t: float
    q: np.ndarray
    gripper: float
    rgb: np.ndarray
    depth: np.ndarray | None = None
    extra: dict[str, float] = field(default_factory=dict)

    def encode(self, writer: EpisodeWriter) -> Any:
        """The frame's images encoded (any thread; no file is touched)."""
        return writer.encode_frame(self.rgb, self.depth)

    def write(self, writer: EpisodeWriter, encoded: Any) -> None:
        """Write the frame (images, then its row); ``encoded`` from :meth:`encode` or None."""
        writer.add_frame(self.t, self.q, self.gripper, self.rgb, depth=self.depth, extra=self.extra, encoded=encoded)


@dataclass
class RigFrameItem:
    """One synced frame of named arms and cameras for an :class:`EpisodeWriterV2`.

    Attributes:
        t: seconds since the episode's start (the reference camera's frame time).
        arms: arm name -> (7,) q1..q6 rad, gripper m.
        rgb: camera name -> (H, W, 3) uint8; depth: camera name -> (H, W) float32 m.
        actions: arm name -> (7,) a1..a6 rad, a_gripper m, or None without actions.
        camera_t: camera name -> its own frame time, s since the start (cameras other than the reference).
        extra: values of the episode's extra ``frames.csv`` columns.
    """

    t: float
    arms: dict[str, np.ndarray]
    rgb: dict[str, np.ndarray]
    depth: dict[str, np.ndarray]
    actions: dict[str, np.ndarray] | None
    camera_t: dict[str, float]
    extra: dict[str, float]

    def encode(self, writer: EpisodeWriterV2) -> Any:
        """Every camera's images encoded (any thread; no file is touched)."""
        return writer.encode_frame(self.rgb, self.depth)

    def write(self, writer: EpisodeWriterV2, encoded: Any) -> None:
        """Write the frame (every camera's images, then its row); ``encoded`` from :meth:`encode` or None."""
        writer.add_frame(self.t, self.arms, self.rgb, depth=self.depth, actions=self.actions, camera_t=self.camera_t,
                         extra=self.extra, encoded=encoded)


_STOP = object()


class EpisodeSink:
    """Owns an episode writer (and the episode's :class:`CanLogSink` s) on a thread.

    Args:
        writer: the episode writer (``episode.json`` already written, ``complete: false``):
            :class:`FrameItem` s go to an :class:`EpisodeWriter`, :class:`RigFrameItem` s to an
            :class:`EpisodeWriterV2`.
        can_logs: the episode's CAN log sinks (one per arm), opened by the caller.
        queue_frames: frames the queue holds before new ones are dropped.
        flush_s: the CAN log is flushed at least this often, s.
        encode_threads: threads encoding images (PNG/JPEG) ahead of the writer, in parallel
            (OpenCV releases the GIL); 0 encodes on the writer thread. 1280x720 RGB + depth
            PNG on 2 cores: 18 frames/s with 0, 42 with 2 (``benchmarks record_write``).
    """

    def __init__(self, writer: Writer, can_logs: Sequence[CanLogSink] = (), *, queue_frames: int = 64,
                 flush_s: float = 0.1, encode_threads: int = 2) -> None:
        if queue_frames < 1:
            raise ValueError(f"queue_frames must be >= 1, got {queue_frames}")
        if encode_threads < 0:
            raise ValueError(f"encode_threads must be >= 0, got {encode_threads}")
        self._encoders = (ThreadPoolExecutor(encode_threads, thread_name_prefix=f"encode-{writer.path.name}")
                          if encode_threads else None)
        self.writer = writer
        self.can_logs = tuple(can_logs)
        self.flush_s = float(flush_s)
        self._frames: queue.Queue[Any] = queue.Queue(maxsize=queue_frames)
        self._joints: collections.deque[tuple[str | None, float, np.ndarray, float]] = collections.deque()
        self._final_extra: dict[str, Any] = {}
        self.error: BaseException | None = None
        self.failed = threading.Event()
        self.frames_written = 0
        self.joints_written = 0
        self.frames_dropped = 0
        self.max_queue = 0
        self.complete = False
        self._doing = "starting"
        self._thread = threading.Thread(target=self._run, name=f"EpisodeSink-{writer.path.name}", daemon=True)
        self._thread.start()

    # -- producer side ------------------------------------------------------------------------

    def put_frame(self, item: FrameItem | RigFrameItem) -> bool:
        """Queue a frame (its images start encoding now); False when it was dropped (queue
        full) or the sink has failed."""
        if self.failed.is_set():
            return False
        if self._frames.full():  # checked first: a dropped frame costs no encoding
            return self._dropped()
        try:
            encoding = None if self._encoders is None else self._encoders.submit(item.encode, self.writer)
        except RuntimeError:  # the writer thread ended (failed or finished) just now
            return False
        try:
            self._frames.put_nowait((item, encoding))
        except queue.Full:  # another producer filled it in between
            if encoding is not None:
                encoding.cancel()
            return self._dropped()
        self.max_queue = max(self.max_queue, self._frames.qsize())
        return True

    def _dropped(self) -> bool:
        self.frames_dropped += 1
        if self.frames_dropped == 1:
            log.warning("%s: the writer falls behind (queue of %d frames full); dropping frames (counted)",
                        self.writer.path, self._frames.maxsize)
        return False

    def put_joint(self, t: float, q: np.ndarray, gripper: float, arm: str | None = None) -> None:
        """Queue a joint-stream row (any thread; never dropped): ``joints.csv``, or with ``arm``
        ``joints_<arm>.csv``; ``t`` s since the start, ``q`` (6,) rad, ``gripper`` m."""
        if not self.failed.is_set():
            self._joints.append((arm, t, q, gripper))

    @property
    def queued_frames(self) -> int:
        return self._frames.qsize()

    # -- the thread ---------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            self._loop()
            self._doing = "closing the episode"
            self.writer.meta.extra.update(self._final_extra)
            self.writer.close()
            for can_log in self.can_logs:
                can_log.close()
            self.complete = True
        except BaseException as exc:  # the first write error ends the episode (module docstring)
            self.error = exc
            self.failed.set()
            log.error("%s: writing stopped while writing %s: %s", self.writer.path, self._doing,
                      describe_write_error(exc))
            try:
                self.writer.__exit__(type(exc), exc, exc.__traceback__)  # close, leave complete: false
            except OSError as again:
                log.error("%s: closing the files failed too: %s", self.writer.path, again)
            for can_log in self.can_logs:
                can_log.abandon()
        finally:
            if self._encoders is not None:
                self._encoders.shutdown(wait=False, cancel_futures=True)

    def _loop(self) -> None:
        last_flush = time.monotonic()
        while True:
            try:
                item = self._frames.get(timeout=self.flush_s)
            except queue.Empty:
                item = None
            if item is not None and item is not _STOP:
                frame, encoding = item
                self._doing = f"frame {self.frames_written} (its images and frames.csv row)"
                frame.write(self.writer, None if encoding is None else encoding.result())
                self.frames_written += 1
            self._doing = "joints.csv"
            self._write_joints()
            now = time.monotonic()
            if self.can_logs and (item is None or item is _STOP or now - last_flush >= self.flush_s):
                for can_log in self.can_logs:
                    self._doing = f"the CAN log {can_log.path.name if can_log.path else ''}"
                    can_log.drain(flush=True)
                last_flush = now
            if item is _STOP:
                return

    def _write_joints(self) -> None:
        while True:
            try:
                arm, t, q, gripper = self._joints.popleft()
            except IndexError:
                return
            if arm is None:
                self.writer.add_joint_sample(t, q, gripper)
            else:
                self.writer.add_joint_sample(arm, t, q, gripper)
            self.joints_written += 1

    # -- ending -------------------------------------------------------------------------------

    def finish(self, extra_meta: dict[str, Any] | None = None, timeout: float = 120.0) -> None:
        """Write everything queued, add ``extra_meta`` to ``episode.json`` and mark the episode
        complete. Raises :class:`StorageError` when a write failed (the episode then stays
        incomplete, with everything written before the failure)."""
        self._final_extra = dict(extra_meta or {})
        deadline = time.monotonic() + timeout
        while self._thread.is_alive():
            try:
                self._frames.put(_STOP, timeout=0.1)
                break
            except queue.Full:
                if time.monotonic() > deadline:
                    break
        self._thread.join(max(0.0, deadline - time.monotonic()))
        if self._thread.is_alive():
            raise StorageError(f"{self.writer.path}: the writer did not finish within {timeout} s "
                               f"({self._frames.qsize()} frames still queued); the episode stays incomplete")
        if self.error is not None:
            raise StorageError(f"{self.writer.path}: {describe_write_error(self.error)} (writing {self._doing}); "
                               f"recording stopped.{self._kept()}") from self.error

    def _kept(self) -> str:
        """What a failed episode kept, with the advice that fits its error (nothing when no frame was written)."""
        if not isinstance(self.error, OSError):
            return (" This is an unexpected error, not a storage problem: please report it."
                    + (f" Kept {self.frames_written} frames and {self.joints_written} joint samples (the episode "
                       f"is left incomplete)" if self.frames_written else ""))
        if not self.frames_written:
            return ""
        free = "free space, then " if self.error.errno in (errno.ENOSPC, errno.EDQUOT) else ""
        return (f" Kept {self.frames_written} frames and {self.joints_written} joint samples (episode left "
                f"incomplete: {free}run `manisplat-record --recover {self.writer.path}`)")
