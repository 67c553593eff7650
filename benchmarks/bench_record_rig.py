"""Two-arm recording: two simulated PiPERs on two virtual buses + three 30 fps 640x480 replayed cameras, in real time.

The real recorder with named arms and cameras (:class:`~manisplat.recorder.rig.RigRecorder`:
a PiperArm reader per bus, a camera thread per camera, the matching, the writer thread with PNG
images, ``joints_<arm>.csv``, ``can_<arm>.asc``) writes a version 2 episode to disk; only the
hardware is simulated: two ``SimRig`` s (``wave``, 200 Hz cycles of 15-16 frames each) and three
``ReplayCamera`` s looping 60 preloaded 640x480 frames (``record_soak``'s source), stamped 0, 10
and 20 ms late and corrected by each camera's latency. ``MANISPLAT_RIG_SECONDS`` (default 60,
--quick 15) sets the length, ``MANISPLAT_RIG_FORMAT`` (png or jpg) the image format. The episode
is deleted afterwards.

Reported: frames written / expected; per camera its drops, frames without a partner image
(unmatched), images no frame took (unused), the largest skew from the frame time and the error of
its ``<camera>.t`` against its true exposure time; per arm the synced joints against the true
state at the true exposure time of the frame (the analytic wave), flagged frames, joint samples
and CAN frames per s; CPU seconds per second of recording (all, and the simulators' own threads);
the load average of the machine.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks._harness import BenchContext
from benchmarks.bench_record_soak import FPS, make_source, thread_cpu_s
from manisplat.drivers.piper import PiperArm
from manisplat.drivers.replay import EpisodeCamera
from manisplat.episode import Episode, validate
from manisplat.episode.infos import ArmInfo, CameraInfo
from manisplat.recorder.clock import SystemClock
from manisplat.recorder.replaycam import ReplayCamera, ReplayEpoch
from manisplat.recorder.rig import RigArm, RigCamera, RigRecorder
from manisplat.recorder.config import RecorderConfig
from manisplat.recorder.simrig import SimRig

THREADED = False
CAMERAS = {"cam_high": ("world", 0.0), "cam_left_wrist": ("left/link6", 0.010), "cam_right_wrist": ("right/link6", 0.020)}
"""Camera -> (mount, how late its stamps are, s: corrected by its latency_s)."""
ARMS = ("left", "right")


def _exposures(camera: ReplayCamera) -> dict[int, float]:
    """seq -> true mid-exposure time (monotonic s) of every frame the camera delivered."""
    return {seq: t for seq, t in camera.exposures}


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    seconds = float(os.environ.get("MANISPLAT_RIG_SECONDS", "15" if ctx.quick else "60"))
    image_format = os.environ.get("MANISPLAT_RIG_FORMAT", "png")
    load = os.getloadavg()
    work = Path(tempfile.mkdtemp(prefix="manisplat-rig-"))
    clock = SystemClock()
    sims: dict[str, SimRig] = {}
    arms: list[RigArm] = []
    cameras: dict[str, ReplayCamera] = {}
    try:
        source = make_source(ctx, work / "source")
        for name in ARMS:
            sims[name] = SimRig(clock, motion="wave", keep_states=False)
            arm = PiperArm(sims[name].open_bus(), read_only=True, own_bus=True)
            arms.append(RigArm(name, arm, ArmInfo(name=name)))
        rig_cameras, epoch = [], ReplayEpoch()  # started together, as manisplat-record's replays
        for name, (mount, late) in CAMERAS.items():
            cameras[name] = ReplayCamera(lambda: EpisodeCamera(source), clock, loop=True, preload=True,
                                         stamp_latency_s=late, epoch=epoch)
            cam = cameras[name]
            info = CameraInfo(name, cam.width, cam.height, cam.K, mount=mount)
            rig_cameras.append(RigCamera(name, cam, info, latency_s=late))
        recorder = RigRecorder(arms, rig_cameras, clock, RecorderConfig(image_format=image_format), nominal_fps=FPS)
        for sim in sims.values():
            sim.start()
        recorder.wait_for_arms(timeout=10.0)
        sim_threads = [sim._thread.native_id for sim in sims.values()]
        cpu0, sim_cpu0, real0 = os.times(), sum(map(thread_cpu_s, sim_threads)), time.monotonic()
        result = recorder.record_episode(work / "episode", duration=seconds)
        cpu1, sim_cpu1, real1 = os.times(), sum(map(thread_cpu_s, sim_threads)), time.monotonic()
        exposures = {name: _exposures(cam) for name, cam in cameras.items()}
        report = validate(work / "episode", decode_images=False)
        ep = Episode.open(work / "episode")
        t0 = ep.meta.extra["clock"]["t0_monotonic"]
        frames = {name: ep.arm_frames(name) for name in ARMS}
        sent = {name: sim.frames_sent for name, sim in sims.items()}
        late_cycles = {name: sim.late_cycles for name, sim in sims.items()}
    finally:
        for cam in cameras.values():
            cam.close()
        for name, sim in sims.items():
            sim.stop()
        for a in arms:
            a.arm.close()
        shutil.rmtree(work, ignore_errors=True)
    s = result.stats
    cpu = (cpu1.user + cpu1.system) - (cpu0.user + cpu0.system)
    sim_cpu = sim_cpu1 - sim_cpu0
    seq = {name: frames["left"].extra[f"{name}.seq"].astype(int) for name in CAMERAS}
    t_true = np.array([exposures["cam_high"][k] for k in seq["cam_high"]])  # monotonic
    rows: list[dict[str, Any]] = [
        {"what": "recording", "value": f"{s.duration_s:.1f} s, 2 arms, 3 cameras 640x480 {image_format}, {s.stop_reason}",
         "ok": result.valid and result.error is None},
        {"what": "frames written / expected (30 fps)", "value": f"{s.frames} / {s.duration_s * FPS:.0f}",
         "ok": abs(s.frames - s.duration_s * FPS) <= 3},
        {"what": "frames lost (camera gaps + skipped + writer queue)", "value": f"{s.frames_lost}",
         "ok": s.frames_lost == 0},
    ]
    for name, c in s.cameras.items():
        own_t = ep_t = None
        if name != "cam_high":
            ep_t = frames["left"].extra[f"{name}.t"] + t0
            own_t = np.array([exposures[name][k] for k in seq[name]])
        error = "" if own_t is None else f", <camera>.t vs true exposure max {np.abs(ep_t - own_t).max() * 1e6:.1f} us"
        rows.append({"what": f"camera {name}", "value": f"dropped {c.dropped_camera}, unmatched {c.unmatched}, "
                                                         f"unused {c.unused}, stale {c.stale}, max skew "
                                                         f"{c.max_skew_s * 1e3:.1f} ms{error}",
                     "ok": c.dropped_camera == 0 and c.unmatched == 0})
    for name in ARMS:
        a = s.arms[name]
        truth = sims[name].truth(t_true)
        err = np.degrees(np.abs(frames[name].q - truth[:, :6]))
        good = frames[name].extra["sync_flags"] == 0
        gripper_mm = np.abs(frames[name].gripper - truth[:, 6]) * 1e3
        rows.append({"what": f"arm {name}: joints vs truth at the true exposure, unflagged frames (deg)",
                     "value": (f"max {err[good].max():.4f}, mean {err[good].mean():.4f}; gripper max "
                               f"{gripper_mm[good].max():.3f} mm" if good.any() else "no unflagged frame"),
                     "ok": bool(good.any()) and err[good].max() < 0.05})
        rows.append({"what": f"arm {name}: flagged frames, largest sync gap",
                     "value": f"{a.flagged} {a.flag_counts or ''}, {a.max_sync_gap_s * 1e3:.1f} ms",
                     "ok": a.flagged == 0})
        rows.append({"what": f"arm {name}: joint samples / CAN frames per s; sent / logged; sim cycles > 50 ms late",
                     "value": f"{a.joint_samples / s.duration_s:.1f} / {a.can_frames_logged / s.duration_s:.0f}; "
                              f"{sent[name]} / {a.can_frames_logged} (dropped {a.can_frames_dropped}); "
                              f"{late_cycles[name]}",
                     "ok": a.can_frames_dropped == 0})
    rows.append({"what": "CPU s per s of recording: all / the two simulators' threads",
                 "value": f"{cpu / (real1 - real0):.2f} / {sim_cpu / (real1 - real0):.2f}", "ok": True})
    rows.append({"what": "load average at the start (1/5/15 min)", "value": " / ".join(f"{x:.1f}" for x in load),
                 "ok": True})
    if not report.ok:
        ctx.notes.append(str(report))
    ctx.notes.append(f"{os.cpu_count()} CPUs, shared with other jobs; the simulators run in the recorder's process "
                     "(their Python threads compete with it for the GIL)")
    return rows
