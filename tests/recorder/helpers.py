"""Test doubles built from the real pieces: a source episode for the replayed camera, and a
lock-step rig (simulated PiPER on a virtual bus, PiperArm, replayed camera, Recorder) on a
ManualClock, so results never depend on the machine's speed."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from manisplat.drivers.piper import PiperArm
from manisplat.drivers.replay import EpisodeCamera
from manisplat.episode import CameraInfo, EpisodeWriter, RobotInfo
from manisplat.recorder.clock import ManualClock
from manisplat.recorder.replaycam import ReplayCamera
from manisplat.recorder.session import Recorder, RecorderConfig
from manisplat.recorder.simrig import SimRig

W, H, FPS = 64, 48, 30.0
K = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])


def source_frame(i: int, camera: int = 0) -> np.ndarray:
    """The rgb image of source frame ``i`` of source ``camera`` (deterministic noise)."""
    return np.random.default_rng(i if camera == 0 else (camera, i)).integers(0, 256, (H, W, 3), dtype=np.uint8)


def write_source(path: Path, frames: int = 60, *, missing: range | None = None, depth: bool = False,
                 camera: int = 0) -> Path:
    """A camera recording as an episode folder: ``frames`` frames at 30 fps with a ``seq``
    column, the images of source ``camera``; frames in ``missing`` are left out (a camera stall:
    their time and seq are skipped)."""
    missing = missing or range(0)
    with EpisodeWriter(path, CameraInfo("src", W, H, K), RobotInfo(), FPS, extra_frame_columns=("seq",),
                       depth_scale=0.001 if depth else None) as writer:
        for i in range(frames):
            if i in missing:
                continue
            d = np.full((H, W), 1.0 + i * 1e-3, np.float32) if depth else None
            writer.add_frame(i / FPS, np.zeros(6), 0.0, source_frame(i, camera), depth=d, extra={"seq": float(i)})
    return path


@dataclass
class Rig:
    clock: ManualClock
    rig: SimRig
    arm: PiperArm
    camera: ReplayCamera
    recorder: Recorder

    def close(self) -> None:
        self.camera.close()
        self.rig.stop()
        self.arm.close()


def lockstep_rig(source: Path, *, motion: str = "wave", stamp_latency_s: float = 0.0, loop: bool = True,
                 **config: Any) -> Rig:
    """Everything wired on a ManualClock (see the module docstring); ``config`` -> RecorderConfig."""
    clock = ManualClock()
    rig = SimRig(clock, motion=motion)
    arm = PiperArm(rig.open_bus(), read_only=True, own_bus=True)
    rig.add_consumer(lambda n: arm.wait_for_frames(n, timeout=30.0))
    camera = ReplayCamera(lambda: EpisodeCamera(source), clock, loop=loop, stamp_latency_s=stamp_latency_s)
    rig.follow(lambda: camera.consumed_until)
    options = {"queue_frames": 10_000, **config}
    # the recorder listens before the rig starts: the rig stops max_lead_s ahead of the camera,
    # which nobody reads before recording, so samples sent before a later listener would be all
    # wait_for_arm could wait for (a deadlock on a loaded machine)
    recorder = Recorder(arm, camera, clock, RecorderConfig(**options), nominal_fps=FPS)
    rig.start()
    recorder.wait_for_arm(timeout=30.0)
    return Rig(clock, rig, arm, camera, recorder)
