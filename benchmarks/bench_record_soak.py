"""Recorder soak: a simulated PiPER at 3040 frames/s + a 30 fps 640x480 replayed camera for 10 simulated minutes.

Everything is the real recorder (PiperArm reader thread, sync, writer thread with PNG images,
joints.csv, the ASC CAN log) writing a real episode to disk; only the hardware is simulated: a
``SimRig`` (SimulatedPiper on a python-can virtual bus, 200 Hz cycles of 15-16 frames) and a
``ReplayCamera`` looping 60 preloaded 640x480 frames (the shared sample's images upscaled with
sensor-like noise, ~500 kB as PNG), both on a ``ScaledClock`` running ``MANISPLAT_SOAK_SPEED``
times faster than real time (default 2; nothing waits for the recorder: a recorder too slow for
that pace loses frames, and they are counted). ``MANISPLAT_SOAK_MINUTES`` (default 10, --quick
0.5) and ``MANISPLAT_SOAK_FORMAT`` (png or jpg) change the run. The episode is deleted afterwards
(its episode.json is kept in the results folder).

Reported: frames written / lost (writer queue drops, camera sequence gaps), how late the
recorder read a frame at worst; CAN frames sent by the simulator / received by the recorder /
in can.asc / dropped by the log queue; RSS before, peak and at the end; CPU seconds per second
of recording for the whole process and without the simulator's own thread.
"""

from __future__ import annotations

import os
import resource
import shutil
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from benchmarks._harness import BenchContext, MissingBenchmarkData
from manisplat.drivers.piper import PiperArm
from manisplat.drivers.replay import EpisodeCamera
from manisplat.episode import CameraInfo, Episode, EpisodeWriter, RobotInfo, validate
from manisplat.recorder.clock import ScaledClock
from manisplat.recorder.config import RecorderConfig
from manisplat.recorder.replaycam import ReplayCamera
from manisplat.recorder.session import Recorder
from manisplat.recorder.simrig import SimRig

THREADED = False
W, H, FPS, SOURCE_FRAMES = 640, 480, 30.0, 60
PAGE = os.sysconf("SC_PAGE_SIZE")
TICK = os.sysconf("SC_CLK_TCK")


