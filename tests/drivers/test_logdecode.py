"""The vectorised log decoder gives, frame by frame, what the scalar decoder gives."""

from __future__ import annotations

import math

import numpy as np
import pytest

from manisplat.drivers.piper import JointAssembler
from manisplat.drivers.piper import protocol as P
from manisplat.drivers.piper.logdecode import INVALID, UNDOCUMENTED, UNKNOWN, VALID, CanArrays, decode_arrays

from .test_replay import fuzz_messages, record_log


def scalar_equals_vector(frames: CanArrays) -> int:
    """Compare every frame; returns how many valid frames were compared field by field."""
    log = decode_arrays(frames)
    kinds = {P.InvalidFrame: INVALID, P.UnknownFrame: UNKNOWN, P.UndocumentedFrame: UNDOCUMENTED}
    position = {name: {int(r): k for k, r in enumerate(tab["row"])} for name, tab in log.tables.items()}
    compared = 0
    for i, msg in enumerate(frames.messages()):
        frame = P.decode_message(msg)
        assert log.status[i] == kinds.get(type(frame), VALID), (i, msg, frame)
        if log.status[i] != VALID:
            continue
        name = type(frame).__name__
        table, k = log.tables[name], position[name][i]
        assert table["t"][k] == msg.timestamp
        for field in P.field_names(type(frame)):
            value, column = getattr(frame, field), table[field][k]
            if field == "data":
                assert bytes(column[: table["length"][k]]) == value
            elif field == "levels":
                assert tuple(column) == value
            elif value is None:
                assert math.isnan(column)
            else:
                assert value == column, (name, field, value, column)
        compared += 1
    return compared


def test_fuzzed_frames_decode_the_same_both_ways():
    frames = CanArrays.from_messages(fuzz_messages(30_000, seed=1))
    assert scalar_equals_vector(frames) > 5000
    counts = decode_arrays(frames).counts()
    assert all(v > 300 for v in counts.values()), counts


def test_every_class_in_a_canonical_sweep():
    """Random 8-byte payloads on every known ID (many valid frames of every class)."""
    rng = np.random.default_rng(3)
    ids = np.repeat(np.array(sorted(P.REGISTRY)), 200)
    n = len(ids)
    frames = CanArrays(np.arange(n) * 1e-3, ids.astype(np.int64), np.full(n, 8, np.int16),
                       rng.integers(0, 256, (n, 8), dtype=np.uint8), np.zeros(n, np.uint8))
    scalar_equals_vector(frames)
    log = decode_arrays(frames)
    assert {P.FRAME_CLASSES[i].__name__ for i in np.unique(log.cls_index)} == {c.__name__ for c in P.FRAME_CLASSES}


def test_joint_samples_of_a_log_equal_streaming_assembly(tmp_path):
    messages = record_log(tmp_path / "run.blf", seconds=0.5)
    rng = np.random.default_rng(0)
    keep = [m for m in messages if not (0x2A5 <= m.arbitration_id <= 0x2A7 and rng.random() < 0.05)]
    frames = CanArrays.from_messages(keep)
    t, q, rows = decode_arrays(frames).joint_samples()
    assembler = JointAssembler()
    streamed = []
    for msg in keep:
        f = P.decode_message(msg)
        if isinstance(f, P.JointFeedback) and (s := assembler.push(f.pair, f.q_a, f.q_b, msg.timestamp)):
            streamed.append(s)
    assert 50 < len(streamed) < 100  # lost frames dropped their cycles
    np.testing.assert_array_equal(t, [s[0] for s in streamed])
    np.testing.assert_array_equal(q, [s[1] for s in streamed])
    assert np.all(frames.can_id[rows] == 0x2A5)


@pytest.mark.parametrize("workers", [2, 3])
def test_threaded_decoding_matches(workers):
    frames = CanArrays.from_messages(fuzz_messages(5000, seed=2))
    one, many = decode_arrays(frames), decode_arrays(frames, workers=workers)
    assert np.array_equal(one.status, many.status) and np.array_equal(one.cls_index, many.cls_index)
    assert one.tables.keys() == many.tables.keys()
    for name in one.tables:
        for col in one.tables[name]:
            np.testing.assert_array_equal(one.tables[name][col], many.tables[name][col])


def test_round_trip_through_messages_and_files(tmp_path):
    messages = fuzz_messages(2000, seed=4)
    frames = CanArrays.from_messages(messages)
    again = CanArrays.from_messages(frames.messages())
    for a, b in zip((frames.t, frames.can_id, frames.length, frames.data, frames.flags),
                    (again.t, again.can_id, again.length, again.data, again.flags)):
        np.testing.assert_array_equal(a, b[: len(a)] if a.ndim == 1 else b)
    assert len(decode_arrays(CanArrays.from_messages([])).status) == 0
