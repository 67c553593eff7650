"""New object poses: table-plane perturbations (x, y, yaw) of where each manipulated object starts
and, for a pick-and-place, where it is placed; and, when asked, a new start of the arm's joints.

A perturbation keeps the pose's height, roll and pitch: ``T' = [Rz(yaw) R, p + (dx, dy, 0)]``,
the yaw turning the object about the vertical through its own origin. ``dx, dy, yaw`` are drawn
uniformly within +- the ranges, from the draws given (:mod:`manisplat.augment.draws`: a generator,
or a sample's point of an even spread; the same draws give the same targets).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from manisplat.augment.draws import Draws
from manisplat.augment.source import rigid, source_demo


@dataclass
class ObjectTarget:
    """Where an object starts in the new demonstration (``T_start`` [4, 4], base frame) and where a
    pick-and-place leaves it (``T_place`` [4, 4]; None when the object is not placed)."""

    T_start: np.ndarray
    T_place: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.T_start = _pose(self.T_start, "T_start")
        self.T_place = None if self.T_place is None else _pose(self.T_place, "T_place")


def _pose(T, what: str) -> np.ndarray:
    T = np.asarray(T, np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"{what} must be a finite 4x4 pose, got shape {T.shape}")
    return rigid(T)


def perturb(T: np.ndarray, dx: float, dy: float, yaw: float) -> np.ndarray:
    """``T`` moved by ``(dx, dy)`` on the table and turned by ``yaw`` about the vertical through its origin."""
    c, s = math.cos(yaw), math.sin(yaw)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = np.array(T, np.float64, copy=True)
    out[:3, :3] = Rz @ out[:3, :3]
    out[:2, 3] += (dx, dy)
    return out


def _draw(rng: Draws, ranges) -> tuple[float, float, float]:
    rx, ry, ryaw = (float(r) for r in ranges)
    if min(rx, ry, ryaw) < 0 or not all(map(math.isfinite, (rx, ry, ryaw))):
        raise ValueError(f"ranges must be finite and >= 0, got {ranges}")
    return tuple(float(rng.uniform(-r, r)) if r > 0 else 0.0 for r in (rx, ry, ryaw))  # type: ignore[return-value]


def sample_targets(twin, rng: Draws, object_range=(0.08, 0.08, math.radians(45)),
                   target_range=(0.05, 0.05, math.radians(45))) -> dict[str, ObjectTarget]:
    """New start (and place) poses for every manipulated object of ``twin``.

    Args:
        object_range: (x m, y m, yaw rad) half-ranges around the object's source start pose.
        target_range: the same around the source's placed pose (pick-and-place objects only).
    """
    src = source_demo(twin)
    out: dict[str, ObjectTarget] = {}
    for name, obj in src.objects.items():
        if not obj.manipulated:
            continue
        T_start = perturb(obj.T_rest, *_draw(rng, object_range))
        T_place = perturb(obj.T_placed, *_draw(rng, target_range)) if obj.T_placed is not None else None
        out[name] = ObjectTarget(T_start, T_place)
    return out


def sample_start(rng: Draws, q_source: np.ndarray, half_range: float, lower: np.ndarray,
                 upper: np.ndarray) -> np.ndarray:
    """The arm's first joint positions [dof] (rad) for a new demonstration: the source's first ones
    ``q_source`` [dof] moved on every joint by a uniform draw within +-``half_range`` (rad), then
    kept within ``lower``..``upper`` [dof] (rad)."""
    if not (math.isfinite(half_range) and half_range >= 0):
        raise ValueError(f"the start's half-range must be finite and >= 0, got {half_range}")
    q_source = np.asarray(q_source, np.float64)
    return np.clip(q_source + rng.uniform(-half_range, half_range, q_source.shape), lower, upper)
