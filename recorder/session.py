"""A recording session of one arm and one camera into version 1 episodes: the special case of
:class:`~.rig.RigRecorder` with one unnamed arm, one camera and the :class:`~.layout.VersionOne`
layout.

    >>> rec = Recorder(arm, camera, SystemClock(), RecorderConfig(latency_s=0.012))
    >>> rec.wait_for_arm()
    >>> result = rec.record_episode(Path("out/episode_0000"), duration=30.0)

Per episode (:meth:`~.rig.RigRecorder.record_episode`):
1. ``episode.json`` (``complete: false``, the clock mapping, the sync settings), ``frames.csv``
   and ``can.asc`` are created; a writer thread (:class:`~.writer.EpisodeSink`) takes over.
2. Every joint sample the arm completes (reader thread) is mapped onto the monotonic timeline
   (:class:`~.clock.ClockMap`), kept for sync (:class:`~.sync.JointHistory`) and queued for
   ``joints.csv``; every CAN frame goes to the CAN log; leader commands to :mod:`.actions`.
3. The camera is read on its own thread (:class:`~.camfeed.CameraFeed`, which counts its
   drops, stale and out-of-order frames and stalls). A frame's time is its stamp minus the
   camera latency (``latency_s``); it waits until a joint sample and a gripper frame after it
   have arrived (or ``max_wait_s`` has passed), then gets the joints interpolated from the joint
   samples and the gripper from the gripper's own frames (:mod:`.sync`, :mod:`.gripper`), the
   action, its flags, and goes to the writer queue (:mod:`.loop`; bounded: a full queue drops
   and counts the frame).
4. At the end (duration, stop event, a camera that ended, a write error) the pending frames are
   resolved, everything queued is written, the statistics (:class:`~.stats.EpisodeStats`) are
   added to ``episode.json`` and ``complete: true`` is written last. A write error instead
   leaves the episode incomplete with everything written before it
   (:class:`~.writer.StorageError`). An episode that ends before its first frame was written
   holds nothing to keep: its folder is removed (and said so).
"""

from __future__ import annotations

from typing import Any

from manisplat.drivers.base import Camera
from manisplat.drivers.piper import PiperArm
from manisplat.episode import CameraInfo, RobotInfo
from manisplat.recorder.clock import Clock
from manisplat.recorder.config import RecorderConfig
from manisplat.recorder.layout import VersionOne, opencv_dist
from manisplat.recorder.rig import RigArm, RigCamera, RigRecorder


class Recorder(RigRecorder):
    """Records version 1 episodes from ``arm`` and ``camera``; see the module docstring.

    Args:
        arm: a PiperArm (read-only is enough) on the bus.
        camera: any :class:`~manisplat.drivers.base.Camera`.
        clock: the host clocks (:class:`~.clock.SystemClock` outside tests).
        config: :class:`~.config.RecorderConfig` (its ``latency_s`` and ``depth`` are the camera's).
        camera_name: ``episode.json`` camera name.
        source_info: free-form description of the arm and camera for ``episode.json``.
        nominal_fps: the camera's configured rate (used when ``config.fps`` is None).
    """

    def __init__(self, arm: PiperArm, camera: Camera, clock: Clock, config: RecorderConfig | None = None, *,
                 camera_name: str = "ego", source_info: dict[str, Any] | None = None,
                 nominal_fps: float | None = None) -> None:
        config = config if config is not None else RecorderConfig()
        info = CameraInfo(name=camera_name, width=camera.width, height=camera.height, K=camera.K,
                          dist=opencv_dist(camera.dist), mount="base", T_mount_cam=None)
        super().__init__([RigArm(None, arm, RobotInfo())],
                         [RigCamera(camera_name, camera, info, latency_s=config.latency_s, depth=config.depth)],
                         clock, config, source_info=source_info, nominal_fps=nominal_fps, layout=VersionOne())
        self.feed = self.feeds[None]

    def wait_for_arm(self, timeout: float = 3.0) -> None:
        """Wait for complete joint samples of the arm (:meth:`.armfeed.ArmFeed.wait`; DriverError
        when none comes within ``timeout`` s), warning when its CAN stamps are not wall-clock."""
        self.wait_for_arms(timeout)
