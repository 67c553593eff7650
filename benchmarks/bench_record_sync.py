"""Recorder sync error (deg) against the truth: our interpolation vs nearest sample vs latest-on-arrival.

Data with known truth: a simulated PiPER (``SimulatedPiper``, stepped synchronously on a
python-can virtual bus, its frames read by the same ``FeedbackTracker`` PiperArm uses) reports
an analytic motion (:func:`manisplat.recorder.simrig.wave_state`, 31 deg/s peak; ``fast`` plays
it 3x faster, 94 deg/s) with the real frame layout: 0.001 deg quantisation, three joint frames per
5 ms cycle, 0x2A5 stamped 0.52 ms after the cycle's sampling instant. Bus stamps get the jitter of
a USB adapter's batching (the whole cycle 0-0.5 ms late); a joint sample reaches Python 0.1-0.6 ms
after its stamp. A 30 fps camera exposes at random phase; its stamp is the mid-exposure time
+-0.2 ms (depthai); the frame reaches Python 30-40 ms after the exposure (USB transfer, ISP).

Methods, each given what a recorder would have:
* ``ours``: :func:`manisplat.recorder.sync.sync_joints` at the frame stamp, on the bus stamps
  (joints from the joint samples, the gripper from its own 0x2A8 frames, as the recorder does);
* ``nearest``: the joint sample whose bus stamp is nearest to the frame stamp;
* ``latest_at_arrival``: the latest joint sample Python had when the frame reached it (what most
  recorders do: read the arm's state in the camera callback).
``dropouts``: the bus goes silent for 50-200 ms now and then (5 % of the time); ``ours`` flags the
frames in a gap (counted, excluded from its error), the baselines cannot tell.
Error per frame = the largest joint error, deg; mean / p95 / max over the frames.
"""

from __future__ import annotations

import uuid
from typing import Any

import can
import numpy as np

from benchmarks._harness import BenchContext
from manisplat.drivers.piper import FeedbackTracker, SimulatedPiper
from manisplat.drivers.piper import protocol as P
from manisplat.recorder.simrig import wave_state
from manisplat.recorder.sync import latest_at_arrival, nearest_sample, sync_joints

THREADED = False
PERIOD = 0.005
MAX_GAP_S = 0.015


def joint_stream(seconds: float, time_scale: float, rng: np.random.Generator,
                 dropouts: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """From a simulated PiPER: joint samples ``(bus stamps (N,), python arrival (N,), values (N, 7))``
    (their gripper: the latest 0x2A8, as PiperArm gives it) and the gripper frames' own
    ``(stamps (G,), widths (G,))``."""
    channel = f"bench-sync-{uuid.uuid4().hex}-bus"
    sim_bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    rx = can.Bus(interface="virtual", channel=channel)
    sim = SimulatedPiper(sim_bus, t0=0.0)
    tracker = FeedbackTracker()
    silent = np.zeros(int(seconds / PERIOD) + 1, dtype=bool)
    if dropouts:
        k = 0
        while k < len(silent):
            k += int(rng.uniform(1.0, 3.0) / PERIOD)
            silent[k:k + int(rng.uniform(0.05, 0.2) / PERIOD)] = True
    stamps, arrival, values, g_stamps, g_widths = [], [], [], [], []
    try:
        for k in range(len(silent) - 1):
            state = wave_state((k + 1) * PERIOD * time_scale)[0]
            sim.model.q, sim.model.gripper = state[:6].copy(), float(state[6])
            if silent[k]:
                sim.model.step(PERIOD)
                continue
            sim.step()
            batch_delay = rng.uniform(0.0, 0.0005)
            while (msg := rx.recv(timeout=0)) is not None:
                msg.timestamp += batch_delay
                if msg.arbitration_id == 0x2A8:
                    g_stamps.append(msg.timestamp)
                    g_widths.append(P.decode_message(msg).width)
                sample = tracker.ingest(msg, 0.0)
                if sample is not None and np.isfinite(sample.gripper):
                    stamps.append(sample.t)
                    arrival.append(sample.t + rng.uniform(0.0001, 0.0006))
                    values.append(np.append(sample.q, sample.gripper))
    finally:
        rx.shutdown()
        sim_bus.shutdown()
    return np.asarray(stamps), np.asarray(arrival), np.asarray(values), np.asarray(g_stamps), np.asarray(g_widths)


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    seconds = 10.0 if ctx.quick else 60.0
    rows = []
    for scenario, time_scale, dropouts in (("slow (31 deg/s)", 1.0, False), ("fast (94 deg/s)", 3.0, False),
                                           ("slow + dropouts", 1.0, True)):
        rng = np.random.default_rng(0)
        stamps, arrival, values, g_stamps, g_widths = joint_stream(seconds, time_scale, rng, dropouts)
        exposure = np.arange(rng.uniform(0.1, 0.13), seconds - 0.1, 1 / 30.0)
        frame_stamp = exposure + rng.normal(0.0, 0.0002, len(exposure))
        frame_arrival = exposure + rng.uniform(0.030, 0.040, len(exposure))
        truth = wave_state(exposure * time_scale)
        ours = sync_joints(stamps, values, frame_stamp, MAX_GAP_S)
        grip = sync_joints(g_stamps, g_widths[:, None], frame_stamp, MAX_GAP_S)  # the recorder's gripper stream
        ours.values[:, 6] = grip.values[:, 0]
        trusted = (ours.flags | grip.flags) == 0
        results = {"ours": (ours.values, trusted),
                   "nearest": (nearest_sample(stamps, values, frame_stamp), np.ones(len(exposure), bool)),
                   "latest_at_arrival": (latest_at_arrival(arrival, values, frame_arrival),
                                         np.ones(len(exposure), bool))}
        for method, (est, keep) in results.items():
            err = np.degrees(np.abs(est[:, :6] - truth[:, :6])).max(axis=1)[keep]
            rows.append({"scenario": scenario, "method": method, "frames": int(keep.sum()),
                         "flagged": int((~keep).sum()), "mean_deg": float(err.mean()),
                         "p95_deg": float(np.percentile(err, 95)), "max_deg": float(err.max()),
                         "gripper_max_mm": float(np.abs(est[keep, 6] - truth[keep, 6]).max() * 1e3)})
    ctx.notes.append("ours flags frames interpolated across a gap > 15 ms (excluded from its row; the baselines "
                     "have no such flag and keep every frame)")
    return rows
