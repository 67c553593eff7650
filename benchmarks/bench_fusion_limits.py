"""Where a fused twin's box region loses at new poses: its outline, its inside, a shift's price.

Issue 34: what a fraction of a pixel of placement costs in the box region.

    python -m benchmarks fusion_limits --work DIR [--counts 1,5,20] [--supersample N] [--out JSON]

Reads the work folder of ``python -m benchmarks reconstruct_fusion --work DIR`` and trains nothing
(and draws nothing but with ``--supersample``): per twin, its new demonstrations' frames
(``aug_N/episode_*``) against the simulator's renders of the same states (``aug_N/sim_states``),
and its held-out frames
(``twin_N/renders/test``) against the recorded ones (``demos``). Over the frames that show the box
(at least 20 of its pixels in the simulator's or the recording's mask):

* the box region's PSNR, split into its **outline** (the region less its 5 x 5 erosion: pixels
  within 2 px of its edge) and its **inside**, and the outline's share of the squared error;
* the **best image shift** of our frames, one per demonstration (within +-1 px in steps of 0.25,
  bilinear), and the PSNR it reaches: what a placement error of under a pixel costs. It is chosen
  by the simulator's renders: a diagnosis, not a score;
* **the price of a shift** on the simulator's own renders: each frame against itself moved by 0.25
  and 0.5 px (the four directions, bilinear): what a render right in all but that placement scores;
* **by phase and face** (``by_phase``): the box region's pooled PSNR at new poses while the box
  stands where the demonstration starts it, while it is carried and where it is placed (its drawn
  poses, ``object_poses.npz``), each split by the face of the simulator's box each pixel's ray hits
  (its top, its sides, its bottom; the box's size from the simulator's scene, its poses from
  ``aug_N/sim_input``): whether what the twin misses at new poses is the faces the key light
  shades differently when the box is turned, or all of it; again over the demonstrations that
  turn the box no more than ``manisplat-augment``'s warning (15 deg) from every view the twin's
  demonstrations had of it (``by_phase_seen_views``: a face never recorded weighs on the rest);
* with ``--supersample N`` (the simulator's python in ``MANISPLAT_SIMENV``), the same states drawn
  N x N times finer and averaged, as a camera's pixels integrate their area
  (``sim_render_states.py --supersample``, into ``aug_N/sim_states_xN``): the box region of the
  simulator's own images against them, by phase (how far the simulator's texture filtering is from
  a camera's), and ours against them.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks._harness import BENCH_DIR, MissingBenchmarkData, machine_info, simulator_python
from benchmarks._simulator import SimJob, run_sim_jobs, sim_tools
from benchmarks.bench_reconstruct_fusion import SOURCE, STATE_RENDERER
from manisplat.episode.images import MASK, RGB, ImageKind, load_image

OWN_OPTIONS = True
OBJECT = "box"
MIN_PIXELS = 20  # frames showing fewer of the box's pixels are left out
OUTLINE_ERODE = 5  # px, the erosion's square: the outline is 2 px wide
SHIFTS = np.arange(-1.0, 1.001, 0.25)  # px, the best shift's grid along x and y
PRICES = (0.25, 0.5)  # px, the shifts whose price the simulator's own renders tell
PHASES = ("start", "carried", "placed")
FACES = ("top", "side", "bottom")  # face_kinds' codes 0, 1, 2
AT_REST_M = 1e-4  # a drawn pose within this of the first (last) one's position: where it starts (is placed)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks fusion_limits", description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, required=True, help="a reconstruct_fusion work folder (its --work)")
    p.add_argument("--counts", default="1,5,20", help="the twins to read, by episodes (default 1,5,20)")
    p.add_argument("--supersample", type=int, default=0, metavar="N",
                   help="also draw the new demonstrations' states N x N finer, averaged (needs MANISPLAT_SIMENV)")
    p.add_argument("--out", type=Path, default=BENCH_DIR / "results_reconstruct" / "fusion_limits.json")
    args = p.parse_args(argv)
    if args.supersample == 1 or args.supersample < 0:
        p.error(f"--supersample takes 2 or more (0: not drawn), not {args.supersample}")
    simenv = simulator_python() if args.supersample else None
    if any(args.work.glob("demos_x*")):
        raise MissingBenchmarkData(f"{args.work} was made with reconstruct_fusion --supersample: its twins learnt from "
                                   "supersampled recordings, and this reads the simulator's own")
    started = time.perf_counter()
    twins = {}
    for count in (int(c) for c in args.counts.split(",")):
        twin, aug = args.work / f"twin_{count}", args.work / f"aug_{count}"
        if not (aug / "sim_states").is_dir() or not (twin / "renders" / "test").is_dir():
            raise MissingBenchmarkData(f"{args.work}: no twin_{count} with renders and aug_{count} with sim_states "
                                       "(run python -m benchmarks reconstruct_fusion --work there first)")
        fine = None
        if simenv is not None:
            fine = _supersampled(simenv, aug, args.work / "demos" / SOURCE, args.supersample)
        twins[str(count)] = {"new_poses": _new_poses(aug, fine), "held_out": _held_out(twin, args.work / "demos")}
        print(f"{count} episodes: {json.dumps(twins[str(count)])}", flush=True)
    result = {"benchmark": "fusion_limits", "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
              "command": "python -m benchmarks fusion_limits " + " ".join(argv if argv is not None else sys.argv[1:]),
              "machine": machine_info(), "object": OBJECT, "supersample": args.supersample, "twins": twins,
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


def box_half_extents() -> np.ndarray:
    """Half sizes [3] (m) of the simulator's box (``pick_place_scene.xml``'s ``box_geom``; read with
    a pattern: MuJoCo takes comments that strict XML refuses)."""
    scene = sim_tools() / "pick_place_scene.xml"
    found = re.search(r'<geom\s+name="box_geom"[^>]*?\ssize="([^"]+)"', scene.read_text())
    if found is None:
        raise MissingBenchmarkData(f"{scene} has no geom named box_geom with a size")
    return np.array([float(v) for v in found.group(1).split()])


def face_kinds(K: np.ndarray, T_base_cam: np.ndarray, T_base_box: np.ndarray, half: np.ndarray,
               region: np.ndarray) -> np.ndarray:
    """For each pixel of ``region`` [H, W] bool, the face of a box (half sizes ``half`` [3] m, at
    ``T_base_box`` [4, 4], its z axis up when it stands) that the pixel centre's ray from a camera
    (intrinsics ``K`` [3, 3], ``T_base_cam`` [4, 4], OpenCV axes) hits first: 0 top, 1 side, 2
    bottom (by the face's normal in the base frame), -1 a ray that misses. Returns [N] int8 in
    ``region``'s row-major order."""
    rows, cols = np.nonzero(region)
    rays = np.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], np.ones(len(rows))], -1)
    T_box_cam = np.linalg.inv(T_base_box) @ T_base_cam
    origin, directions = T_box_cam[:3, 3], rays @ T_box_cam[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):  # rays parallel to a slab: +-inf, handled by the min/max
        near_planes = np.minimum((-half - origin) / directions, (half - origin) / directions)
        far_planes = np.maximum((-half - origin) / directions, (half - origin) / directions)
    near, far = np.nan_to_num(near_planes, nan=-np.inf).max(1), np.nan_to_num(far_planes, nan=np.inf).min(1)
    axis = np.nan_to_num(near_planes, nan=-np.inf).argmax(1)
    normals = np.zeros((len(rows), 3))
    normals[np.arange(len(rows)), axis] = -np.sign(directions[np.arange(len(rows)), axis])  # faces the ray
    up = (normals @ T_base_box[:3, :3].T)[:, 2]
    kinds = np.where(up > 0.5, 0, np.where(up < -0.5, 2, 1)).astype(np.int8)
    return np.where((near <= far) & (far > 0), kinds, -1).astype(np.int8)


