"""Where each sample's random numbers come from: an even spread, or independent draws.

``even`` (``manisplat-augment``'s default): sample ``k`` takes point ``k`` of a scrambled Sobol
sequence (``scipy.stats.qmc.Sobol``), one coordinate per draw in the order the sampler asks for
them (object start x, y, yaw, then its place, then the arm's start joints). ``random``: sample
``k`` draws from its own generator (``numpy.random.default_rng``), so that any one can be made
again from its seed alone. Fifty independent draws leave holes and clusters in the (x, y, yaw)
box; a low-discrepancy sequence spreads the same number evenly, as a grid would, for any count (a
prefix of the sequence is as even as its length allows; a discarded sample leaves its point
unused). Both give uniform marginals within the same ranges.
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

SAMPLINGS = ("random", "even")
#: coordinates per Sobol point: enough for two arms' objects, places, handover and starts
SOBOL_DIMS = 64


class Draws(Protocol):
    """What a sampler draws from: ``uniform(low, high[, size])`` as ``numpy.random.Generator``."""

    def uniform(self, low: float = 0.0, high: float = 1.0, size=None): ...


class SequencePoint:
    """One point of a low-discrepancy sequence served as successive uniform draws.

    Args:
        point: [dims] coordinates in [0, 1); each ``uniform`` call takes the next ``size`` of them.
    """

    def __init__(self, point: np.ndarray) -> None:
        self._point = np.asarray(point, np.float64)
        self._used = 0

    def uniform(self, low: float = 0.0, high: float = 1.0, size=None):
        count = 1 if size is None else int(np.prod(size))
        if self._used + count > len(self._point):
            raise ValueError(f"an even spread serves {len(self._point)} draws per sample; this sample asks for more")
        u = self._point[self._used:self._used + count]
        self._used += count
        values = low + (high - low) * u
        return float(values[0]) if size is None else values.reshape(size)


class SampleDraws:
    """The draws of every sample of one ``manisplat-augment`` run.

    Args:
        sampling: one of :data:`SAMPLINGS`.
        seed: the run's seed (``--seed``).
        count: how many samples may be drawn at most.
    """

    def __init__(self, sampling: str, seed: int, count: int) -> None:
        if sampling not in SAMPLINGS:
            raise ValueError(f"sampling must be one of {', '.join(SAMPLINGS)}, got {sampling!r}")
        self.seed = int(seed)
        self._points = None
        if sampling == "even":
            from scipy.stats import qmc

            engine = qmc.Sobol(SOBOL_DIMS, scramble=True, seed=np.random.default_rng(self.seed))
            self._points = engine.random_base2(max(0, math.ceil(math.log2(max(1, count)))))[:count]

    def seed_of(self, index: int) -> int:
        """The seed recorded for sample ``index`` (its generator's, with ``random``)."""
        return self.seed * 1_000_003 + index

    def __call__(self, index: int) -> Draws:
        """The draws of sample ``index`` (0-based)."""
        if self._points is None:
            return np.random.default_rng(self.seed_of(index))
        if index >= len(self._points):
            raise IndexError(f"sample {index}: the even spread was made for {len(self._points)} samples")
        return SequencePoint(self._points[index])
