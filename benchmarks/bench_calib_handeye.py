"""Camera-to-base (eye-to-hand) accuracy: our solver vs every OpenCV hand-eye method, same data.

Board views are rendered by the project itself (``manisplat.calib.render``: true camera model,
1280x720, f = 900 px, supersampled, Gaussian blur sigma 0.8 px, grey-level noise 2), detected
with OpenCV's CharucoDetector, and every detected corner gets N(0, 0.2 px) more noise. Each
trial draws a new scene (camera ~1 m from the workspace, board 5-10 cm off the flange) and 15
random board poses (0.45-0.85 m, tilts up to 40 deg). Robot poses are exact. Per trial every
method sees the same views: ours (closed form, then the joint reprojection refinement) and each
OpenCV method (calibrateHandEye TSAI/PARK/HORAUD/ANDREFF/DANIILIDIS, calibrateRobotWorldHandEye
SHAH/LI, on the per-view PnP poses).

Part ``main``: 200 trials, 15 poses. Part ``poses``: 3..50 poses (40 trials, nested subsets of
50 views). Part ``noise``: 0..2 px added corner noise at 15 poses (40 trials). A failure
(error raised, NaN, identity) counts as failed and is left out of the medians. Writes
``calib_handeye.png`` (error against poses and noise).

Rows: part, method, n_poses, noise_px, trials, failed, rot_med_deg, rot_p90_deg, trans_med_mm, trans_p90_mm.
"""

from __future__ import annotations

import time

import numpy as np

from benchmarks._harness import BenchContext
from manisplat.calib.board import BoardSpec
from manisplat.calib.detect import BoardDetector
from manisplat.calib.errors import CalibrationError
from manisplat.calib.handeye import OPENCV_HAND_EYE, OPENCV_ROBOT_WORLD, opencv_closed_forms
from manisplat.calib.poses import pose_difference
from manisplat.calib.render import render_board
from manisplat.calib.solve import solve_hand_eye
from manisplat.calib.synth import default_scene, random_board_poses, robot_poses_for

THREADED = False
METHODS = ("ours", "ours_closed_form") + OPENCV_HAND_EYE + OPENCV_ROBOT_WORLD
GOAL_ROT_DEG, GOAL_TRANS_MM = 0.05, 0.5


def _trial_views(spec, detector, rng, n):
    """Scene, robot poses (n, 4, 4) and detections (ids, clean corners) of n rendered views."""
    sc = default_scene(rng)
    Tcb = random_board_poses(spec, sc.camera, n, rng)
    dets = []
    for T in Tcb:
        d = detector.detect(render_board(spec, sc.camera, T, blur_sigma=0.8, noise_std=2.0, rng=rng))
        dets.append(d)
    return sc, robot_poses_for(sc, Tcb), dets


def _solve_all(spec, detector, sc, A, dets, noise_px, rng) -> dict[str, tuple[float, float] | None]:
    views, keep = [], []
    for k, d in enumerate(dets):
        d2 = type(d)(d.ids, d.corners + rng.normal(0.0, noise_px, d.corners.shape), d.markers)
        v, _ = detector.view(k, d2, sc.camera)
        if v is not None:
            views.append(v)
            keep.append(k)
    out: dict[str, tuple[float, float] | None] = {m: None for m in METHODS}
    A = A[keep]
    try:
        r = solve_hand_eye(views, A, spec, sc.camera, use_opencv=False)
        out["ours"] = pose_difference(r.T_mount_cam, sc.T_base_cam)
        cf = r.closed_forms.get("ours", {})
        if "error" not in cf:
            from manisplat.calib.handeye import closed_form, to_problem
            Ap, B = to_problem("base", A, np.stack([v.T_cam_board for v in views]))
            out["ours_closed_form"] = pose_difference(closed_form(Ap, B)[1], sc.T_base_cam)
    except CalibrationError:
        pass
    if len(views) >= 3:
        for name, res in opencv_closed_forms("base", A, np.stack([v.T_cam_board for v in views])).items():
            if not isinstance(res, str):
                out[name] = pose_difference(res[1], sc.T_base_cam)
    return out


