"""Joint state at frame times: interpolation, gaps flagged, never extrapolated; the baselines;
the history buffer the reader thread fills."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from manisplat.recorder.sync import (FLAG_BEFORE, FLAG_GAP, FLAG_HELD, JointHistory, latest_at_arrival,
                                     nearest_sample, sync_joints)

T = np.array([0.0, 0.005, 0.010, 0.050, 0.055])
V = np.array([[0.0, 1.0], [0.5, 1.0], [1.0, 1.0], [5.0, 2.0], [5.5, 2.0]])


def test_interpolates_between_the_samples_around_each_frame() -> None:
    r = sync_joints(T, V, np.array([0.0, 0.0025, 0.010, 0.0525]), max_gap_s=0.015)
    np.testing.assert_allclose(r.values, [[0.0, 1.0], [0.25, 1.0], [1.0, 1.0], [5.25, 2.0]], atol=1e-12)
    np.testing.assert_allclose(r.gap, [0.005, 0.005, 0.04, 0.005], atol=1e-12)
    # a sample time: exact, bracketed by the gap that follows it (t=0.010 -> [0.010, 0.050])
    assert r.flags.tolist() == [0, 0, FLAG_GAP, 0]


def test_a_frame_in_a_dropout_is_flagged_not_hidden() -> None:
    r = sync_joints(T, V, np.array([0.030]), max_gap_s=0.015)
    assert r.flags[0] == FLAG_GAP and r.gap[0] == pytest.approx(0.04)
    np.testing.assert_allclose(r.values[0], [3.0, 1.5])  # still the interpolation, flagged


def test_never_extrapolates_after_the_last_or_before_the_first_sample() -> None:
    r = sync_joints(T, V, np.array([-0.01, 0.07]), max_gap_s=0.015)
    assert r.flags.tolist() == [FLAG_BEFORE, FLAG_HELD]
    np.testing.assert_array_equal(r.values, [V[0], V[-1]])
    np.testing.assert_allclose(r.gap, [0.01, 0.015])


def test_needs_samples() -> None:
    with pytest.raises(ValueError, match="N >= 1"):
        sync_joints(np.zeros(0), np.zeros((0, 7)), np.array([0.0]), 0.01)


@settings(max_examples=50, deadline=None)
@given(st.integers(2, 40), st.integers(0, 10_000))
def test_matches_numpy_interp_inside_the_range(n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.001, 0.01, n))
    v = rng.normal(size=(n, 7))
    q = rng.uniform(t[0], t[-1], 20)
    r = sync_joints(t, v, q, max_gap_s=1.0)
    expected = np.stack([np.interp(q, t, v[:, j]) for j in range(7)], axis=1)
    np.testing.assert_allclose(r.values, expected, atol=1e-12)
    assert not r.flags.any()


def test_baselines() -> None:
    frames = np.array([0.0021, 0.0029, 0.052])
    np.testing.assert_array_equal(nearest_sample(T, V, frames), V[[0, 1, 3]])
    arrival = T + 0.001
    np.testing.assert_array_equal(latest_at_arrival(arrival, V, np.array([0.0005, 0.0065, 0.2])), V[[0, 1, 4]])


def test_history_refuses_time_going_back_and_keeps_the_newest_samples() -> None:
    h = JointHistory(dims=2, capacity=8)
    assert h.sync(0.0, 0.01) is None and h.latest() is None
    for k in range(30):
        assert h.append(k * 0.005, np.array([k, -k]))
    assert not h.append(0.0, np.array([0, 0])) and h.refused == 1
    assert len(h) == 8 and h.first_t == pytest.approx(22 * 0.005) and h.last_t == pytest.approx(29 * 0.005)
    values, gap, flags = h.sync(27.5 * 0.005, 0.01)
    np.testing.assert_allclose(values, [27.5, -27.5]) and gap == pytest.approx(0.005) and flags == 0
    times, vals = h.since(28 * 0.005 - 1e-9)
    np.testing.assert_allclose(vals[:, 0], [28, 29])
    times, vals = h.around(0.0)  # before the kept window: only its first sample
    assert vals[:, 0].tolist() == [22]