def phases_of(poses: np.ndarray) -> list[str]:
    """Each frame's phase by the drawn object poses [T, 4, 4]: "start" where the object is where
    the first frame has it, "placed" where the last frame has it, "carried" between."""
    first, last = poses[0, :3, 3], poses[-1, :3, 3]
    return ["start" if np.linalg.norm(T[:3, 3] - first) < AT_REST_M else
            "placed" if np.linalg.norm(T[:3, 3] - last) < AT_REST_M else "carried" for T in poses]


def _supersampled(simenv: Path, aug: Path, parent: Path, n: int) -> Path:
    """``aug``'s new demonstrations' states drawn ``n`` x ``n`` finer and averaged, in
    ``aug/sim_states_x{n}`` (drawn once; kept)."""
    out = aug / f"sim_states_x{n}"
    inputs = sorted(p for p in (aug / "sim_input").iterdir() if p.is_dir())
    run_sim_jobs(simenv, [SimJob(str(STATE_RENDERER), (str(path), "--parent", str(parent), "--render",
                                                       str(out / path.name), "--supersample", str(n)),
                                 out / path.name / "render.json") for path in inputs])
    return out


def _new_poses(aug: Path, fine: Path | None = None) -> dict:
    """:func:`summary` of a twin's new demonstrations against the simulator's renders of their
    states, the best shift per demonstration, the price of a shift on those renders and the box
    region's pooled PSNR by phase and face; with ``fine`` (the same states supersampled), the
    box region's pooled PSNR by phase of the simulator's renders and of ours against those."""
    from manisplat.augment.views import UNSEEN_WARN_DEG
    from manisplat.episode import Episode

    half = box_half_extents()
    view_change = {s["episode"]: s["view_change_deg"].get(OBJECT)
                   for s in json.loads((aug / "augment_report.json").read_text())["samples"] if s["valid"]}
    parts, best, prices = [], {}, {str(s): [] for s in PRICES}
    pooled = {(over, phase, face): [0.0, 0] for over in ("by_phase", "by_phase_seen_views") for phase in PHASES
              for face in ("all", *FACES)}
    against_fine = {(who, phase): [0.0, 0] for who in ("simulator", "ours") for phase in PHASES}
    for path in sorted(aug.glob("episode_*")):
        ours = Episode.open(path)
        box = [v for v, name in ours.meta.labels.items() if name == f"object/{OBJECT}"]
        sim = aug / "sim_states" / path.name
        K, T_base_cam = np.asarray(ours.meta.camera.K, float), np.asarray(ours.meta.camera.T_mount_cam, float)
        with np.load(aug / "sim_input" / path.name / "object_poses.npz") as drawn:
            in_simulator = np.asarray(drawn[OBJECT], float)
        with np.load(path / "object_poses.npz") as drawn:
            phases = phases_of(np.asarray(drawn[OBJECT], float))
        within = (view_change.get(path.name) or 0.0) <= UNSEEN_WARN_DEG
        pools = ("by_phase", "by_phase_seen_views") if within else ("by_phase",)
        frames, errors = 0, np.zeros((len(SHIFTS), len(SHIFTS)))
        for i, (rgb, mask) in enumerate(zip(sorted((sim / "rgb").iterdir()), sorted((sim / "masks").iterdir()))):
            pred = ours.rgb(i).astype(np.float32) / 255
            region = np.isin(_read(mask, MASK, pred), box)
            if region.sum() < MIN_PIXELS:
                continue
            target = _read(rgb, RGB, pred).astype(np.float32) / 255
            squared = ((pred - target) ** 2).mean(-1)[region]
            kinds = face_kinds(K, T_base_cam, in_simulator[i], half, region)
            for face, code in (("all", None), *((f, c) for c, f in enumerate(FACES))):
                chosen = squared if code is None else squared[kinds == code]
                for over in pools:
                    pooled[over, phases[i], face][0] += float(chosen.sum())
                    pooled[over, phases[i], face][1] += int(chosen.size)
            if fine is not None:
                finer = _read(fine / path.name / "rgb" / rgb.name, RGB, pred).astype(np.float32) / 255
                for who, image in (("simulator", target), ("ours", pred)):
                    against_fine[who, phases[i]][0] += float(((image - finer) ** 2).mean(-1)[region].sum())
                    against_fine[who, phases[i]][1] += int(region.sum())
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
    by_phase = {over: {phase: {face: _pooled_psnr(*pooled[over, phase, face]) for face in ("all", *FACES)}
                       for phase in PHASES} for over in ("by_phase", "by_phase_seen_views")}
    return {**summary(parts), "best_shift": best,
            "best_shift_gain_db": float(np.mean([d["psnr_shifted"] - d["psnr_unshifted"] for d in best.values()])),
            "simulator_shifted_psnr": {k: float(np.mean(v)) for k, v in prices.items()}, **by_phase,
            "view_change_deg": view_change,
            **({} if fine is None else {"against_supersampled": {
                f"{who}_vs_supersampled": {phase: _pooled_psnr(*against_fine[who, phase])["psnr"] for phase in PHASES}
                for who in ("simulator", "ours")}})}


def _pooled_psnr(total: float, pixels: int) -> dict:
    """The PSNR (dB; None without pixels) of a sum of squared errors over ``pixels`` pixels."""
    return {"pixels": pixels, "psnr": psnr_of(total / pixels) if pixels else None}


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