def _rows(part, results, n, noise):
    rows = []
    for m in METHODS:
        vals = [r[m] for r in results if r[m] is not None]
        row = {"part": part, "method": m, "n_poses": n, "noise_px": noise, "trials": len(results),
               "failed": len(results) - len(vals)}
        if vals:
            rot, trans = np.array(vals).T
            row.update(rot_med_deg=float(np.median(rot)), rot_p90_deg=float(np.percentile(rot, 90)),
                       trans_med_mm=float(np.median(trans)), trans_p90_mm=float(np.percentile(trans, 90)))
        rows.append(row)
    return rows


def _plot(rows, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    for col, (part, key, label) in enumerate([("poses", "n_poses", "number of poses"),
                                              ("noise", "noise_px", "added corner noise sigma (px)")]):
        for m in METHODS:
            pts = sorted((r[key], r.get("rot_med_deg"), r.get("trans_med_mm")) for r in rows
                         if r["part"] == part and r["method"] == m and "rot_med_deg" in r)
            if not pts:
                continue
            x, rot, trans = zip(*pts)
            style = dict(lw=2.5, color="k") if m == "ours" else dict(lw=1, alpha=0.8)
            axes[0, col].plot(x, rot, "o-", label=m, ms=3, **style)
            axes[1, col].plot(x, trans, "o-", label=m, ms=3, **style)
        for row, (unit, goal) in enumerate([("rotation error (deg)", GOAL_ROT_DEG), ("translation error (mm)", GOAL_TRANS_MM)]):
            ax = axes[row, col]
            ax.set_yscale("log")
            ax.axhline(goal, color="r", ls="--", lw=1)
            ax.set_xlabel(label)
            ax.set_ylabel("median " + unit)
            ax.grid(True, which="both", alpha=0.3)
            if part == "poses":
                ax.set_xscale("log")
                ax.set_xticks([3, 5, 10, 15, 20, 30, 50], ["3", "5", "10", "15", "20", "30", "50"])
                ax.minorticks_off()
    axes[0, 0].legend(fontsize=7, ncol=2)
    fig.suptitle("camera-to-base error, eye-to-hand, rendered board views (red: goal)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run(ctx: BenchContext) -> list[dict]:
    spec = BoardSpec()
    detector = BoardDetector(spec)
    trials_main = 20 if ctx.quick else 200
    trials_sweep = 5 if ctx.quick else 40
    rows = []
    t0 = time.perf_counter()
    main = []
    for trial in range(trials_main):
        rng = np.random.default_rng(1000 + trial)
        sc, A, dets = _trial_views(spec, detector, rng, 15)
        main.append(_solve_all(spec, detector, sc, A, dets, 0.2, rng))
    rows += _rows("main", main, 15, 0.2)
    counts = [3, 4, 5, 7, 10, 15, 20, 30, 50]
    noises = [0.0, 0.1, 0.2, 0.5, 1.0, 2.0]
    by_n = {n: [] for n in counts}
    by_noise = {s: [] for s in noises}
    for trial in range(trials_sweep):
        rng = np.random.default_rng(5000 + trial)
        sc, A, dets = _trial_views(spec, detector, rng, max(counts))
        for n in counts:
            by_n[n].append(_solve_all(spec, detector, sc, A[:n], dets[:n], 0.2, rng))
        for s in noises:
            by_noise[s].append(_solve_all(spec, detector, sc, A[:15], dets[:15], s, rng))
    for n in counts:
        rows += _rows("poses", by_n[n], n, 0.2)
    for s in noises:
        rows += _rows("noise", by_noise[s], 15, s)
    _plot(rows, ctx.out_dir / "calib_handeye.png")
    ours = next(r for r in rows if r["part"] == "main" and r["method"] == "ours")
    best = min((r for r in rows if r["part"] == "main" and r["method"] in OPENCV_HAND_EYE + OPENCV_ROBOT_WORLD
                and "trans_med_mm" in r), key=lambda r: r["trans_med_mm"])
    ctx.notes.append(f"main: ours {ours['rot_med_deg']:.4f} deg / {ours['trans_med_mm']:.3f} mm median "
                     f"(goal <= {GOAL_ROT_DEG} deg / {GOAL_TRANS_MM} mm); best OpenCV by translation: {best['method']} "
                     f"{best['rot_med_deg']:.4f} deg / {best['trans_med_mm']:.3f} mm; {time.perf_counter() - t0:.0f} s total")
    ctx.notes.append(f"plot: {ctx.out_dir / 'calib_handeye.png'}")
    return rows
