"""A recorded camera stream replayed live: frames come at their recorded spacing on a
:class:`~.clock.Clock` and are re-stamped on that clock's monotonic timeline, as a live camera's
would be. The recorder then cannot tell it from an OAK.

Timing model (all s): the frame recorded at ``t_src`` is exposed at
``t_exp = t_start + (t_src - t_src0) - delivery_delay_s`` and reaches the host at
``t_exp + delivery_delay_s`` (``t_start``: the clock when the first frame was asked for). It is
stamped ``t_exp + stamp_latency_s``: 0 for a camera that stamps the middle of the exposure
exactly (depthai), something else to play a camera whose stamps are late by a latency the
recorder must correct (``--latency-ms``). With ``loop`` the stream repeats with its own period.

Several replayed cameras of one rig share a :class:`ReplayEpoch`: ``t_start`` is then the clock
when the first of them asked for a frame, whichever reader thread starts first, so a camera whose
thread starts late on a loaded machine is not shifted against the others (and the frames of one
recording keep their recorded offsets: ``t_src0`` is that recording's first frame delivered).
"""

from __future__ import annotations

import collections
import logging
import math
import threading
from pathlib import Path
from typing import Callable, Hashable

import numpy as np

from manisplat.drivers.base import Camera, CameraFrame, DriverError, SequenceTracker
from manisplat.recorder.clock import Clock, RealDeadline

log = logging.getLogger(__name__)

MAX_PRELOAD_BYTES = 4 << 30


