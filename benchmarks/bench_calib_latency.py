"""Camera latency recovery on synthetic moving episodes rendered by the project (known offset).

Each case writes an episode with ``manisplat.calib.synth.write_latency_episode``: the built-in
PiPER makes bursty min-jerk moves with a board on link6 in front of a textured static
background, 320x240 at 30 fps, 200 Hz joints; frame k is rendered at its exposure time and
stamped ``+ latency``. ``estimate_latency`` then runs with the robot signal in metres
(uncalibrated) or in pixels (calibrated camera). Goal: |error| <= 2 ms.

Rows: duration_s, signal, latency_ms, estimate_ms, error_ms, sigma_ms, correlation, seconds.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._harness import BenchContext
from manisplat.calib.board import BoardSpec
from manisplat.calib.latency import estimate_latency
from manisplat.calib.synth import default_truth, write_latency_episode

THREADED = False


def run(ctx: BenchContext) -> list[dict]:
    spec = BoardSpec()
    cases = [(0.0, False), (0.012, True), (0.025, False), (0.040, True), (0.047, False), (0.060, True),
             (-0.015, False), (0.090, True)]
    durations = [10.0] if ctx.quick else [10.0, 20.0]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for duration in durations:
            for k, (latency, calibrated) in enumerate(cases[:3] if ctx.quick else cases):
                truth = default_truth(spec, width=320, height=240, f=260.0, latency_s=latency)
                path = Path(tmp) / f"ep_{duration}_{k}"
                write_latency_episode(path, spec, truth, rng=np.random.default_rng(100 + k), duration_s=duration,
                                      calibrated=calibrated)
                t0 = time.perf_counter()
                est = estimate_latency(path)
                rows.append({"duration_s": duration, "signal": est.signal, "latency_ms": latency * 1000,
                             "estimate_ms": est.latency_s * 1000, "error_ms": (est.latency_s - latency) * 1000,
                             "sigma_ms": est.std_s * 1000, "correlation": est.correlation,
                             "seconds": time.perf_counter() - t0})
    for d in durations:
        errs = [abs(r["error_ms"]) for r in rows if r["duration_s"] == d]
        ctx.notes.append(f"{d:g} s episodes: max |error| {max(errs):.2f} ms, median {np.median(errs):.2f} ms "
                         f"over {len(errs)} (goal <= 2 ms)")
    return rows
