"""The small interfaces a recorder talks to: an :class:`Arm` gives joint states, a
:class:`Camera` gives frames. Hardware drivers, log replays and simulations all implement them,
so the recorder never knows which one it has.

Clocks: ``t`` is the source's own timestamp (for a CAN arm the bus timestamp python-can gives:
wall clock on socketcan/virtual/slcan; for depthai the host steady clock; for a replay the
recorded time). ``t_host`` is ``time.monotonic()`` when the value became available on this host,
the clock a recorder can always compare across devices.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from manisplat.episode.images import StoredChroma


class DriverError(RuntimeError):
    """A device, bus or replay problem (no device, closed bus, timeout waiting for feedback)."""


@dataclass(frozen=True)
class JointState:
    """One complete joint sample of a 6-joint arm.

    Attributes:
        t: source timestamp, s (see the module docstring).
        q: (6,) float64 joint angles, rad.
        gripper: finger-pad gap, m (nan when the source has none yet).
        effort: (6,) float64 joint torques, N*m (nan where unknown).
        seq: 0, 1, 2, ... in the order samples were produced by this arm object.
        t_host: ``time.monotonic()`` when the sample became available, s.
    """

    t: float
    q: np.ndarray
    gripper: float = float("nan")
    effort: np.ndarray = field(default_factory=lambda: np.full(6, np.nan))
    seq: int = 0
    t_host: float = float("nan")


@dataclass(frozen=True)
class ArmHealth:
    """Whether an arm's data is flowing.

    Attributes:
        state: ``"ok"``, ``"waiting"`` (nothing received yet), ``"silent"`` (nothing for longer
            than the timeout), ``"bus_off"``, ``"error_passive"``, ``"read_error"`` or ``"ended"``
            (a replay ran out).
        detail: a sentence for a log or a user.
        silent_for_s: seconds since the last valid frame (inf before the first one).
    """

    state: str
    detail: str = ""
    silent_for_s: float = float("inf")

    @property
    def ok(self) -> bool:
        return self.state == "ok"


@runtime_checkable
class Arm(Protocol):
    """What a recorder needs from an arm."""

    def joint_state(self) -> JointState | None:
        """The latest complete joint sample, or None before the first."""

    def wait_for_joint_state(self, after_seq: int = -1, timeout: float = 1.0) -> JointState:
        """The first sample with ``seq > after_seq``; :class:`TimeoutError` after ``timeout`` s."""

    def health(self) -> ArmHealth:
        """Whether data is flowing."""

    def close(self) -> None:
        """Stop reading and leave the device safe."""


@dataclass(frozen=True)
class CameraFrame:
    """One camera frame.

    Attributes:
        seq: the source's sequence number (depthai per-stream counter; frame index in a replay).
        t: timestamp, s: host steady clock (= ``time.monotonic()`` on Linux) at the middle of
            the exposure when the exposure time is known, else as the source stamps it.
        rgb: (H, W, 3) uint8 RGB.
        depth: (H, W) float32 z-depth in metres aligned to ``rgb`` (0 = invalid), or None.
        exposure_s: exposure time, s (None when unknown).
        dropped: frames missing just before this one, from gaps in ``seq``.
        t_host: ``time.monotonic()`` when the frame reached this process, s.
    """

    seq: int
    t: float
    rgb: np.ndarray
    depth: np.ndarray | None = None
    exposure_s: float | None = None
    dropped: int = 0
    t_host: float = float("nan")


@runtime_checkable
class Camera(Protocol):
    """What a recorder needs from a camera. ``K`` is the (3, 3) float64 pinhole matrix at the
    output size ``width`` x ``height``; ``dist`` the OpenCV distortion coefficients;
    ``chroma_subsampling`` how the source kept the frames' colour before they reached the host
    (a video's 4:2:0, an episode's; None where it is not known), which PNG files would lose."""

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    chroma_subsampling: StoredChroma | None

    def read(self, timeout: float | None = 1.0) -> CameraFrame | None:
        """The next frame; None at the end of a finite source; :class:`TimeoutError` when no
        frame comes within ``timeout`` s (None waits forever)."""

    def close(self) -> None:
        """Stop the device or replay."""


class SequenceTracker:
    """Drop detection from sequence numbers: :meth:`update` returns how many were skipped."""

    def __init__(self) -> None:
        self.last: int | None = None
        self.dropped = 0
        self.frames = 0

    def update(self, seq: int) -> int:
        """Frames missing between the previous ``seq`` and this one (0 for the first; a
        sequence that goes backwards, e.g. a device restart, counts no drops and restarts)."""
        gap = 0 if self.last is None or seq <= self.last else seq - self.last - 1
        self.last = seq
        self.dropped += gap
        self.frames += 1
        return gap
