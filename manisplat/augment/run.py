"""What ``manisplat-augment`` does: plan demonstrations until enough are valid, then render and
write them (in parallel processes with ``--workers``), then the report and the TCP-path plot."""

from __future__ import annotations

import argparse
import json
import logging
import shlex
import shutil
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from manisplat.augment.cli import REPORT, load_poses_file
from manisplat.augment.frames import from_centre_frame, to_centre_frame
from manisplat.augment.trajectory import (AugmentConfig, NewTrajectory, ObjectTarget, Rejected, augment_trajectory,
                                          sample_targets)
from manisplat.augment.writer import write_demonstration
from manisplat.episode.fsio import atomic_write_bytes
from manisplat.twin import Twin, TwinFormatError

log = logging.getLogger("manisplat.augment")
PLOT = "tcp_paths.png"
SHEETS = 5  # demonstrations with a contact sheet (sheets/episode_NNNN.png)


class AugmentError(RuntimeError):
    """The reconstruction cannot be augmented (no twin, no phases or poses, bad --poses)."""


@dataclass
class Sample:
    """One drawn sample: its index and seed, targets, and the trajectory or why it was discarded."""

    index: int
    seed: int
    targets: dict[str, ObjectTarget]
    trajectory: NewTrajectory | None = None
    reason: str | None = None
    detail: str | None = None
    plan_s: float = 0.0
    episode: str | None = None


def run_augmentation(args: argparse.Namespace) -> dict:
    """Plan, render, write and report; returns the report written to ``augment_report.json``."""
    start = time.perf_counter()
    logging.getLogger("manisplat.episode").setLevel(logging.WARNING)  # one line per episode written: the bar says it
    twin = _load_twin(args.recon)
    if args.overwrite:
        _remove_earlier(args.out)
    args.out.mkdir(parents=True, exist_ok=True)
    config = AugmentConfig(speed=args.speed, planner_timeout_s=args.planner_timeout, seed=args.seed)
    explicit = _explicit_targets(args.poses, twin) if args.poses else None
    wanted = len(explicit) if explicit is not None else args.n
    limit = len(explicit) if explicit is not None else (args.max_samples or max(10, 3 * args.n))
    object_range = (args.object_range[0], args.object_range[1], np.radians(args.object_range[2]))
    target_range = (args.target_range[0], args.target_range[1], np.radians(args.target_range[2]))

    samples: list[Sample] = []
    bar = tqdm(total=wanted, desc="planning", unit="demo", disable=args.quiet)
    while sum(s.trajectory is not None for s in samples) < wanted and len(samples) < limit:
        index = len(samples)
        seed = args.seed * 1_000_003 + index
        if explicit is not None:
            targets = explicit[index]
        else:
            targets = sample_targets(twin, np.random.default_rng(seed), object_range, target_range)
        sample = Sample(index, seed, targets)
        t0 = time.perf_counter()
        try:
            sample.trajectory = augment_trajectory(twin, targets, config)
            bar.update(1)
        except Rejected as exc:
            sample.reason, sample.detail = exc.reason, exc.detail
            log.debug("sample %d discarded: %s (%s)", index, exc.reason, exc.detail)
        sample.plan_s = time.perf_counter() - t0
        samples.append(sample)
        bar.set_postfix(drawn=len(samples), discarded=sum(s.trajectory is None for s in samples))
    bar.close()
    plan_s = time.perf_counter() - start
    valid = [s for s in samples if s.trajectory is not None]
    for k, s in enumerate(valid):
        s.episode = f"episode_{k:04d}"

    t0 = time.perf_counter()
    _render_and_write(twin, args.recon, valid, args.out, workers=args.workers, image_format=args.image_format,
                      quiet=args.quiet)
    render_s = time.perf_counter() - t0
    _plot_tcp_paths(args.out / PLOT, twin, valid)
    for s in valid[:SHEETS]:
        _contact_sheet(args.out / s.episode, args.out / "sheets" / f"{s.episode}.png")
    report = _report(twin, args, samples, wanted, {"plan": plan_s, "render_and_write": render_s,
                                                   "total": time.perf_counter() - start})
    atomic_write_bytes(args.out / REPORT, (json.dumps(report, indent=1) + "\n").encode())
    return report


