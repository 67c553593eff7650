"""How faithfully the twin draws the object where augmentation moved it: each augmented
demonstration's first frame against the simulator's render of the same start.

The simulator's object starts where the demonstration's own rigid motion (its first skill's
``T`` in ``augmentation.json``) takes the source's start pose; the robot stands at the source's
first joints there and at the demonstration's own in the twin's image, so robot pixels are left
out. Scored per start: the object region (both masks' union, grown by :data:`GROW` px) PSNR, the
outline overlap (IoU of the two masks), the twin's object area over the simulator's and the rest
of the image (which holds the arms' shadows, different as the arms stand differently); then by
the start's turn from the source's yaw and its distance from the base (the bins where the
policies fail, docs/benchmarks.md), and a sheet of the worst starts (twin above simulator)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_dilation

GROW = 2  # px: the object region reaches this far past both outlines (the edges are where they differ)
TURN_BINS_DEG = (-22.0, 22.0)  # clockwise beyond the first, counter-clockwise beyond the second
PSNR_MAX = 100.0  # dB: what identical pixels score
CROP = 48  # px: the side of the sheet's squares around the object
NEAR_M, FAR_M = 0.27, 0.32  # the policy benchmark's near-the-base and far bins (x-y distance from the base)


@dataclass(frozen=True)
class StartScore:
    """One augmented demonstration's first frame against the simulator's."""

    episode: str
    turn_deg: float
    distance_m: float
    object_psnr: float
    outline_iou: float
    area_ratio: float
    rest_psnr: float
    object_px: int


def simulator_start(folder: Path, T_source_start: np.ndarray, name: str) -> tuple[float, float, float]:
    """(x m, y m, yaw rad) of the simulator's ``name`` at the start of the augmented demonstration
    ``folder``: its first skill on ``name`` moves the source's start pose ``T_source_start`` [4, 4]."""
    segments = json.loads((folder / "augmentation.json").read_text())["segments"]
    skill = next((s for s in segments if s["kind"] == "skill" and s["object"] == name), None)
    if skill is None:
        raise ValueError(f"{folder}: no skill moves {name!r}")
    T = np.asarray(skill["T"], np.float64) @ T_source_start
    return float(T[0, 3]), float(T[1, 3]), math.atan2(T[1, 0], T[0, 0])


def score_start(episode: str, twin_rgb: np.ndarray, twin_mask: np.ndarray, sim_rgb: np.ndarray, sim_mask: np.ndarray,
                object_label: int, robot_labels: list[int], turn_deg: float, distance_m: float) -> StartScore:
    """Score one start: images [H, W, 3] uint8, masks [H, W] labels (the same values in both)."""
    twin_object, sim_object = twin_mask == object_label, sim_mask == object_label
    robot = np.isin(twin_mask, robot_labels) | np.isin(sim_mask, robot_labels)
    region = binary_dilation(twin_object | sim_object, iterations=GROW) & ~robot
    union = (twin_object | sim_object).sum()
    return StartScore(episode, turn_deg, distance_m, _psnr(twin_rgb, sim_rgb, region),
                      float((twin_object & sim_object).sum() / union) if union else float("nan"),
                      float(twin_object.sum() / sim_object.sum()) if sim_object.any() else float("nan"),
                      _psnr(twin_rgb, sim_rgb, ~region & ~robot), int(sim_object.sum()))


def by_bin(scores: list[StartScore]) -> dict[str, dict[str, float | int]]:
    """Mean object PSNR, outline IoU, area ratio and rest PSNR of the starts in each bin (and of all)."""
    low, high = TURN_BINS_DEG
    bins = {"all": scores,
            f"clockwise_beyond_{-low:g}_deg": [s for s in scores if s.turn_deg < low],
            f"within_{high:g}_deg": [s for s in scores if low <= s.turn_deg <= high],
            f"counter_clockwise_beyond_{high:g}_deg": [s for s in scores if s.turn_deg > high],
            f"near_base_under_{NEAR_M:g}_m": [s for s in scores if s.distance_m < NEAR_M],
            f"far_from_base_over_{FAR_M:g}_m": [s for s in scores if s.distance_m >= FAR_M]}
    return {name: {"starts": len(group),
                   "object_psnr": _mean([s.object_psnr for s in group]),
                   "outline_iou": _mean([s.outline_iou for s in group]),
                   "area_ratio": _mean([s.area_ratio for s in group]),
                   "rest_psnr": _mean([s.rest_psnr for s in group])} for name, group in bins.items()}


def object_crops(twin_rgb: np.ndarray, sim_rgb: np.ndarray, sim_object: np.ndarray, size: int = CROP
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The two images' [size, size, 3] squares centred on the simulator's object (``sim_object``
    [H, W] bool; the image's centre without it)."""
    rows, cols = np.nonzero(sim_object)
    centre = (int(rows.mean()), int(cols.mean())) if len(rows) else (sim_object.shape[0] // 2, sim_object.shape[1] // 2)
    half = size // 2

    def crop(image: np.ndarray) -> np.ndarray:
        padded = np.pad(image, ((half, half), (half, half), (0, 0)))
        return padded[centre[0]: centre[0] + size, centre[1]: centre[1] + size]

    return crop(twin_rgb), crop(sim_rgb)


def worst_first(scores: list[StartScore], crops: list[tuple[np.ndarray, np.ndarray]], out: Path,
                count: int = 8, zoom: int = 3) -> Path:
    """A sheet of the ``count`` starts whose object region scored lowest: the twin's crop above the
    simulator's, each labelled with its turn and PSNR; written to ``out`` (PNG)."""
    import cv2

    order = sorted(range(len(scores)), key=lambda i: scores[i].object_psnr)[:count]
    columns = []
    for i in order:
        twin, sim = (cv2.resize(c, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST) for c in crops[i])
        column = np.concatenate([twin, sim], axis=0).copy()
        label = f"{scores[i].turn_deg:+.0f}deg {scores[i].object_psnr:.1f}dB"
        cv2.putText(column, label, (3, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        columns.append(column)
    sheet = np.concatenate(columns, axis=1) if columns else np.zeros((2 * CROP * zoom, CROP * zoom, 3), np.uint8)
    cv2.imwrite(str(out), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    return out


def _psnr(a: np.ndarray, b: np.ndarray, region: np.ndarray) -> float:
    """PSNR (dB, 8-bit) of ``a`` against ``b`` over ``region`` [H, W] bool, at most
    :data:`PSNR_MAX` (identical); NaN over no pixel."""
    if not region.any():
        return float("nan")
    error = float(((a.astype(np.float64) - b.astype(np.float64)) ** 2)[region].mean())
    return min(PSNR_MAX, 10.0 * math.log10(255.0 ** 2 / max(error, 1e-10)))


def _mean(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return round(float(np.mean(finite)), 3) if finite else float("nan")