def make_source(ctx: BenchContext, path: Path) -> Path:
    """60 frames at 640x480 from the shared sample (upscaled, +-2 grey levels of noise)."""
    try:
        sample = Episode.open(ctx.require_shared("data", "sim_pick_place_small"))
    except MissingBenchmarkData:
        sample = None
    rng = np.random.default_rng(0)
    K = np.array([[500.0, 0, (W - 1) / 2], [0, 500.0, (H - 1) / 2], [0, 0, 1]])
    with EpisodeWriter(path, CameraInfo("soak", W, H, K), RobotInfo(), FPS, extra_frame_columns=("seq",)) as w:
        for i in range(SOURCE_FRAMES):
            if sample is not None:
                img = cv2.resize(sample.rgb(i * len(sample) // SOURCE_FRAMES), (W, H), interpolation=cv2.INTER_CUBIC)
            else:
                yy, xx = np.mgrid[0:H, 0:W]
                img = np.stack([(xx + i) % 256, (yy * 2) % 256, (xx + yy) % 256], axis=-1).astype(np.uint8)
            noisy = np.clip(img.astype(np.int16) + rng.normal(0, 2.0, img.shape).round().astype(np.int16), 0, 255)
            w.add_frame(i / FPS, np.zeros(6), 0.0, noisy.astype(np.uint8), extra={"seq": float(i)})
    return path


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE / 2**20


def thread_cpu_s(native_id: int) -> float:
    with open(f"/proc/self/task/{native_id}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK  # utime, stime


class RssSampler:
    """RSS every 0.5 s (real) on a thread: its peak and its whole course."""

    def __init__(self) -> None:
        self.peak = rss_mb()
        self.samples: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.5):
            self.samples.append(rss_mb())
            self.peak = max(self.peak, self.samples[-1])

    def quarters(self) -> str:
        """Mean RSS (MB) over each quarter of the run: a leak shows as a rising trend."""
        n = len(self.samples)
        if n < 4:
            return "-"
        return " / ".join(f"{np.mean(self.samples[k * n // 4:(k + 1) * n // 4]):.0f}" for k in range(4))

    def stop(self) -> float:
        self._stop.set()
        self._thread.join()
        return max(self.peak, rss_mb())


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    minutes = float(os.environ.get("MANISPLAT_SOAK_MINUTES", "0.5" if ctx.quick else "10"))
    speed = float(os.environ.get("MANISPLAT_SOAK_SPEED", "2"))
    image_format = os.environ.get("MANISPLAT_SOAK_FORMAT", "png")
    work = Path(tempfile.mkdtemp(prefix="manisplat-soak-"))
    try:
        source = make_source(ctx, work / "source")
        clock = ScaledClock(speed)
        rig = SimRig(clock, motion="wave", keep_states=False).start()
        arm = PiperArm(rig.open_bus(), read_only=True, own_bus=True)
        camera = ReplayCamera(lambda: EpisodeCamera(source), clock, loop=True, preload=True)
        recorder = Recorder(arm, camera, clock, RecorderConfig(image_format=image_format), nominal_fps=FPS)
        recorder.wait_for_arm(timeout=10.0)
        rss_before = rss_mb()
        sampler = RssSampler()
        cpu0, rig_cpu0, real0 = os.times(), thread_cpu_s(rig._thread.native_id), time.monotonic()
        last_print = [0.0]

        def progress(s: Any) -> None:
            if time.monotonic() - last_print[0] > 30:
                last_print[0] = time.monotonic()
                print(f"  soak: {s.elapsed_s / 60:5.2f} of {minutes:g} simulated min, {s.frames} frames, "
                      f"lost {s.lost}, queue {s.queue}, CAN {s.can_fps:.0f}/s", flush=True)

        result = recorder.record_episode(work / "episode", duration=minutes * 60.0, on_status=progress)
        cpu1, rig_cpu1, real1 = os.times(), thread_cpu_s(rig._thread.native_id), time.monotonic()
        rss_peak = sampler.stop()
        rss_end = rss_mb()
        camera.close()
        rig.stop()
        sent = rig.frames_sent
        try:
            arm.wait_for_frames(sent, timeout=30.0)
        except TimeoutError:
            pass  # counted below as lost
        received = arm.stats().frames
        arm.close()
        report = validate(work / "episode", decode_images=False)
        lines = sum(1 for line in open(work / "episode" / "can.asc", errors="replace") if " Rx " in line)
        size_gb = sum(p.stat().st_size for p in (work / "episode").rglob("*") if p.is_file()) / 1e9
        shutil.copy(work / "episode" / "episode.json", ctx.out_dir / "record_soak_episode.json")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    s = result.stats
    sim_s = s.duration_s
    cpu = (cpu1.user + cpu1.system) - (cpu0.user + cpu0.system)
    rig_cpu = rig_cpu1 - rig_cpu0
    rows = [
        {"what": "recording", "value": f"{sim_s / 60:.2f} simulated min in {(real1 - real0) / 60:.2f} real min "
                                        f"(x{sim_s / (real1 - real0):.2f}), {image_format}, {size_gb:.1f} GB",
         "ok": result.valid and result.error is None},
        {"what": "frames written / expected (30 fps)", "value": f"{s.frames} / {sim_s * FPS:.0f}",
         "ok": abs(s.frames - sim_s * FPS) <= 2},
        {"what": "frames lost (queue drops + camera gaps)", "value": f"{s.dropped_queue} + {s.dropped_camera}",
         "ok": s.frames_lost == 0},
        {"what": "frames flagged (sync)", "value": f"{s.flagged}", "ok": s.flagged == 0},
        {"what": "worst frame read delay (recorder behind)", "value": f"{camera.max_late_s * 1e3:.0f} ms", "ok": True},
        {"what": "CAN frames sent / received / in can.asc", "value": f"{sent} / {received} / {lines}",
         "ok": sent == received and lines == s.can_frames_logged},
        {"what": "CAN frames in can.asc per s of recording", "value": f"{lines / sim_s:.1f}",
         "ok": abs(lines / sim_s - 3040) < 5},
        {"what": "CAN frames lost (bus + log queue)", "value": f"{sent - received} + {s.can_frames_dropped}",
         "ok": sent == received and s.can_frames_dropped == 0},
        {"what": "joint samples in joints.csv", "value": f"{s.joint_samples} ({s.joint_samples / sim_s:.1f} /s)",
         "ok": True},
        {"what": "RSS before / peak / end (MB)", "value": f"{rss_before:.0f} / {rss_peak:.0f} / {rss_end:.0f}",
         "ok": True},
        {"what": "RSS mean per quarter of the run (MB)", "value": sampler.quarters(), "ok": True},
        {"what": "ru_maxrss (MB)", "value": f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f}",
         "ok": True},
        {"what": "CPU s per s of recording: all / without the simulator",
         "value": f"{cpu / sim_s:.3f} / {(cpu - rig_cpu) / sim_s:.3f}", "ok": True},
        {"what": "simulator cycles late by > 50 ms", "value": f"{rig.late_cycles}", "ok": rig.late_cycles == 0},
    ]
    if not report.ok:
        ctx.notes.append(str(report))
    ctx.notes.append(f"speed x{speed:g} of real time (MANISPLAT_SOAK_SPEED); {os.cpu_count()} CPUs; the CPU "
                     "figures include the replayed camera (preloaded, ~0) and, in 'all', the simulated arm")
    return rows
