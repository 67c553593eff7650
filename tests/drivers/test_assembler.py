"""The joint-cycle rule: a sample is 0x2A5 -> 0x2A6 -> 0x2A7 consecutive, in order, within the
window; never halves of two cycles. Streaming and vectorised assembly agree."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from manisplat.drivers.piper.assembler import JointAssembler, assemble_joint_samples

PERIOD = 0.005
SPACING = 130e-6


def cycle_frames(k: int, q: np.ndarray) -> list[tuple[int, float, float, float]]:
    """The three joint frames of cycle ``k``: (pair, q_a, q_b, t)."""
    t = k * PERIOD
    return [(p, q[2 * p], q[2 * p + 1], t + (4 + p) * SPACING) for p in range(3)]


def stream(frames, window=0.0025):
    a = JointAssembler(window)
    out = [s for f in frames if (s := a.push(*f)) is not None]
    return out, a


def vector(frames, window=0.0025):
    f = np.array(frames, dtype=np.float64).reshape(-1, 4)
    return assemble_joint_samples(f[:, 0].astype(int), f[:, 1:3], f[:, 3], window)


def q_of(k: int) -> np.ndarray:
    return np.arange(6) + 10.0 * k


def test_complete_cycles_give_samples_stamped_at_their_first_frame():
    frames = [f for k in range(5) for f in cycle_frames(k, q_of(k))]
    out, a = stream(frames)
    assert [s[1].tolist() for s in out] == [q_of(k).tolist() for k in range(5)]
    assert [s[0] for s in out] == [k * PERIOD + 4 * SPACING for k in range(5)]
    assert a.samples == 5 and a.discarded == 0


@pytest.mark.parametrize("lost", [0, 1, 2])
def test_a_lost_frame_drops_only_its_cycle(lost):
    frames = [f for k in range(3) for f in cycle_frames(k, q_of(k))]
    del frames[3 + lost]  # one frame of cycle 1
    out, a = stream(frames)
    assert [s[1][0] for s in out] == [q_of(0)[0], q_of(2)[0]]
    assert a.discarded == 2


def test_halves_of_two_cycles_never_join():
    # 0x2A5 of cycle 0, then (0x2A6, 0x2A7 of cycle 0 and 0x2A5 of cycle 1 lost) 0x2A6, 0x2A7 of cycle 1:
    # the order is right but they are 5 ms apart, more than the window.
    c0, c1 = cycle_frames(0, q_of(0)), cycle_frames(1, q_of(1))
    out, a = stream([c0[0], c1[1], c1[2]])
    assert out == [] and a.discarded == 3
    # with a window longer than a cycle the rule would (wrongly) join them: the window is the guard
    assert len(stream([c0[0], c1[1], c1[2]], window=0.01)[0]) == 1


def test_reordered_repeated_and_backwards_frames_are_dropped():
    c = cycle_frames(0, q_of(0))
    assert stream([c[0], c[2], c[1]])[0] == []
    assert stream([c[0], c[1], c[1], c[2]])[0] == []
    back = (c[2][0], c[2][1], c[2][2], c[0][3] - 1e-4)  # 0x2A7 stamped before 0x2A5
    assert stream([c[0], c[1], back])[0] == []


def test_window_must_be_positive():
    with pytest.raises(ValueError):
        JointAssembler(0.0)


@given(st.lists(st.tuples(st.integers(0, 2), st.floats(0, 0.004)), max_size=60))
def test_streaming_and_vectorised_assembly_agree(events):
    t = 0.0
    frames = []
    for i, (pair, dt) in enumerate(events):
        t += dt
        frames.append((pair, float(i), -float(i), t))
    out, _ = stream(frames)
    tv, qv, first = vector(frames)
    assert len(out) == len(tv)
    assert np.array_equal(np.array([s[0] for s in out]), tv)
    assert np.array_equal(np.array([s[1] for s in out]).reshape(-1, 6), qv)
    assert all(frames[i][0] == 0 for i in first)