class ReplayEpoch:
    """The start shared by several replayed streams (module docstring): the clock time ``t_start``
    (s) fixed by the first stream to ask for a frame, and per source timeline (a recording) the
    source time ``t_src0`` (s) of the first frame asked for on it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._t_start: float | None = None
        self._t_src0: dict[Hashable, float] = {}

    def fix(self, timeline: Hashable, t_src: float, t_start: float) -> tuple[float, float]:
        """``(t_src0, t_start)`` for a stream on ``timeline`` whose first frame, at source time
        ``t_src``, would start at clock time ``t_start`` on its own; the first call fixes them."""
        with self._lock:
            if self._t_start is None:
                self._t_start = t_start
            return self._t_src0.setdefault(timeline, t_src), self._t_start


class ReplayCamera:
    """A finite :class:`~manisplat.drivers.base.Camera` replayed live on ``clock``.

    Args:
        open_source: makes a fresh source camera (called again for each loop), e.g.
            ``lambda: EpisodeCamera(path)``; its frames' ``t`` and ``seq`` are the recorded ones.
        clock: the clock frames are paced and stamped on.
        loop: repeat the stream forever.
        fps: keep only frames at most this often (None: all).
        preload: read every source frame into memory first (a benchmark measures the recorder,
            not the decoding of the replay's files).
        delivery_delay_s: exposure-to-host delay, s; stamp_latency_s: stamp minus true
            mid-exposure time, s (module docstring).
        stop: an event that makes a waiting :meth:`read` return None.
        epoch: the start shared with the rig's other replayed cameras (None: its own);
        timeline: which recording's timeline its source times are on, within ``epoch``.

    ``has_depth`` says whether the stream's frames carry depth (its first frame is read at once).
    """

    def __init__(self, open_source: Callable[[], Camera], clock: Clock, *, loop: bool = False, fps: float | None = None,
                 preload: bool = False, delivery_delay_s: float = 0.03, stamp_latency_s: float = 0.0,
                 stop: threading.Event | None = None, epoch: ReplayEpoch | None = None,
                 timeline: Hashable = None) -> None:
        if fps is not None and not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        self._open = open_source
        self.clock = clock
        self.loop = loop
        self.delivery_delay_s = float(delivery_delay_s)
        self.stamp_latency_s = float(stamp_latency_s)
        self.stop = stop if stop is not None else threading.Event()
        self.epoch, self.timeline = epoch, timeline
        self._source = open_source()
        self.width, self.height = self._source.width, self._source.height
        self.K = np.asarray(self._source.K, dtype=np.float64)
        self.dist = np.asarray(self._source.dist, dtype=np.float64)
        self.chroma_subsampling = self._source.chroma_subsampling
        self._frames: list[CameraFrame] | None = None
        self._first: CameraFrame | None = None  # read ahead to tell whether the stream has depth
        if preload:
            self._frames = self._read_all()
            if not self._frames:
                raise DriverError("the replayed camera stream holds no frames")
            first = self._frames[0]
        else:
            try:
                first = self._first = self._source.read(timeout=10.0)
            except TimeoutError:
                self._source.close()
                raise DriverError("the replayed camera stream sent no frame within 10 s") from None
        self.has_depth = first is not None and first.depth is not None
        self._pending: CameraFrame | None = None
        self._t_src0: float | None = None
        self._t_start: float | None = None
        self._period: float | None = None  # one loop's length, s
        self._laps = 0
        self._index = 0
        self._seq_per_lap = 0
        self._max_seq = 0
        self._last_src_t = -math.inf
        self._next_keep = -math.inf
        self._min_interval = 0.0 if fps is None else 1.0 / fps
        self.nominal_fps = fps
        self.tracker = SequenceTracker()
        self.consumed_until: float = clock.monotonic()  # every frame due before this was read
        self.exposures: collections.deque[tuple[int, float]] = collections.deque(maxlen=100_000)
        self.max_late_s = 0.0  # the most a frame was read after it was due (the reader fell behind)
        self.delivered = 0

    def _read_all(self) -> list[CameraFrame]:
        frames, size = [], 0
        while (f := self._source.read(timeout=10.0)) is not None:
            frames.append(f)
            size += f.rgb.nbytes + (f.depth.nbytes if f.depth is not None else 0)
            if size > MAX_PRELOAD_BYTES:
                raise DriverError(f"the replayed stream needs more than {MAX_PRELOAD_BYTES >> 30} GiB in memory")
        return frames

    def _next_source_frame(self) -> CameraFrame | None:
        """The next recorded frame, starting the next lap when looping; None at the end."""
        if self._frames is not None:
            if self._index >= len(self._frames):
                if not self.loop:
                    return None
                self._new_lap()
            f = self._frames[self._index]
            self._index += 1
            return f
        if self._first is not None:
            f, self._first = self._first, None
        else:
            f = self._source.read(timeout=10.0)
        if f is None and self.loop and self._index > 0:
            self._source.close()
            self._source = self._open()
            self._new_lap()
            f = self._source.read(timeout=10.0)
        if f is not None:
            self._index += 1
        return f

    def _new_lap(self) -> None:
        if self._period is None:
            self._period = self._last_src_t - self._t_src0 + (self._min_interval or self._mean_interval())
            self._seq_per_lap = self._max_seq + 1
        self._laps += 1
        self._index = 0

    def _mean_interval(self) -> float:
        if self._frames is not None and len(self._frames) > 1:
            return (self._frames[-1].t - self._frames[0].t) / (len(self._frames) - 1)
        return 1.0 / 30.0

    def read(self, timeout: float | None = 1.0) -> CameraFrame | None:
        """The next frame once it is due on the clock; None at the end of a non-looping stream
        (or when ``stop`` is set); TimeoutError when it is not due within ``timeout`` (real) s."""
        if self._pending is None:
            self._pending = self._take()
            if self._pending is None:
                return None
        f = self._pending
        due = self._due(f)
        self.consumed_until = max(self.consumed_until, due)  # a lock-step simulator may run up to here
        stop = self.stop if timeout is None else RealDeadline(timeout, self.stop)
        reached = self.clock.sleep_until(due, stop)
        if self.stop.is_set():
            return None
        if not reached:
            raise TimeoutError(f"replayed frame {f.seq} is not due within {timeout} s")
        self._pending = None
        self.delivered += 1
        self.max_late_s = max(self.max_late_s, self.clock.monotonic() - due)
        t_exp = due - self.delivery_delay_s
        self.exposures.append((f.seq, t_exp))  # the truth a test compares with
        return CameraFrame(seq=f.seq, t=t_exp + self.stamp_latency_s, rgb=f.rgb, depth=f.depth, exposure_s=None,
                           dropped=self.tracker.update(f.seq), t_host=self.clock.monotonic())

    def _take(self) -> CameraFrame | None:
        """The next source frame to deliver (decimated to ``fps``), with its seq and time
        shifted by the laps done; its ``t`` is still on the source's timeline."""
        while True:
            f = self._next_source_frame()
            if f is None:
                return None
            if self._t_src0 is None:
                t_start = self.clock.monotonic() + self.delivery_delay_s
                self._t_src0, self._t_start = (f.t, t_start) if self.epoch is None else \
                    self.epoch.fix(self.timeline, f.t, t_start)
                self._max_seq = f.seq
            if self._laps == 0:
                self._last_src_t = f.t
                self._max_seq = max(self._max_seq, f.seq)
            t = f.t + self._laps * (self._period or 0.0)
            if t + 1e-9 < self._next_keep:
                continue
            self._next_keep = max(self._next_keep + self._min_interval, t) if self._min_interval else t
            return CameraFrame(seq=f.seq + self._laps * self._seq_per_lap, t=t, rgb=f.rgb, depth=f.depth)

    def _due(self, f: CameraFrame) -> float:
        return self._t_start + (f.t - self._t_src0)

    def close(self) -> None:
        self.stop.set()
        self._source.close()

    def __enter__(self) -> ReplayCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ReplayInputError(DriverError):
    """A ``--camera replay:PATH`` that is not a recording the recorder can replay, or options that do
    not fit it: bad input (exit 2), not a device that cannot be reached."""


def open_replay_source(path: str | Path, camera: str | None = None) -> Callable[[], Camera]:
    """A factory of the source camera a ``--camera replay:PATH`` names: an episode folder
    (:class:`~manisplat.drivers.replay.EpisodeCamera`: its one camera, or of an episode with
    several the one named ``camera``) or a depthai recording ``.mkv``/``.avi``/``.mp4`` with its
    ``.mcap`` beside it and a ``calibration.json`` (depthai format) or ``K.json``
    (``{"K": 3x3, "dist": [...]}``) in the same folder."""
    from manisplat.drivers.replay import EpisodeCamera
    from manisplat.episode import Episode, EpisodeFormatError

    path = Path(path)
    if path.is_dir():
        if not (path / "episode.json").is_file():
            raise ReplayInputError(f"replay camera: {path} is a folder without episode.json (not an episode)")
        try:
            names = list(Episode.open(path).cameras)
        except EpisodeFormatError as exc:
            raise ReplayInputError(f"replay camera: {exc}") from None
        pick = camera if camera in names else names[0] if len(names) == 1 else None
        if pick is None:
            raise ReplayInputError(f"replay camera: {path} has the cameras {', '.join(names)}; a recorded camera "
                                   f"named like one of them replays it (--camera {names[0]}=replay:{path})")
        return lambda: EpisodeCamera(path, camera=pick)
    if path.suffix in (".mkv", ".avi", ".mp4"):
        import json

        from manisplat.drivers.oak import DepthaiReplayCamera

        calib = path.parent / "calibration.json"
        kfile = path.parent / "K.json"
        if calib.is_file():
            return lambda: DepthaiReplayCamera(path, calibration=calib)
        if kfile.is_file():
            raw = json.loads(kfile.read_text())
            return lambda: DepthaiReplayCamera(path, K=np.asarray(raw["K"]), dist=np.asarray(raw.get("dist", [])))
        raise ReplayInputError(f"replay camera: {path} needs intrinsics: put calibration.json (depthai) or K.json "
                          f"beside it")
    raise ReplayInputError(f"replay camera: {path} is neither an episode folder nor a depthai recording (.mkv/.avi/.mp4)")
