"""Episode writing throughput of the recorder's writer (EpisodeSink), by encoding threads.

Frames (a smooth random texture with sensor-like noise, and a smooth depth map) are put as
fast as the sink takes them (no drops: the producer waits while the queue is full) into a
real episode on disk, PNG for RGB and depth; the row is frames per second from the first put
to ``finish()`` (everything written and the episode complete). ``encode_threads`` 0 encodes
on the writer thread (the previous design). A recording at F fps keeps up when the row's
``fps`` stays above F with the rest of the recorder (about 0.4 core at 3040 CAN frames/s).

Rows: size, depth, encode_threads, frames, seconds, fps, speedup (vs 0 threads).
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from benchmarks._harness import BenchContext
from manisplat.episode import CameraInfo, EpisodeWriter, RobotInfo
from manisplat.recorder.writer import EpisodeSink, FrameItem

THREADED = False
QUEUE = 16


def _images(width: int, height: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    small = rng.uniform(0, 255, (height // 16, width // 16, 3)).astype(np.float32)
    smooth = cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
    rgb = np.clip(smooth + rng.normal(0, 3, (height, width, 3)), 0, 255).astype(np.uint8)
    depth = cv2.resize(rng.uniform(0.5, 2.0, (height // 16, width // 16)).astype(np.float32), (width, height))
    return rgb, depth


def _throughput(folder: Path, width: int, height: int, depth: bool, threads: int, frames: int) -> float:
    rng = np.random.default_rng(0)
    images = [_images(width, height, rng) for _ in range(8)]
    K = np.array([[width * 0.8, 0, (width - 1) / 2], [0, width * 0.8, (height - 1) / 2], [0, 0, 1]])
    writer = EpisodeWriter(folder, CameraInfo("bench", width, height, K), RobotInfo(), 30.0,
                           depth_scale=0.001 if depth else None)
    sink = EpisodeSink(writer, queue_frames=QUEUE, encode_threads=threads)
    start = time.perf_counter()
    for i in range(frames):
        rgb, d = images[i % len(images)]
        while sink.queued_frames >= QUEUE and not sink.failed.is_set():
            time.sleep(0.001)  # wait for room instead of dropping
        if not sink.put_frame(FrameItem(i / 30, np.zeros(6), 0.0, rgb, d if depth else None)):
            raise RuntimeError(f"the writer refused frame {i}: {sink.error}")
    sink.finish()
    return time.perf_counter() - start


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    cases = [(640, 400, False), (1280, 720, True)]
    frames = 30 if ctx.quick else 150
    thread_counts = [0, 1, 2, 4]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for width, height, depth in cases:
            base = None
            for threads in thread_counts:
                seconds = _throughput(Path(tmp) / f"ep_{width}_{threads}", width, height, depth, threads, frames)
                fps = frames / seconds
                base = base or fps
                rows.append({"size": f"{width}x{height}", "depth": depth, "encode_threads": threads,
                             "frames": frames, "seconds": seconds, "fps": fps, "speedup": fps / base})
    ctx.notes.append(f"{os.cpu_count()} CPUs; PNG for RGB and depth; frames/s until the episode is complete")
    return rows
