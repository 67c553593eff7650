"""One camera's side of a recording with several cameras: a reader thread per camera and episode,
the camera's own drop accounting, and the frames waiting to be matched into a written frame.

A :class:`CameraFeed` reads its camera on its own thread (so one slow or silent camera never
holds the others up), corrects each stamp by the camera's latency (frame time = stamp -
``latency_s``, monotonic s) and keeps the frames in time order for the recorder to match
(:mod:`.rig`). It counts, per episode, what :class:`CameraStats` lists.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
from dataclasses import dataclass

from manisplat.drivers.base import Camera, CameraFrame, DriverError
from manisplat.recorder.clock import Clock

log = logging.getLogger(__name__)


@dataclass
class CameraStats:
    """What one camera did in one episode (``episode.json`` ``stats.cameras.<camera>``).

    Counts of frames: ``frames`` written; ``dropped_camera`` missing in the camera's sequence
    numbers; ``stale`` read after the start but exposed before it; ``out_of_order`` with a time
    not after the previous frame's; ``unmatched`` frames of the reference camera not written
    because this camera had no frame within the allowed skew; ``unused`` frames of this camera
    that no written frame took (a faster camera, or its partner frame was lost). ``stalls``:
    silences longer than the stall limit; ``longest_gap_s`` between two frames;
    ``max_skew_s`` the largest distance of a written image from its frame's time.
    """

    frames: int = 0
    dropped_camera: int = 0
    stale: int = 0
    out_of_order: int = 0
    unmatched: int = 0
    unused: int = 0
    stalls: int = 0
    longest_gap_s: float = 0.0
    max_skew_s: float = 0.0


class CameraFeed:
    """Reads one camera on a thread during an episode; see the module docstring.

    Args:
        name: the camera's name.
        camera: the camera.
        clock: the host clocks.
        latency_s: the camera's latency, s (a frame's time is its stamp minus this).
        depth: record the camera's depth (DriverError on a frame without it).
        poll_s: the thread waits at most this long for a frame before it checks for a stop, s.
        stall_after_s: a camera silent for longer counts as stalled, s.
    """

    def __init__(self, name: str, camera: Camera, clock: Clock, *, latency_s: float, depth: bool,
                 poll_s: float = 0.05, stall_after_s: float = 0.5) -> None:
        self.name = name
        self.camera = camera
        self.clock = clock
        self.latency_s = float(latency_s)
        self.depth = depth
        self.poll_s = poll_s
        self.stall_after_s = stall_after_s
        self.stats = CameraStats()
        self.error: str | None = None
        self.ended = False
        self.last_frame_host = clock.monotonic()
        self._frames: collections.deque[tuple[float, CameraFrame]] = collections.deque()
        self._lock = threading.Lock()
        self._t0 = math.inf
        self._last_t = -math.inf
        self._stalled = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- the episode --------------------------------------------------------------------------

    def start(self, t0: float) -> None:
        """Start reading for an episode that starts at ``t0`` (monotonic s)."""
        self.stats = CameraStats()
        self._frames.clear()
        self._t0, self._last_t = t0, -math.inf
        self.last_frame_host = self.clock.monotonic()
        self._stalled = False
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"camera-{self.name}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop reading (the frames read stay available)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(self.poll_s + 5.0)
            self._thread = None

    @property
    def done(self) -> bool:
        """The camera ended or failed: no further frame will come."""
        return self.ended or self.error is not None

    def caught_up(self, t: float) -> bool:
        """Whether every frame exposed before ``t`` (monotonic s) has been read: one at or after
        ``t`` has come, or the camera is done."""
        return self.done or self._last_t >= t

    def silent_s(self) -> float:
        """Seconds since the last frame (or the start)."""
        return self.clock.monotonic() - self.last_frame_host

    # -- the reader thread --------------------------------------------------------------------

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                frame = self.camera.read(timeout=self.poll_s)
                if frame is None:
                    self.ended = True
                    return
                self._accept(frame)
            except TimeoutError:
                pass
            except DriverError as exc:
                self.error = f"camera {self.name} failed: {exc}"
                log.error("%s", self.error)
                return
            self._count_stall(self.silent_s())

    def _count_stall(self, silent: float) -> None:
        """Count a silence of ``silent`` s as a stall once, when it is longer than the limit."""
        if silent > self.stall_after_s and not self._stalled:
            self._stalled = True
            self.stats.stalls += 1
            log.warning("camera %s has sent no frame for %.2f s", self.name, silent)

    def _accept(self, frame: CameraFrame) -> None:
        stats = self.stats
        now = self.clock.monotonic()
        self._count_stall(now - self.last_frame_host)  # a silence that a read returning only after it hid
        if self._stalled:
            self._stalled = False
            log.info("camera %s sends frames again after %.2f s", self.name, now - self.last_frame_host)
        self.last_frame_host = now
        if self.depth and frame.depth is None:
            raise DriverError("depth was asked for but the camera gives frames without depth")
        t = frame.t - self.latency_s
        if t < self._t0:
            stats.stale += 1
            return
        stats.dropped_camera += frame.dropped if self._last_t > -math.inf else 0
        if t <= self._last_t:
            stats.out_of_order += 1
            log.warning("camera %s: frame %d at t=%.6f is not after the previous one (%.6f); dropped", self.name,
                        frame.seq, t, self._last_t)
            return
        if self._last_t > -math.inf:
            stats.longest_gap_s = max(stats.longest_gap_s, t - self._last_t)
        self._last_t = t
        with self._lock:
            self._frames.append((t, frame))

    # -- matching (the recorder's thread) -----------------------------------------------------

    def oldest(self) -> tuple[float, CameraFrame] | None:
        """The oldest frame waiting, or None."""
        with self._lock:
            return self._frames[0] if self._frames else None

    def pop_oldest(self) -> tuple[float, CameraFrame]:
        with self._lock:
            return self._frames.popleft()

    def find(self, t: float, max_skew_s: float, *, decide: bool) -> tuple[bool, int | None]:
        """Where the frame nearest to ``t`` (monotonic s) within ``max_skew_s`` waits: ``(decided, index)``.

        Frames older than ``t - max_skew_s`` can no longer be taken (frame times only grow) and
        are counted ``unused``. Decided once a frame at or after ``t`` has arrived (frames come in
        time order), when the camera is done, or with ``decide``; undecided, ``index`` is None;
        decided without a frame near enough, too."""
        with self._lock:
            while self._frames and self._frames[0][0] < t - max_skew_s:
                self._frames.popleft()
                self.stats.unused += 1
            if not (decide or self.done or any(ft >= t for ft, _ in self._frames)):
                return False, None
            near = [k for k, (ft, _) in enumerate(self._frames) if abs(ft - t) <= max_skew_s]
            if not near:
                return True, None
            return True, min(near, key=lambda k: abs(self._frames[k][0] - t))

    def take(self, index: int, t: float) -> tuple[float, CameraFrame]:
        """Take the frame :meth:`find` found for the frame at ``t``; the ones before it are counted ``unused``."""
        with self._lock:
            for _ in range(index):
                self._frames.popleft()
                self.stats.unused += 1
            taken = self._frames.popleft()
        self.stats.max_skew_s = max(self.stats.max_skew_s, abs(taken[0] - t))
        return taken

    def drop_waiting(self) -> None:
        """At the end of the episode: count the frames no written frame took as ``unused``."""
        with self._lock:
            self.stats.unused += len(self._frames)
            self._frames.clear()