def reconstruct_command(recon: Path) -> str:
    """The manisplat-reconstruct command that makes a twin in ``recon``, as it must be typed there
    (``--overwrite`` where the folder already holds something, which it would otherwise refuse)."""
    in_use = recon.is_dir() and any(recon.iterdir())
    return f"manisplat-reconstruct EPISODE --out {shlex.quote(str(recon))}" + " --overwrite" * in_use


def _load_twin(recon: Path) -> Twin:
    try:
        twin = Twin.load(recon)
    except (TwinFormatError, FileNotFoundError) as exc:
        raise AugmentError(f"{exc} (run {reconstruct_command(recon)} first)") from exc
    if len(twin.arms) > 1 or len(twin.cameras) > 1:
        raise AugmentError(f"{recon}: a twin of arms {', '.join(twin.arm_names)} and cameras "
                           f"{', '.join(twin.cameras)}: augmentation re-plans one arm seen by one camera; several arms or "
                           "cameras are not supported yet")
    if not twin.objects:
        raise AugmentError(f"{recon}: the reconstruction has no manipulated object to move")
    for name in twin.objects:
        if not twin.phases.get(name):
            raise AugmentError(f"{recon}: object {name!r} has no Motion/Skill phases in twin.json")
        if name not in twin.object_poses or len(twin.object_poses[name]) != twin.n_frames:
            raise AugmentError(f"{recon}: object {name!r} has no pose per frame in twin.pt")
    return twin


def _explicit_targets(path: Path, twin: Twin) -> list[dict[str, ObjectTarget]]:
    try:
        entries = load_poses_file(path)
    except ValueError as exc:
        raise AugmentError(str(exc)) from exc
    out = []
    for k, entry in enumerate(entries):
        unknown = set(entry) - set(twin.objects)
        if unknown:
            raise AugmentError(f"--poses {path}: entry {k} names {sorted(unknown)}; the twin's objects are "
                               f"{twin.objects}")
        missing = set(twin.objects) - set(entry)
        if missing:
            raise AugmentError(f"--poses {path}: entry {k} gives no pose for {sorted(missing)}")
        out.append({name: ObjectTarget(from_centre_frame(twin, name, p["T_start"]),
                                       None if p.get("T_place") is None else from_centre_frame(twin, name, p["T_place"]))
                    for name, p in entry.items()})
    return out


def _remove_earlier(out: Path) -> None:
    for path in [*out.glob("episode_*"), *out.glob(".partial-episode_*")]:
        shutil.rmtree(path)
    for name in (REPORT, PLOT):
        (out / name).unlink(missing_ok=True)
    shutil.rmtree(out / "sheets", ignore_errors=True)


# ------------------------------------------------------------------ rendering in processes
_WORKER_TWIN: Twin | None = None


def _init_worker(recon: str, backend: str) -> None:
    global _WORKER_TWIN
    import torch

    torch.set_num_threads(1)
    logging.getLogger("manisplat.episode").setLevel(logging.WARNING)
    _WORKER_TWIN = Twin.load(recon, backend=backend)


def _write_one(trajectory: NewTrajectory, path: str, seed: int, image_format: str) -> str:
    assert _WORKER_TWIN is not None
    write_demonstration(_WORKER_TWIN, trajectory, Path(path), seed=seed, image_format=image_format)
    return path


def _render_and_write(twin: Twin, recon: Path, valid: list[Sample], out: Path, *, workers: int, image_format: str,
                      quiet: bool) -> None:
    """Render and write ``valid``: with ``twin`` here, or in ``workers`` processes that each load it from ``recon``."""
    frames = sum(len(s.trajectory.t) for s in valid)
    bar = tqdm(total=frames if workers == 1 else len(valid), desc="rendering",
               unit="frame" if workers == 1 else "demo", disable=quiet)
    if workers == 1:
        for s in valid:
            write_demonstration(twin, s.trajectory, out / s.episode, seed=s.seed, image_format=image_format,
                                on_frame=lambda: bar.update(1))
    else:
        with ProcessPoolExecutor(max_workers=workers, initializer=_init_worker,
                                 initargs=(str(recon), twin.backend)) as pool:
            futures = [pool.submit(_write_one, s.trajectory, str(out / s.episode), s.seed, image_format) for s in valid]
            for future in as_completed(futures):
                future.result()
                bar.update(1)
    bar.close()


