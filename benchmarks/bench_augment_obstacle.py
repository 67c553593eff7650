"""New demonstrations around an obstacle: how often the motions are re-planned (straight,
RRT-Connect, joined at rest), validity with reasons, rate, and an independent clearance check.

Twin: the built-in sample (as in ``augment_plan``: 64 frames, 160x120, a short training). The
obstacle is a cube (``AugmentConfig.obstacles``) centred where the TCP passes halfway through the
source's own transfer (the box's start and place targets unperturbed: the straight transfer goes
through its centre); rows for no cube, a 3 cm and a 6 cm one. Samples as in ``augment_plan``
(object +-8 cm, +-8 cm, +-45 deg; place +-5 cm, +-5 cm, +-45 deg; seed = sample index), so a
sample's transfer passes near the cube, through it, or clear of it.

Columns: cube side (m), workers, n samples, valid, validity, reasons (count per Rejected reason;
a collision by where it was found: ``skill`` frames, moved rigidly with the object and never
re-planned, a ``skill end`` where a motion must start or end, or a re-planned ``motion``),
valid_per_min (wall clock of the batch; each worker's scene set up once, not counted), mean
planning seconds per valid sample, the valid samples' motions by method and how many were joined at
rest (the arm stopped at a skill to turn), and ``tcp_clear_mm_min``: the smallest distance (mm)
from the cube to the TCP over every valid demonstration's frames, the commanded path between them
sampled 10x (independent of the planner's collision model, which checks the arm's and fingers'
meshes: the TCP is the fingertips' centre, so it must stay clear by at least a pad's half-width).
"""

from __future__ import annotations

import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from benchmarks.bench_augment_plan import OBJECT_RANGE, TARGET_RANGE, _sample_twin

SIDES = (0.0, 0.03, 0.06)
_WORKER = None


def _cube_centre(twin) -> np.ndarray:
    """Where the TCP is halfway through the source's own transfer (base frame, m) [3]."""
    import torch

    from manisplat.augment.source import source_demo
    from manisplat.augment.trajectory import AugmentConfig, ObjectTarget, augment_trajectory

    src = source_demo(twin)
    same = {k: ObjectTarget(o.T_rest, o.T_placed) for k, o in src.objects.items() if o.manipulated}
    traj = augment_trajectory(twin, same, AugmentConfig())
    f0, f1 = next(s for s in traj.segments if s["name"] == "M_transfer")["frames"]
    return twin.robot.tcp_pose(torch.as_tensor(traj.q[(f0 + f1) // 2])).numpy()[:3, 3]


def _init(twin_dir: str, side: float, centre: np.ndarray) -> None:
    global _WORKER
    import torch

    torch.set_num_threads(1)
    from manisplat.augment.collision import BoxObstacle
    from manisplat.twin import Twin

    T = np.eye(4)
    T[:3, 3] = centre
    obstacles = (BoxObstacle((side,) * 3, T),) if side > 0 else ()
    _WORKER = (Twin.load(twin_dir), obstacles)
    _one(0)  # builds the scene (kinematics, collision model, allowed pairs) outside the timed batch


def _where(message: str) -> str:
    """Which part of a demonstration a collision was found in: a skill's own frames (moved rigidly
    with the object, never re-planned), a skill's end where a motion starts or ends, or a
    re-planned motion's path."""
    if "configuration collides" in message:
        return "skill end"
    return "skill" if message.split(": ")[1].startswith("S_") else "motion"


def _one(index: int) -> dict:
    from manisplat.augment.trajectory import AugmentConfig, Rejected, augment_trajectory, sample_targets

    twin, obstacles = _WORKER
    targets = sample_targets(twin, np.random.default_rng(index), OBJECT_RANGE, TARGET_RANGE)
    try:
        traj = augment_trajectory(twin, targets, AugmentConfig(obstacles=obstacles, seed=index))
    except Rejected as exc:
        return {"reason": f"{exc.reason} ({_where(str(exc))})" if exc.reason == "collision" else exc.reason}
    return {"reason": None, "planning_s": traj.planner["times_s"]["planning_s"], "q": traj.q,
            "methods": [r["method"] for r in traj.planner["segments"]],
            "at_rest": sum(r.get("joined") == "at rest" for r in traj.planner["segments"])}


def _tcp_clearance(twin, q: np.ndarray, side: float, centre: np.ndarray) -> float:
    """The smallest distance (m) from the cube to the TCP along ``q`` [T, dof], the joint-linear
    path between frames sampled 10x."""
    import torch

    u = np.linspace(0.0, 1.0, 10, endpoint=False)[:, None, None]
    dense = np.concatenate([(q[:-1] + u * (q[1:] - q[:-1])[None]).reshape(-1, q.shape[1]), q[-1:]])
    tcp = twin.robot.tcp_pose(torch.as_tensor(dense)).numpy()[:, :3, 3]
    outside = np.maximum(np.abs(tcp - centre) - side / 2, 0.0)
    return float(np.linalg.norm(outside, axis=1).min())


def _row(twin, twin_dir, side: float, centre: np.ndarray, workers: int, n: int) -> dict:
    with ProcessPoolExecutor(max_workers=workers, initializer=_init, initargs=(str(twin_dir), side, centre)) as pool:
        t0 = time.perf_counter()
        results = list(pool.map(_one, range(n), chunksize=1))
        wall = time.perf_counter() - t0
    valid = [r for r in results if r["reason"] is None]
    reasons = Counter(r["reason"] for r in results if r["reason"] is not None)
    methods = Counter(m for r in valid for m in r["methods"])
    clear = [_tcp_clearance(twin, r["q"], side, centre) for r in valid] if side > 0 else []
    return {"cube_m": side, "workers": workers, "n": n, "valid": len(valid), "validity": len(valid) / n,
            "reasons": ", ".join(f"{k} {v}" for k, v in sorted(reasons.items())) or "-",
            "valid_per_min": len(valid) / wall * 60,
            "planning_s": float(np.mean([r["planning_s"] for r in valid])) if valid else None,
            "motions": ", ".join(f"{k} {v}" for k, v in sorted(methods.items())),
            "joined_at_rest": sum(r["at_rest"] for r in valid),
            "tcp_clear_mm_min": 1000 * min(clear) if clear else None}


def run(ctx) -> list[dict]:
    from manisplat.twin import Twin

    n = 20 if ctx.quick else 100
    twin_dir = _sample_twin(ctx.quick)
    twin = Twin.load(twin_dir)
    centre = _cube_centre(twin)
    ctx.notes.append(f"cube centred at {np.round(centre, 4).tolist()} m (base frame): the TCP halfway through the "
                     "source's transfer")
    ctx.notes.append("threads = worker processes; rates exclude each worker's one-time scene setup")
    return [_row(twin, twin_dir, side, centre, ctx.threads, n) for side in SIDES]
