"""The raw CAN stream of an episode, every frame as received, in a python-can log beside it.

:class:`CanLogSink` is a python-can listener on the arm's reader thread. It only queues each
message (cheap, never blocks the reader); the episode's writer thread calls :meth:`drain` to
write them with python-can's writer for the file's suffix (``can.asc`` by default: text, one
line per frame, readable after a crash up to its last whole line) and flushes it.

The log's time zero is the episode's start: the first line written is an event at the
episode's ``t0`` (wall clock), so the file's relative timestamps are seconds since the
episode's start; ``episode.json`` ``can_log`` gives the absolute wall time of zero.
:func:`repair_can_log` cuts a log torn by a crash back to its last whole line.
"""

from __future__ import annotations

import collections
import copy
import logging
import os
import threading
from pathlib import Path

import can

from manisplat.episode.fsio import fsync_path

log = logging.getLogger(__name__)

CAN_LOG_NAME = "can.asc"


def can_log_name(arm: str | None = None) -> str:
    """The CAN log of an episode: ``can.asc`` for the one arm of a version 1 episode,
    ``can_<arm>.asc`` for a named arm."""
    return CAN_LOG_NAME if arm is None else f"can_{arm}.asc"


MAX_QUEUED = 3_040 * 60  # one minute of a PiPER's feedback; more means the disk cannot keep up
PREROLL = 3_040 * 2  # frames kept between episodes, so a log starts exactly at its episode's start


class CanLogSink(can.Listener):
    """Queues every CAN frame of the current episode for its log (see the module docstring).

    Attributes:
        received: frames queued since :meth:`open`.
        written: frames written to the file.
        dropped: frames lost because the queue was full (the writer fell a minute behind).
    """

    def __init__(self, max_queued: int = MAX_QUEUED, preroll: int = PREROLL) -> None:
        self.max_queued = max_queued
        self._queue: collections.deque[can.Message] = collections.deque()
        self._preroll: collections.deque[can.Message] = collections.deque(maxlen=preroll)
        self._lock = threading.Lock()
        self._writer: can.io.generic.MessageWriter | None = None
        self.path: Path | None = None
        self._sealed = False
        self.received = self.written = self.dropped = 0

    def open(self, path: str | Path, t0_wall: float) -> None:
        """Start the log of a new episode at ``path``; its time zero is ``t0_wall`` (epoch s)."""
        with self._lock:
            if self._writer is not None:
                raise RuntimeError(f"CAN log {self.path} is still open")
            self.path = Path(path)
            self._writer = can.Logger(self.path)
            self._sealed = False
            self._queue.clear()
            self.received = self.written = self.dropped = 0
            if isinstance(self._writer, can.ASCWriter):
                self._writer.log_event("manisplat episode start (time zero)", t0_wall)
            while self._preroll:  # frames received during the set-up, at or after time zero
                msg = self._preroll.popleft()
                if msg.timestamp >= t0_wall:
                    self._queue.append(msg)
                    self.received += 1

    def on_message_received(self, msg: can.Message) -> None:
        with self._lock:
            if self._writer is None or self._sealed:
                self._preroll.append(msg)
                return
            if len(self._queue) >= self.max_queued:
                self.dropped += 1
                if self.dropped == 1:
                    log.error("CAN log %s: the writer is a minute behind; dropping frames (counted)", self.path)
                return
            self._queue.append(msg)
            self.received += 1

    def seal(self) -> None:
        """Take no more frames into this episode's log (they go to the pre-roll of the next);
        what is queued is still written by :meth:`close`. ``received`` is final after this."""
        with self._lock:
            self._sealed = True

    @property
    def queued(self) -> int:
        return len(self._queue)

    def drain(self, flush: bool = True) -> int:
        """Write every queued frame (writer thread); returns how many. OSError propagates."""
        writer = self._writer
        if writer is None:
            return 0
        n = self._write_queued(writer)
        if flush:
            writer.file.flush()
        return n

    def _write_queued(self, writer: can.io.generic.MessageWriter) -> int:
        n = 0
        while True:
            try:
                msg = self._queue.popleft()
            except IndexError:
                break
            channel = can.util.channel2int(msg.channel) if msg.channel is not None else None
            if channel is None or not 0 <= channel < 255:  # e.g. a virtual channel name
                msg = copy.copy(msg)
                msg.channel = None
            writer.on_message_received(msg)
            n += 1
        self.written += n
        return n

    def close(self, sync: bool = True) -> None:
        """Write what is queued, close the file (fsynced with ``sync``)."""
        with self._lock:
            writer, self._writer = self._writer, None
        if writer is None:
            return
        try:
            self._write_queued(writer)
            writer.file.flush()
            if sync:
                os.fsync(writer.file.fileno())
        finally:
            writer.stop()
        if sync and self.path is not None:
            fsync_path(self.path.parent)

    def abandon(self) -> None:
        """Stop logging after a write error: close the file without writing more."""
        with self._lock:
            writer, self._writer = self._writer, None
        self._queue.clear()
        if writer is not None:
            try:
                writer.file.close()
            except OSError as exc:
                log.error("CAN log %s: closing after an error failed too: %s", self.path, exc)


def repair_can_log(path: str | Path, backup_dir: str | Path) -> int:
    """Cut a text CAN log torn by a crash back to its last whole line; returns the bytes cut
    (0 when it ends with a line break or is not a text log). The torn tail is kept in
    ``backup_dir/<name>.torn``."""
    path = Path(path)
    if path.suffix not in (".asc", ".log", ".csv", ".trc") or not path.is_file():
        return 0
    data = path.read_bytes()
    if not data or data.endswith(b"\n"):
        return 0
    cut = data.rfind(b"\n") + 1
    backup = Path(backup_dir)
    backup.mkdir(parents=True, exist_ok=True)
    (backup / (path.name + ".torn")).write_bytes(data[cut:])
    with open(path, "r+b") as f:
        f.truncate(cut)
        f.flush()
        os.fsync(f.fileno())
    log.info("%s: cut the torn last line (%d bytes, kept in %s)", path, len(data) - cut, backup)
    return len(data) - cut
