"""Replays: a python-can log played onto a virtual bus (so :class:`PiperArm` runs unchanged on a
file), and a recorded episode as an :class:`~manisplat.drivers.base.Arm` (its joint stream) and a
:class:`~manisplat.drivers.base.Camera` (its frames), with the original timestamps.

    >>> player = CanLogPlayer("run.blf", realtime=False)
    >>> arm = PiperArm(player.open_bus(), read_only=True)   # open the receiving bus first
    >>> player.start(); player.wait(); arm.wait_for_frames(player.sent)

The log format follows the suffix through :class:`can.LogReader`: ``.blf``, ``.asc``, ``.log``
(candump -L), ``.csv``, ``.trc``, ``.db``, ``.mf4`` (with asammdf), each also ``.gz`` where
python-can allows it. Frames keep their recorded timestamps (the player's bus preserves them;
ASC logs start at 0.0) unless ``rewrite_timestamps`` stamps the send time instead.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from pathlib import Path

import can
import numpy as np

from manisplat.drivers.base import ArmHealth, CameraFrame, DriverError, JointState, SequenceTracker
from manisplat.episode import Episode, EpisodeFormatError

log = logging.getLogger(__name__)


class CanLogPlayer:
    """Plays a python-can log file onto the virtual bus ``channel``.

    Args:
        path: the log file (format by suffix).
        channel: virtual channel name (default: a fresh unique one).
        realtime: reproduce the recorded spacing (scaled by ``1 / speed``); False sends as fast
            as the receivers' queues take the frames.
        speed: playback speed factor for ``realtime``.
        rewrite_timestamps: stamp frames with the send time instead of the recorded one.
        max_gap_s: in ``realtime``, longer idle gaps in the log are cut to this (as
            :class:`can.MessageSync`'s ``skip``).

    Attributes:
        sent: frames sent so far.
        error: the exception that stopped playback early, if any.
    """

    def __init__(self, path: str | Path, *, channel: str | None = None, realtime: bool = True, speed: float = 1.0,
                 rewrite_timestamps: bool = False, max_gap_s: float = 60.0) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"CAN log {self.path} not found")
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        self.channel = channel if channel is not None else f"replay-{uuid.uuid4().hex}"
        self.realtime = realtime
        self.speed = float(speed)
        self.rewrite_timestamps = rewrite_timestamps
        self.max_gap_s = float(max_gap_s)
        self.sent = 0
        self.error: BaseException | None = None
        self._bus = can.Bus(interface="virtual", channel=self.channel, preserve_timestamps=not rewrite_timestamps)
        self._stop = threading.Event()
        self._done = threading.Event()
        self._thread: threading.Thread | None = None

    def open_bus(self, **kwargs: object) -> can.BusABC:
        """A receiving bus on the player's channel (open it before :meth:`start`)."""
        return can.Bus(interface="virtual", channel=self.channel, **kwargs)

    def start(self) -> CanLogPlayer:
        """Start playing on a background thread."""
        if self._thread is not None:
            raise RuntimeError("CanLogPlayer already started")
        self._thread = threading.Thread(target=self._run, name=f"CanLogPlayer-{self.path.name}", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        try:
            with can.LogReader(self.path) as reader:
                self._play(reader)
        except Exception as exc:  # a broken file: keep what was sent, report why it stopped
            self.error = exc
            log.error("CanLogPlayer: %s: playback stopped after %d frames: %s", self.path, self.sent, exc)
        finally:
            self._done.set()

    def _play(self, reader: can.LogReader) -> None:
        start_wall = None
        t_log0 = 0.0
        skipped = 0.0
        previous = None
        for msg in reader:
            if self._stop.is_set():
                return
            if self.realtime:
                if start_wall is None:
                    start_wall, t_log0 = time.perf_counter(), msg.timestamp
                elif previous is not None and msg.timestamp - previous > self.max_gap_s:
                    skipped += msg.timestamp - previous - self.max_gap_s
                previous = msg.timestamp
                due = start_wall + (msg.timestamp - t_log0 - skipped) / self.speed
                delay = due - time.perf_counter()
                if delay > 0 and self._stop.wait(delay):
                    return
            if self.rewrite_timestamps:
                msg.timestamp = time.time()
            self._bus.send(msg)
            self.sent += 1

    @property
    def done(self) -> bool:
        """Whether playback has finished (end of file, error or stop)."""
        return self._done.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the end of playback; False on timeout."""
        return self._done.wait(timeout)

    def stop(self) -> None:
        """Stop playing and close the player's bus."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._bus.shutdown()

    def __enter__(self) -> CanLogPlayer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class EpisodeArm:
    """An episode's joint stream (``joints.csv``, else ``frames.csv``) as an
    :class:`~manisplat.drivers.base.Arm`, with its original timestamps.

    With ``realtime`` the sample of the episode time elapsed since the first call is current;
    otherwise every :meth:`wait_for_joint_state` advances to the next sample at once.
    """

    def __init__(self, episode: Episode | str | Path, *, realtime: bool = False) -> None:
        self.episode = episode if isinstance(episode, Episode) else Episode.open(episode)
        table = self.episode.joints()
        source = table if table is not None and len(table) else self.episode.frames
        self.t = source.t
        self.q = source.q
        self.gripper = source.gripper
        self.realtime = realtime
        self._next = 0  # index of the next sample (as-fast-as-possible mode)
        self._start: float | None = None
        self._closed = False

    def __len__(self) -> int:
        return len(self.t)

    def _state(self, i: int) -> JointState:
        return JointState(t=float(self.t[i]), q=self.q[i].copy(), gripper=float(self.gripper[i]), seq=i,
                          t_host=time.monotonic())

    def _current(self) -> int:
        if not self.realtime:
            return self._next - 1
        if self._start is None:
            self._start = time.monotonic()
        elapsed = time.monotonic() - self._start
        return int(np.searchsorted(self.t - self.t[0], elapsed, side="right")) - 1

    def joint_state(self) -> JointState | None:
        i = self._current()
        return self._state(i) if i >= 0 else None

    def wait_for_joint_state(self, after_seq: int = -1, timeout: float = 1.0) -> JointState:
        if self._closed:
            raise DriverError("EpisodeArm is closed")
        want = after_seq + 1
        if want >= len(self):
            raise TimeoutError(f"{self.episode.path}: the episode has {len(self)} joint samples")
        if not self.realtime:
            self._next = max(self._next, want + 1)
            return self._state(self._next - 1)
        if self._start is None:
            self._start = time.monotonic()
        due = self._start + (self.t[want] - self.t[0])
        if due - time.monotonic() > timeout:
            time.sleep(timeout)
            raise TimeoutError(f"sample {want} is due in more than {timeout} s")
        time.sleep(max(0.0, due - time.monotonic()))
        return self._state(max(want, self._current()))

    def health(self) -> ArmHealth:
        if self._current() >= len(self) - 1:
            return ArmHealth("ended", f"{self.episode.path}: all {len(self)} joint samples read", 0.0)
        return ArmHealth("ok", "", 0.0)

    def close(self) -> None:
        self._closed = True

    def __enter__(self) -> EpisodeArm:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class EpisodeCamera:
    """One camera of an episode (docs/episode-format.md) as a :class:`~manisplat.drivers.base.Camera`:
    RGB, depth when present, the camera's frame times (its ``<camera>.t`` column, else ``t``: the
    episode's monotonic clock, mid-exposure where the recorder knew it), ``seq`` from the
    ``<camera>.seq`` or ``seq`` column when present (else the frame index) and drops from its
    gaps. ``camera`` names it (None: the episode's one camera; several are refused naming them).
    ``realtime`` paces frames at their recorded spacing; otherwise as fast as read."""

    def __init__(self, episode: Episode | str | Path, *, camera: str | None = None, realtime: bool = False) -> None:
        self.episode = episode if isinstance(episode, Episode) else Episode.open(episode)
        cam = self.episode.camera if camera is None else self.episode.cameras.get(camera)
        if cam is None:
            raise EpisodeFormatError(f"{self.episode.path}: no camera {camera!r}; cameras: "
                                     f"{', '.join(self.episode.cameras)}")
        self.camera = camera
        self.width, self.height, self.K, self.dist = cam.width, cam.height, cam.K.copy(), cam.dist.copy()
        self.chroma_subsampling = self.episode.chroma_subsampling(camera)
        self.realtime = realtime
        self.tracker = SequenceTracker()
        self._index = 0
        self._start: float | None = None
        self._t = self.episode.camera_times(camera)
        columns = self.episode.arm_frames(next(iter(self.episode.arms))).extra  # the columns no arm owns
        seq = columns.get(f"{camera}.seq", columns.get("seq"))
        self._seq = seq.astype(np.int64) if seq is not None else np.arange(len(self.episode), dtype=np.int64)

    def __len__(self) -> int:
        return len(self.episode)

    def read(self, timeout: float | None = 1.0) -> CameraFrame | None:
        i = self._index
        if i >= len(self.episode):
            return None
        t = self._t
        if self.realtime:
            if self._start is None:
                self._start = time.monotonic()
            delay = self._start + (t[i] - t[0]) - time.monotonic()
            if timeout is not None and delay > timeout:
                time.sleep(timeout)
                raise TimeoutError(f"frame {i} is due in more than {timeout} s")
            time.sleep(max(0.0, delay))
        rgb, depth = self.episode.rgb(i, self.camera), self.episode.depth(i, self.camera)
        self._index += 1
        seq = int(self._seq[i])
        return CameraFrame(seq=seq, t=float(t[i]), rgb=rgb, depth=depth, exposure_s=None,
                           dropped=self.tracker.update(seq), t_host=time.monotonic())

    def close(self) -> None:
        self._index = len(self.episode)

    def __enter__(self) -> EpisodeCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
