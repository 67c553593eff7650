"""What happened in one episode (``episode.json`` ``stats``): :class:`RigStats` per camera and
per arm, as every recording counts it, and :class:`EpisodeStats`, its flat version 1 view for
one arm and one camera."""

from __future__ import annotations

from dataclasses import dataclass, field

from manisplat.recorder.camfeed import CameraStats


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
    arms: dict[str | None, ArmStats] = field(default_factory=dict)  # None: the unnamed arm of version 1

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

    def count_frames(self, frames: int) -> None:
        """Set the frames written, the episode's and every camera's."""
        self.frames = frames
        for camera in self.cameras.values():
            camera.frames = frames


@dataclass
class EpisodeStats:
    """What happened in a version 1 episode: one arm, one camera (also ``episode.json`` ``stats``).

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

    @classmethod
    def of(cls, stats: RigStats) -> EpisodeStats:
        """The version 1 view of the statistics of a recording with one arm and one camera."""
        arm = next(iter(stats.arms.values()), ArmStats())
        camera = next(iter(stats.cameras.values()), CameraStats())
        return cls(frames=stats.frames, dropped_camera=camera.dropped_camera, dropped_queue=stats.dropped_queue,
                   stale=camera.stale, out_of_order=camera.out_of_order, flagged=stats.flagged,
                   flag_counts=arm.flag_counts, joint_samples=arm.joint_samples,
                   can_frames_logged=arm.can_frames_logged, can_frames_dropped=arm.can_frames_dropped,
                   duration_s=stats.duration_s, max_sync_gap_s=arm.max_sync_gap_s, camera_stalls=camera.stalls,
                   longest_camera_gap_s=camera.longest_gap_s, gripper_action_from_state=arm.gripper_action_from_state,
                   stop_reason=stats.stop_reason)
