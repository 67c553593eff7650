"""Where each augmented sample's random numbers come from: independent draws made again from a
seed, or an even spread (a scrambled Sobol sequence) that leaves no holes in the ranges."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import qmc

from manisplat.augment.draws import SOBOL_DIMS, SampleDraws


def _first(draws: SampleDraws, count: int, per_sample: int) -> np.ndarray:
    """[count, per_sample] unit draws of samples 0..count-1, taken as the sampler takes them."""
    out = []
    for index in range(count):
        draw = draws(index)
        out.append([draw.uniform(0.0, 1.0) for _ in range(per_sample)])
    return np.array(out)


def test_random_draws_are_each_samples_own_generator():
    draws = SampleDraws("random", 3, 10)
    for index in (0, 7):
        expected = np.random.default_rng(3 * 1_000_003 + index).uniform(-0.1, 0.1, 4)
        np.testing.assert_array_equal(draws(index).uniform(-0.1, 0.1, 4), expected)
    assert draws.seed_of(7) == 3 * 1_000_003 + 7


def test_an_even_spread_puts_one_sample_in_each_slice_of_every_range():
    """64 samples: each coordinate has exactly one value in each 64th of its range, and the first
    two exactly one in each cell of an 8 x 8 grid (Sobol's stratification), where independent
    draws leave slices empty."""
    u = _first(SampleDraws("even", 0, 64), 64, 3)
    for column in u.T:
        assert sorted(np.floor(column * 64).astype(int)) == list(range(64))
    cells = np.floor(u[:, 0] * 8).astype(int) * 8 + np.floor(u[:, 1] * 8).astype(int)
    assert sorted(cells) == list(range(64))
    independent = _first(SampleDraws("random", 0, 64), 64, 3)
    assert len(set(np.floor(independent[:, 0] * 64).astype(int))) < 64


def test_fifty_evenly_spread_samples_cover_the_box_better_than_independent_ones():
    even, independent = _first(SampleDraws("even", 0, 150), 50, 3), _first(SampleDraws("random", 0, 150), 50, 3)
    assert qmc.discrepancy(even) < 0.5 * qmc.discrepancy(independent)


def test_an_even_spread_is_made_again_by_its_seed_and_changed_by_another():
    a, b, c = (_first(SampleDraws("even", seed, 20), 20, 6) for seed in (1, 1, 2))
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_a_samples_point_does_not_depend_on_how_many_may_be_drawn():
    """--n and --max-samples change how many points are made, not which: the same seed gives the
    same first demonstrations."""
    np.testing.assert_array_equal(_first(SampleDraws("even", 5, 10), 10, 6), _first(SampleDraws("even", 5, 300), 10, 6))


def test_an_even_spread_serves_draws_in_order_and_in_range():
    draw = SampleDraws("even", 0, 4)(2)
    first = draw.uniform(-0.1, 0.1)
    rest = draw.uniform(-5.0, 5.0, (2, 3))
    assert isinstance(first, float) and -0.1 <= first < 0.1
    assert rest.shape == (2, 3) and np.all((rest >= -5.0) & (rest < 5.0))
    again = SampleDraws("even", 0, 4)(2)
    assert again.uniform(-0.1, 0.1) == first


def test_a_sample_asking_for_more_draws_than_a_point_holds_is_an_error():
    draw = SampleDraws("even", 0, 2)(0)
    draw.uniform(0.0, 1.0, SOBOL_DIMS - 1)
    with pytest.raises(ValueError, match="draws per sample"):
        draw.uniform(0.0, 1.0, 2)


def test_bad_sampling_and_a_sample_past_the_spread_are_errors():
    with pytest.raises(ValueError, match="random, even"):
        SampleDraws("grid", 0, 4)
    with pytest.raises(IndexError, match="4 samples"):
        SampleDraws("even", 0, 4)(4)
