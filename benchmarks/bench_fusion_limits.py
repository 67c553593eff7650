"""Where a fused twin's box region loses at new poses: its outline, its inside, a shift's price.

Issue 34: what a fraction of a pixel of placement costs in the box region.

    python -m benchmarks fusion_limits --work DIR [--counts 1,5,20] [--out JSON]

Reads the work folder of ``python -m benchmarks reconstruct_fusion --work DIR`` and trains or
renders nothing: per twin, its new demonstrations' frames (``aug_N/episode_*``) against the
simulator's renders of the same states (``aug_N/sim_states``), and its held-out frames
(``twin_N/renders/test``) against the recorded ones (``demos``). Over the frames that show the box
(at least 20 of its pixels in the simulator's or the recording's mask):

* the box region's PSNR, split into its **outline** (the region less its 5 x 5 erosion: pixels
  within 2 px of its edge) and its **inside**, and the outline's share of the squared error;
* the **best image shift** of our frames, one per demonstration (within +-1 px in steps of 0.25,
  bilinear), and the PSNR it reaches: what a placement error of under a pixel costs. It is chosen
  by the simulator's renders: a diagnosis, not a score;
* **the price of a shift** on the simulator's own renders: each frame against itself moved by 0.25
  and 0.5 px (the four directions, bilinear): what a render right in all but that placement scores.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks._harness import BENCH_DIR, MissingBenchmarkData, machine_info
from manisplat.episode.images import MASK, RGB, ImageKind, load_image

OWN_OPTIONS = True
OBJECT = "box"
MIN_PIXELS = 20  # frames showing fewer of the box's pixels are left out
OUTLINE_ERODE = 5  # px, the erosion's square: the outline is 2 px wide
SHIFTS = np.arange(-1.0, 1.001, 0.25)  # px, the best shift's grid along x and y
PRICES = (0.25, 0.5)  # px, the shifts whose price the simulator's own renders tell


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks fusion_limits", description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, required=True, help="a reconstruct_fusion work folder (its --work)")
    p.add_argument("--counts", default="1,5,20", help="the twins to read, by episodes (default 1,5,20)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_reconstruct" / "fusion_limits.json")
    args = p.parse_args(argv)
    started = time.perf_counter()
    twins = {}
    for count in (int(c) for c in args.counts.split(",")):
        twin, aug = args.work / f"twin_{count}", args.work / f"aug_{count}"
        if not (aug / "sim_states").is_dir() or not (twin / "renders" / "test").is_dir():
            raise MissingBenchmarkData(f"{args.work}: no twin_{count} with renders and aug_{count} with sim_states "
                                       "(run python -m benchmarks reconstruct_fusion --work there first)")
        twins[str(count)] = {"new_poses": _new_poses(aug), "held_out": _held_out(twin, args.work / "demos")}
        print(f"{count} episodes: {json.dumps(twins[str(count)])}", flush=True)
    result = {"benchmark": "fusion_limits", "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
              "command": "python -m benchmarks fusion_limits " + " ".join(argv if argv is not None else sys.argv[1:]),
              "machine": machine_info(), "object": OBJECT, "twins": twins,
              "wall_s": round(time.perf_counter() - started, 1)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


def psnr_of(squared: float) -> float:
    """PSNR (dB) of a mean squared error of images in [0, 1]."""
    return float(-10 * np.log10(max(squared, 1e-12)))


def outline_split(pred: np.ndarray, target: np.ndarray, region: np.ndarray) -> dict[str, float]:
    """Squared errors of ``pred`` against ``target`` ([H, W, 3] in [0, 1]) over ``region`` [H, W]
    bool: ``region``'s sum and pixel count, its outline's (within 2 px of its edge) and its inside's."""
    import cv2

    inside = cv2.erode(region.astype(np.uint8), np.ones((OUTLINE_ERODE, OUTLINE_ERODE), np.uint8)).astype(bool)
    squared = ((pred - target) ** 2).mean(-1)
    outline = region & ~inside
    return {"sum": float(squared[region].sum()), "n": int(region.sum()), "outline_sum": float(squared[outline].sum()),
            "outline_n": int(outline.sum()), "inside_sum": float(squared[inside].sum()), "inside_n": int(inside.sum())}