# ------------------------------------------------------------------ report and plot
def _report(twin: Twin, args: argparse.Namespace, samples: list[Sample], wanted: int, timing: dict) -> dict:
    valid = [s for s in samples if s.trajectory is not None]
    reasons: dict[str, int] = {}
    for s in samples:
        if s.reason:
            reasons[s.reason] = reasons.get(s.reason, 0) + 1
    motions = [r for s in valid for r in s.trajectory.planner["segments"]]
    skill_mm = [s.trajectory.validation.get("skill_error_mm", 0.0) for s in valid]
    skill_deg = [s.trajectory.validation.get("skill_error_deg", 0.0) for s in valid]
    return {
        "parent": twin.episode, "recon": str(args.recon), "seed": args.seed, "requested": wanted,
        "drawn": len(samples), "valid": len(valid), "written": len(valid),
        "validity_rate": len(valid) / max(len(samples), 1), "reasons": reasons,
        "ranges": {"object": args.object_range, "target": args.target_range, "units": "m, m, deg"},
        "speed": args.speed, "workers": args.workers,
        "skill_error_max": {"mm": max(skill_mm, default=0.0), "deg": max(skill_deg, default=0.0)},
        "motions": {"planned": len(motions), "by_method": dict(Counter(r["method"] for r in motions)),
                    "joined_at_rest": sum(r.get("joined") == "at rest" for r in motions)},
        "timing_s": {k: round(v, 2) for k, v in timing.items()},
        "plan_s_per_sample": round(float(np.mean([s.plan_s for s in samples])) if samples else 0.0, 4),
        "samples": [{"index": s.index, "seed": s.seed, "valid": s.trajectory is not None, "episode": s.episode,
                     "reason": s.reason, "detail": s.detail, "plan_s": round(s.plan_s, 4)} for s in samples],
    }


def _plot_tcp_paths(path: Path, twin: Twin, valid: list[Sample]) -> None:
    """Top view (base x-y, cm) of every new TCP path over the source's, with the new object poses."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    fig, ax = plt.subplots(figsize=(6.5, 6))
    source = twin.robot.tcp_pose(torch.as_tensor(twin.q)).numpy()[:, :2, 3] * 100
    for k, s in enumerate(valid):
        tcp = twin.robot.tcp_pose(torch.as_tensor(s.trajectory.q)).numpy()[:, :2, 3] * 100
        ax.plot(tcp[:, 0], tcp[:, 1], lw=0.8, alpha=0.6, color=f"C{k % 10}")
        for name, poses in s.trajectory.objects.items():
            start, end = (to_centre_frame(twin, name, poses[key])[:2, 3] * 100 for key in ("T_start", "T_end"))
            ax.plot(*start, "o", ms=3, color=f"C{k % 10}")
            ax.plot(*end, "s", ms=3, mfc="none", color=f"C{k % 10}")
    ax.plot(source[:, 0], source[:, 1], "k--", lw=1.8, label="source demonstration")
    ax.plot([], [], "o", color="grey", ms=3, label="object start")
    ax.plot([], [], "s", mfc="none", color="grey", ms=3, label="object end")
    ax.set(xlabel="x (cm, robot base)", ylabel="y (cm)", title=f"TCP paths of {len(valid)} new demonstrations",
           aspect="equal")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _contact_sheet(episode: Path, path: Path, frames: int = 8) -> None:
    """Eight frames of a written demonstration in a 2 x 4 grid, each labelled with its index and time."""
    import cv2

    from manisplat.episode import Episode

    ep = Episode.open(episode)
    chosen = np.linspace(0, len(ep) - 1, frames).round().astype(int)
    tiles = []
    for i in chosen:
        tile = cv2.cvtColor(ep.rgb(int(i)), cv2.COLOR_RGB2BGR)
        cv2.putText(tile, f"{i}  {ep.frames.t[i]:.2f} s", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1,
                    cv2.LINE_AA)
        tiles.append(tile)
    rows = [np.concatenate(tiles[r * 4:(r + 1) * 4], axis=1) for r in range(frames // 4)]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(rows, axis=0))
