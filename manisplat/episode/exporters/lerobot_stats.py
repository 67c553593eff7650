"""Feature statistics as LeRobot computes and stores them (``meta/stats.json`` and the episodes'
``stats/<feature>/<stat>`` columns): min, max, mean, std (population), count and the quantiles
q01, q10, q50, q90, q99; images per channel in [0, 1] with shape (3, 1, 1) from sampled frames."""

from __future__ import annotations

import numpy as np

QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
STATS_SAMPLES_MIN, STATS_SAMPLES_MAX = 100, 10_000
"""Frames of an episode sampled for image stats, as LeRobot does: all up to 100, then T^0.75."""


def _quantiles(values: np.ndarray) -> dict[str, np.ndarray]:
    """q01..q99 per column of (N, D) ``values`` (each column's mean when N < 2, as LeRobot does)."""
    if len(values) < 2:
        mean = values.mean(axis=0)
        return {f"q{round(q * 100):02d}": mean.copy() for q in QUANTILES}
    out = np.quantile(values, QUANTILES, axis=0)
    return {f"q{round(q * 100):02d}": out[k] for k, q in enumerate(QUANTILES)}


def vector_stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """LeRobot stats of (N, D) or (N,) ``values``: per column min/max/mean/std (population),
    count [N] and quantiles q01, q10, q50, q90, q99; each of shape (D,) (or (1,) for (N,))."""
    values = np.asarray(values, dtype=np.float64).reshape(len(values), -1)
    return {"min": values.min(axis=0), "max": values.max(axis=0), "mean": values.mean(axis=0),
            "std": values.std(axis=0), "count": np.array([len(values)]), **_quantiles(values)}


def stats_sample_indices(length: int) -> np.ndarray:
    """Frames whose images enter an episode's image stats (LeRobot's ``sample_indices``)."""
    count = min(length, max(STATS_SAMPLES_MIN, min(int(length ** 0.75), STATS_SAMPLES_MAX)))
    return np.unique(np.round(np.linspace(0, length - 1, count)).astype(np.int64))


def _downsample(image: np.ndarray) -> np.ndarray:
    """LeRobot's ``auto_downsample_height_width``: stride to ~150 px when the long side is >= 300."""
    height, width = image.shape[:2]
    if max(height, width) < 300:
        return image
    step = int(width / 150) if width > height else int(height / 150)
    return image[::step, ::step]


class ImageStats:
    """Per-channel stats of sampled frames, in [0, 1], from exact 256-level histograms."""

    def __init__(self) -> None:
        self.histogram = np.zeros((3, 256), dtype=np.int64)
        self.count = 0

    def add(self, rgb: np.ndarray) -> None:
        pixels = _downsample(rgb).reshape(-1, 3)
        for c in range(3):
            self.histogram[c] += np.bincount(pixels[:, c], minlength=256)
        self.count += 1

    def result(self) -> dict[str, np.ndarray]:
        levels = np.arange(256) / 255.0
        total = self.histogram.sum(axis=1)
        mean = self.histogram @ levels / total
        std = np.sqrt(np.maximum(self.histogram @ levels ** 2 / total - mean ** 2, 0.0))
        present = self.histogram > 0
        stats = {"min": levels[present.argmax(axis=1)], "max": levels[255 - present[:, ::-1].argmax(axis=1)],
                 "mean": mean, "std": std}
        cumulative = np.cumsum(self.histogram, axis=1)
        for q in QUANTILES:  # the lowest level with at least q of the pixels at or below it
            rank = np.array([np.searchsorted(cumulative[c], q * total[c]) for c in range(3)])
            stats[f"q{round(q * 100):02d}"] = levels[rank]
        out = {k: v.reshape(3, 1, 1) for k, v in stats.items()}
        out["count"] = np.array([self.count])
        return out


class DepthStats:
    """Scalar stats (shape (1,)) of a depth column over every pixel of the sampled frames, in mm."""

    def __init__(self) -> None:
        self.samples: list[np.ndarray] = []

    def add(self, depth_mm: np.ndarray) -> None:
        self.samples.append(_downsample(depth_mm).ravel())

    def result(self) -> dict[str, np.ndarray]:
        stats = vector_stats(np.concatenate(self.samples)[:, None])
        stats["count"] = np.array([len(self.samples)])
        return stats


def aggregate_stats(per_episode: list[dict[str, dict[str, np.ndarray]]]) -> dict[str, dict[str, np.ndarray]]:
    """Dataset stats from episode stats, as LeRobot aggregates them: min of mins, max of maxes,
    count-weighted mean, pooled variance, count-weighted mean of each quantile."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for key in per_episode[0]:
        stats = [ep[key] for ep in per_episode]
        counts = np.array([s["count"][0] for s in stats], dtype=np.float64)
        weights = (counts / counts.sum()).reshape(-1, *([1] * stats[0]["mean"].ndim))
        means = np.stack([s["mean"] for s in stats])
        mean = (weights * means).sum(axis=0)
        variance = (weights * (np.stack([s["std"] for s in stats]) ** 2 + (means - mean) ** 2)).sum(axis=0)
        merged = {"min": np.min([s["min"] for s in stats], axis=0), "max": np.max([s["max"] for s in stats], axis=0),
                  "mean": mean, "std": np.sqrt(variance), "count": np.array([int(counts.sum())])}
        for q in QUANTILES:
            name = f"q{round(q * 100):02d}"
            merged[name] = (weights * np.stack([s[name] for s in stats])).sum(axis=0)
        out[key] = merged
    return out


def as_lists(stats: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, list]]:
    return {key: {name: value.tolist() for name, value in feature.items()} for key, feature in stats.items()}