def shifted(image: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``image`` [H, W, C] moved by (dx, dy) px, bilinear, edges repeated."""
    import cv2

    h, w = image.shape[:2]
    return cv2.warpAffine(image, np.float32([[1, 0, dx], [0, 1, dy]]), (w, h), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE)


def shift_errors(pred: np.ndarray, target: np.ndarray, region: np.ndarray) -> np.ndarray:
    """[S, S] mean squared error over ``region`` of ``pred`` moved by every (dx, dy) of :data:`SHIFTS`."""
    out = np.empty((len(SHIFTS), len(SHIFTS)))
    for a, dx in enumerate(SHIFTS):
        for b, dy in enumerate(SHIFTS):
            out[a, b] = ((shifted(pred, dx, dy) - target) ** 2).mean(-1)[region].mean()
    return out


def shift_price(target: np.ndarray, region: np.ndarray, step: float) -> float:
    """Mean squared error over ``region`` of ``target`` against itself moved by ``step`` px (the
    mean over the four directions)."""
    return float(np.mean([((shifted(target, dx, dy) - target) ** 2).mean(-1)[region].mean()
                          for dx, dy in ((step, 0), (-step, 0), (0, step), (0, -step))]))


def summary(parts: list[dict[str, float]]) -> dict[str, float]:
    """Per-frame means of PSNR over the region, its outline and inside, and the outline's share of the
    squared error summed over the frames."""
    return {"frames": len(parts),
            "psnr": float(np.mean([psnr_of(p["sum"] / p["n"]) for p in parts])),
            "psnr_outline": float(np.mean([psnr_of(p["outline_sum"] / p["outline_n"]) for p in parts if p["outline_n"]])),
            "psnr_inside": float(np.mean([psnr_of(p["inside_sum"] / p["inside_n"]) for p in parts if p["inside_n"]])),
            "outline_share_of_error": sum(p["outline_sum"] for p in parts) / max(sum(p["sum"] for p in parts), 1e-12),
            "outline_share_of_pixels": sum(p["outline_n"] for p in parts) / max(sum(p["n"] for p in parts), 1)}


def _new_poses(aug: Path) -> dict:
    """:func:`summary` of a twin's new demonstrations against the simulator's renders of their
    states, the best shift per demonstration and the price of a shift on those renders."""
    from manisplat.episode import Episode

    parts, best, prices = [], {}, {str(s): [] for s in PRICES}
    for path in sorted(aug.glob("episode_*")):
        ours = Episode.open(path)
        box = [v for v, name in ours.meta.labels.items() if name == f"object/{OBJECT}"]
        sim = aug / "sim_states" / path.name
        frames, errors = 0, np.zeros((len(SHIFTS), len(SHIFTS)))
        for i, (rgb, mask) in enumerate(zip(sorted((sim / "rgb").iterdir()), sorted((sim / "masks").iterdir()))):
            pred = ours.rgb(i).astype(np.float32) / 255
            region = np.isin(_read(mask, MASK, pred), box)
            if region.sum() < MIN_PIXELS:
                continue
            target = _read(rgb, RGB, pred).astype(np.float32) / 255
            parts.append(outline_split(pred, target, region))
            errors += shift_errors(pred, target, region)
            frames += 1
            for step in PRICES:
                prices[str(step)].append(psnr_of(shift_price(target, region, step)))
        a, b = np.unravel_index(errors.argmin(), errors.shape)
        centre = len(SHIFTS) // 2
        best[path.name] = {"shift_px": [float(SHIFTS[a]), float(SHIFTS[b])],
                           "psnr_unshifted": psnr_of(errors[centre, centre] / frames),
                           "psnr_shifted": psnr_of(errors[a, b] / frames)}
    return {**summary(parts), "best_shift": best,
            "best_shift_gain_db": float(np.mean([d["psnr_shifted"] - d["psnr_unshifted"] for d in best.values()])),
            "simulator_shifted_psnr": {k: float(np.mean(v)) for k, v in prices.items()}}


def _held_out(twin: Path, demos: Path) -> dict:
    """:func:`summary` of a twin's held-out renders against the recorded frames (frame numbers run
    over its episodes in the twin's order, as ``manisplat-reconstruct`` writes them)."""
    from manisplat.episode import Episode

    meta = json.loads((twin / "twin.json").read_text())
    episodes = [Episode.open(demos / name) for name in [meta["episode"], *[d["episode"] for d in meta.get("demonstrations", [])]]]
    starts = np.cumsum([0] + [len(e) for e in episodes])
    parts = []
    for png in sorted((twin / "renders" / "test").iterdir()):
        frame = int(png.stem)
        k = int(np.searchsorted(starts, frame, side="right")) - 1
        episode, i = episodes[k], frame - int(starts[k])
        box = [v for v, name in episode.meta.labels.items() if name == f"object/{OBJECT}"]
        region = np.isin(episode.mask(i), box)
        if region.sum() < MIN_PIXELS:
            continue
        target = episode.rgb(i).astype(np.float32) / 255
        parts.append(outline_split(_read(png, RGB, target).astype(np.float32) / 255, target, region))
    return summary(parts)


def _read(path: Path, kind: ImageKind, like: np.ndarray) -> np.ndarray:
    """The image ``path`` (an episode's ``RGB`` or ``MASK`` kind, RGB order), checked to be as large
    as ``like`` [H, W, ...] (:func:`~manisplat.episode.images.load_image`: a clear error otherwise)."""
    return load_image(path, kind, like.shape[1], like.shape[0])


if __name__ == "__main__":
    raise SystemExit(main())
