"""PiPER CAN decoding: frames/s per frame and vectorised over a 10-minute log (1.82M frames).

The log is a synthetic PiPER feedback stream at the real rates (0x2A1..0x2A8 and 0x251..0x256 at
200 Hz, 0x261..0x266 at 40 Hz: 3040 frames/s, 130 us apart within a cycle), built with numpy:
smooth joint motion, the flange pose from the built-in model's FK, gripper, driver frames.

Rows (``what``):
* ``decode()`` per frame: the scalar decoder on every frame of the log (bytes in, dataclass out);
* ``FeedbackTracker.ingest()`` per frame: what PiperArm's reader thread does for each message
  (decode, per-ID counts and gaps, latest values, joint-cycle assembly), on the first minute;
* ``decode_arrays()``: the vectorised decoder over the whole log with ``workers`` = threads,
  and ``joint_samples()`` after it;
* ``CanArrays.read`` of a BLF file of the first minute (python-can's reader dominates).
The scalar rows run once (threads = 1); they hold the GIL, threads do not change them.
``check`` confirms that the vectorised and scalar decoders agree on the counts and samples.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import can
import numpy as np
import torch

from benchmarks._harness import BenchContext, time_call
from manisplat.drivers.piper import FeedbackTracker
from manisplat.drivers.piper import protocol as P
from manisplat.drivers.piper.logdecode import CanArrays, decode_arrays
from manisplat.geometry import matrix_to_rpy
from manisplat.robot import builtin_piper

THREADED = True
RATE = 200.0
SPACING = 130e-6


def _be(values: np.ndarray, code: str) -> np.ndarray:
    """(K,) ints -> (K, n) uint8 big-endian bytes."""
    return np.ascontiguousarray(values.astype(code)).view(np.uint8).reshape(len(values), -1)


def synthetic_log(seconds: float, seed: int = 0) -> CanArrays:
    """A PiPER feedback stream of ``seconds`` (see the module docstring)."""
    k = int(round(seconds * RATE))
    t = np.arange(k) / RATE
    rng = np.random.default_rng(seed)
    robot = builtin_piper(with_geometry=False)
    mid, half = (robot.lower + robot.upper) / 2, (robot.upper - robot.lower) / 2
    freq = rng.uniform(0.05, 0.3, 6)
    q = mid + 0.6 * half * np.sin(2 * np.pi * freq * t[:, None] + rng.uniform(0, 6.3, 6))  # [K, 6]
    qd = np.gradient(q, t, axis=0)
    grip = 0.035 + 0.03 * np.sin(2 * np.pi * 0.1 * t)
    T = robot.link_pose(torch.from_numpy(q), "link6")  # [K, 4, 4]
    xyz = T[:, :3, 3].numpy()
    rpy = matrix_to_rpy(T[:, :3, :3]).numpy()
    mdeg = lambda x: np.round(np.degrees(x) * 1000).astype(np.int64)  # noqa: E731
    um = lambda x: np.round(x * 1e6).astype(np.int64)  # noqa: E731
    blocks: list[tuple[int, np.ndarray, np.ndarray, int]] = []  # (id, cycles, data [n, 8], slot)

    def add(can_id: int, data: np.ndarray, slot: int, cycles: np.ndarray | None = None) -> None:
        blocks.append((can_id, np.arange(k) if cycles is None else cycles, data, slot))

    status = np.zeros((k, 8), np.uint8)
    status[:, 0], status[:, 2] = 1, 1  # CAN control, MOVE J
    status[:, 4] = (np.abs(qd).max(axis=1) > 1e-3).astype(np.uint8)
    add(0x2A1, status, 0)
    pose = [(um(xyz[:, 0]), um(xyz[:, 1])), (um(xyz[:, 2]), mdeg(rpy[:, 0])), (mdeg(rpy[:, 1]), mdeg(rpy[:, 2]))]
    for p, (a, b) in enumerate(pose):
        add(0x2A2 + p, np.hstack([_be(a, ">i4"), _be(b, ">i4")]), 1 + p)
    for p in range(3):
        add(0x2A5 + p, np.hstack([_be(mdeg(q[:, 2 * p]), ">i4"), _be(mdeg(q[:, 2 * p + 1]), ">i4")]), 4 + p)
    gripper = np.hstack([_be(um(grip), ">i4"), _be(np.full(k, 500), ">i2"), np.full((k, 1), 0x40, np.uint8),
                         np.zeros((k, 1), np.uint8)])
    add(0x2A8, gripper, 7)
    for m in range(6):
        current = rng.normal(0, 0.3, k)
        add(0x251 + m, np.hstack([_be(np.round(qd[:, m] * 1000), ">i2"), _be(np.round(current * 1000), ">i2"),
                                  _be(np.round(q[:, m] * 1000), ">i4")]), 8 + m)
    slow = np.arange(0, k, 5)
    for m in range(6):
        n = len(slow)
        low = np.hstack([_be(np.full(n, 240), ">u2"), _be(np.full(n, 35), ">i2"), np.full((n, 1), 30, np.uint8),
                         np.full((n, 1), 0x40, np.uint8), _be(np.zeros(n), ">u2")])
        add(0x261 + m, low, 14 + m, slow)
    ids = np.concatenate([np.full(len(c), i) for i, c, _, _ in blocks])
    times = np.concatenate([c / RATE + s * SPACING for _, c, _, s in blocks]) + 1_700_000_000.0
    data = np.concatenate([d for _, _, d, _ in blocks]).astype(np.uint8)
    order = np.argsort(times, kind="stable")
    n = len(order)
    return CanArrays(times[order], ids[order].astype(np.int64), np.full(n, 8, np.int16), data[order],
                     np.zeros(n, np.uint8))


def _scalar_rows(log: CanArrays, minute: CanArrays) -> list[dict[str, Any]]:
    ids, data = log.can_id.tolist(), [bytes(row) for row in log.data]
    decode = P.decode
    start = time.perf_counter()
    kinds: dict[type, int] = {}
    for can_id, payload in zip(ids, data):
        kind = type(decode(can_id, payload))
        kinds[kind] = kinds.get(kind, 0) + 1
    elapsed = time.perf_counter() - start
    rows = [{"what": "decode() per frame", "frames": len(log), "seconds": elapsed, "frames_per_s": len(log) / elapsed,
             "x_realtime": len(log) / elapsed / 3040.0}]
    messages = list(minute.messages())
    tracker = FeedbackTracker()
    start = time.perf_counter()
    for msg in messages:
        tracker.ingest(msg, 0.0)
    elapsed = time.perf_counter() - start
    rows.append({"what": "FeedbackTracker.ingest() per frame", "frames": len(messages), "seconds": elapsed,
                 "frames_per_s": len(messages) / elapsed, "x_realtime": len(messages) / elapsed / 3040.0,
                 "check": f"{tracker.assembler.samples} samples, {tracker.invalid} invalid"})
    rows[0]["check"] = f"{kinds.get(P.InvalidFrame, 0)} invalid"
    return rows


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    seconds = 60.0 if ctx.quick else 600.0
    log = synthetic_log(seconds)
    minute = log.slice(0, int(60 * 3040))
    rows: list[dict[str, Any]] = []
    if ctx.threads == 1:
        rows += _scalar_rows(log, minute)
    result = decode_arrays(log, workers=ctx.threads)
    t_vec = time_call(lambda: decode_arrays(log, workers=ctx.threads), repeat=3, warmup=1)
    t_joint = time_call(result.joint_samples, repeat=3, warmup=1)
    counts = result.counts()
    samples = len(result.joint_samples()[0])
    expected = int(round(seconds * RATE))
    rows.append({"what": f"decode_arrays(workers={ctx.threads})", "frames": len(log), "seconds": t_vec,
                 "frames_per_s": len(log) / t_vec, "x_realtime": len(log) / t_vec / 3040.0,
                 "check": f"{counts['valid']} valid, {counts['invalid']} invalid, {samples}/{expected} samples"})
    rows.append({"what": "joint_samples() after it", "frames": len(log), "seconds": t_joint,
                 "frames_per_s": len(log) / t_joint, "x_realtime": len(log) / t_joint / 3040.0})
    if ctx.threads == 1:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "minute.blf"
            with can.Logger(path) as writer:
                for msg in minute.messages():
                    writer.on_message_received(msg)
            start = time.perf_counter()
            back = CanArrays.read(path)
            elapsed = time.perf_counter() - start
        rows.append({"what": "CanArrays.read(BLF, 1 min)", "frames": len(back), "seconds": elapsed,
                     "frames_per_s": len(back) / elapsed, "x_realtime": len(back) / elapsed / 3040.0,
                     "check": f"{np.array_equal(back.data, minute.data)} (bytes equal)"})
    if counts["valid"] != len(log) or samples != expected:
        raise AssertionError(f"decoding disagrees with the synthetic log: {counts}, {samples} samples")
    ctx.notes.append(f"log: {seconds:.0f} s of PiPER feedback, {len(log)} frames (3040 frames/s); x_realtime = "
                     "frames_per_s / 3040; vectorised times: median of 3 runs")
    return rows
