"""The settings of a recording (the CLI flags), shared by every recorder."""

from __future__ import annotations

import math
from dataclasses import dataclass

DEPTH_SCALE = 0.001  # metres per depth unit: millimetres, the OAK's own unit


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
        flush_grace_s: at the end, a lagging camera thread gets ``max_wait_s`` on the recording's
            clock and at most this much more real time to deliver its last frames, s.
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
    flush_grace_s: float = 1.0

    def __post_init__(self) -> None:
        if self.actions not in ("auto", "on", "off"):
            raise ValueError(f"actions must be auto, on or off; got {self.actions!r}")
        if self.image_format not in ("png", "jpg"):
            raise ValueError(f"image_format must be png or jpg; got {self.image_format!r}")
        for name in ("max_gap_s", "max_wait_s", "camera_poll_s", "stall_after_s", "max_action_age_s",
                     "flush_grace_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.max_skew_s is not None and not self.max_skew_s > 0:
            raise ValueError(f"max_skew_s must be > 0, got {self.max_skew_s}")
        if self.fps is not None and not self.fps > 0:
            raise ValueError(f"fps must be > 0, got {self.fps}")
        if not math.isfinite(self.latency_s) or abs(self.latency_s) > 1.0:
            raise ValueError(f"latency_s must be within +-1 s, got {self.latency_s}")
