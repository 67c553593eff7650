"""How near each evaluation start lies to a training demonstration's start, and how success
depends on it.

A start is (x m, y m, yaw rad) of the object in the simulator's frame. The distance between two
starts is the Euclidean norm of their differences divided by the evaluation's half-ranges
(8 cm, 8 cm, 45 deg: 1.0 is a half-range; the yaw difference wrapped to [-pi, pi)). Each
evaluation start's distance to its nearest training start says how far the policy must
generalise there; success counted within distance bins says whether the demonstrations' spread
is what limits it (few training starts near a failed one) or something else (failures where
training starts are near).
"""

from __future__ import annotations

import math

import numpy as np

#: the bins' edges, in half-ranges: near, between, far
DISTANCE_EDGES = (0.35, 0.5)


def nearest_distances(eval_starts: np.ndarray, training_starts: np.ndarray, half_ranges: tuple[float, float, float]
                      ) -> np.ndarray:
    """[E] distance of each of ``eval_starts`` [E, 3] to the nearest of ``training_starts`` [N, 3]
    (both (x m, y m, yaw rad)), in the half-ranges ``half_ranges`` (m, m, rad)."""
    eval_starts = np.asarray(eval_starts, np.float64).reshape(-1, 3)
    training_starts = np.asarray(training_starts, np.float64).reshape(-1, 3)
    scale = np.asarray(half_ranges, np.float64)
    if not len(training_starts) or not (np.isfinite(scale).all() and (scale > 0).all()):
        raise ValueError(f"need training starts and positive half-ranges, got {len(training_starts)} and {half_ranges}")
    delta = eval_starts[:, None, :] - training_starts[None, :, :]
    delta[..., 2] = (delta[..., 2] + math.pi) % (2 * math.pi) - math.pi
    return np.linalg.norm(delta / scale, axis=2).min(axis=1)


def success_by_distance(distances: np.ndarray, successes: np.ndarray, edges: tuple[float, ...] = DISTANCE_EDGES
                        ) -> dict:
    """Starts and successes in each distance bin, and the median distance of the successful
    and the failed starts (None where there are none); ``distances`` [E], ``successes`` [E] bool."""
    distances, successes = np.asarray(distances, np.float64), np.asarray(successes, bool)
    bounds = [0.0, *edges, math.inf]
    bins = {}
    for low, high in zip(bounds[:-1], bounds[1:]):
        inside = (distances >= low) & (distances < high)
        name = f"under_{high:g}" if low == 0 else f"over_{low:g}" if math.isinf(high) else f"{low:g}_to_{high:g}"
        bins[name] = {"starts": int(inside.sum()), "successes": int(successes[inside].sum())}

    def median(values: np.ndarray) -> float | None:
        return round(float(np.median(values)), 3) if len(values) else None

    return {"bins": bins, "median_distance_succeeded": median(distances[successes]),
            "median_distance_failed": median(distances[~successes]),
            "p90_distance": round(float(np.quantile(distances, 0.9)), 3) if len(distances) else None}
