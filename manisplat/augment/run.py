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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from manisplat.augment.bimanual import BimanualPlanner, BimanualTrajectory
from manisplat.augment.cli import REPORT, load_poses_file
from manisplat.augment.draws import SampleDraws
from manisplat.augment.frames import from_centre_frame, to_centre_frame
from manisplat.augment.symmetry import Symmetry
from manisplat.augment.trajectory import (AugmentConfig, NewTrajectory, ObjectTarget, Rejected, augment_trajectory,
                                          augmenter_for, sample_targets)
from manisplat.augment.views import UNSEEN_WARN_DEG, SeenViews
from manisplat.augment.writer import write_demonstration
from manisplat.episode.fsio import atomic_write_bytes
from manisplat.robot.arms import ArmSet
from manisplat.twin import Twin, TwinFormatError
from manisplat.twin.support import MAX_STEP

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
    targets: dict  # object -> ObjectTarget; with several arms: arm -> object -> ObjectTarget (its base frame)
    trajectory: NewTrajectory | BimanualTrajectory | None = None
    reason: str | None = None
    detail: str | None = None
    plan_s: float = 0.0
    episode: str | None = None
    source: str = ""  # the source demonstration it was planned from (its episode's name)
    #: object -> the largest angle (deg) from a recorded view it is seen at (:mod:`.views`)
    view_change_deg: dict[str, float] = field(default_factory=dict)
    #: first joints (rad; arm name -> joints on a two-arm twin) when --start-range moved them
    start_q: np.ndarray | dict[str, np.ndarray] | None = None


def run_augmentation(args: argparse.Namespace) -> dict:
    """Plan, render, write and report; returns the report written to ``augment_report.json``."""
    start = time.perf_counter()
    logging.getLogger("manisplat.episode").setLevel(logging.WARNING)  # one line per episode written: the bar says it
    twin = _load_twin(args.recon)
    sources = _sources(twin, args)
    if args.overwrite:
        _remove_earlier(args.out)
    args.out.mkdir(parents=True, exist_ok=True)
    config = AugmentConfig(speed=args.speed, profile=args.profile, planner_timeout_s=args.planner_timeout,
                           planner_checks=args.planner_checks,
                           seed=args.seed, symmetries=_symmetries(twin, args.symmetries))
    planners = {name: _arms_planner(source, args) for name, source in sources.items()}
    if args.start_range > 0:
        for name, source in sources.items():
            _check_new_start(source, planners[name])
    explicit = _explicit_targets(args.poses, twin) if args.poses else None
    wanted = len(explicit) if explicit is not None else args.n
    limit = len(explicit) if explicit is not None else (args.max_samples or max(10, 3 * args.n))
    object_range = (args.object_range[0], args.object_range[1], np.radians(args.object_range[2]))
    target_range = (args.target_range[0], args.target_range[1], np.radians(args.target_range[2]))
    draws = SampleDraws(args.sampling, args.seed, limit)
    views = SeenViews.of(twin)
    if views is None and args.max_view_change is not None:
        raise AugmentError("--max-view-change: the twin has no fixed camera whose views could be compared")

    samples: list[Sample] = []
    bar = tqdm(total=wanted, desc="planning", unit="demo", disable=args.quiet)
    while sum(s.trajectory is not None for s in samples) < wanted and len(samples) < limit:
        index = len(samples)
        seed = draws.seed_of(index)
        name = list(sources)[index % len(sources)]
        source, arms = sources[name], planners[name]
        rng = draws(index)
        if explicit is not None:
            targets = explicit[index]
        elif arms is not None:
            targets = arms.sample_targets(rng, object_range, target_range, tuple(args.handover_range))
        else:
            targets = sample_targets(source, rng, object_range, target_range)
        sample = Sample(index, seed, targets, source=name)
        t0 = time.perf_counter()
        try:
            if args.start_range > 0:  # drawn after the objects: the same seed gives the same object poses
                half_range = np.radians(args.start_range)
                sample.start_q = arms.sample_starts(rng, half_range) if arms is not None else \
                    augmenter_for(source).sample_start(rng, half_range)
            trajectory = arms.run(targets, config, sample.start_q) if arms is not None else \
                augment_trajectory(source, targets, config, sample.start_q)
            if views is not None:
                sample.view_change_deg = views.change_deg(trajectory.object_poses)
                _check_views(sample.view_change_deg, args.max_view_change)
            sample.trajectory = trajectory
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
    unseen = [s for s in valid if max(s.view_change_deg.values(), default=0.0) > UNSEEN_WARN_DEG]
    if unseen:
        log.warning("%d of %d new demonstrations show an object from more than %g deg away from every view the "
                    "recording had of it: sides the twin never saw (--max-view-change discards them; more "
                    "demonstrations of the scene add views)", len(unseen), len(valid), UNSEEN_WARN_DEG)
    for k, s in enumerate(valid):
        s.episode = f"episode_{k:04d}"

    t0 = time.perf_counter()
    _render_and_write(sources, args.recon, valid, args.out, workers=args.workers, image_format=args.image_format,
                      quiet=args.quiet)
    render_s = time.perf_counter() - t0
    _plot_tcp_paths(args.out / PLOT, twin, valid, sources)
    for s in valid[:SHEETS]:
        _contact_sheet(args.out / s.episode, args.out / "sheets" / f"{s.episode}.png")
    report = _report(twin, args, samples, wanted, {"plan": plan_s, "render_and_write": render_s,
                                                   "total": time.perf_counter() - start},
                     handover=any(a is not None and bool(a.handovers) for a in planners.values()))
    atomic_write_bytes(args.out / REPORT, (json.dumps(report, indent=1) + "\n").encode())
    return report


def _check_views(change_deg: dict[str, float], limit: float | None) -> None:
    """Rejected("unseen_side") when an object's view change (deg) exceeds ``limit`` (None: never)."""
    if limit is None:
        return
    for name, angle in change_deg.items():
        if angle > limit:
            raise Rejected("unseen_side", f"{name} is seen {angle:.0f} deg from every recorded view of it "
                                          f"(--max-view-change {limit:g})")


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
    if not twin.objects:
        raise AugmentError(f"{recon}: the reconstruction has no manipulated object to move")
    for demo in twin.demonstrations.values():
        source = "" if len(twin.demonstrations) == 1 else f" (source {demo.episode})"
        for name in twin.objects:
            if not demo.phases.get(name):
                raise AugmentError(f"{recon}: object {name!r} has no Motion/Skill phases in twin.json{source}")
            if name not in demo.object_poses or len(demo.object_poses[name]) != len(demo.t):
                raise AugmentError(f"{recon}: object {name!r} has no pose per frame in twin.pt{source}")
    if twin.commands is None:
        log.warning("%s keeps no recorded commands (the recording has none, or the twin was made before "
                    "2026-11-27): the new commands are the next frame's joints; %s keeps them where the "
                    "recording has commands", recon, reconstruct_command(recon))
    elif twin.commands.gripper is None:
        log.warning("%s keeps no recorded gripper commands (made before 2026-11-28): the new gripper commands "
                    "are open or closed from the grasp to the release, not the source's; %s keeps them",
                    recon, reconstruct_command(recon))
    else:
        log.info("commands: the source's, led by %.2f of a frame, skills pressing and the gripper commanded "
                 "as it did", twin.commands.lead)
    if twin.support is not None and twin.support.smallest_edge() > MAX_STEP:
        log.warning("the recording's depth comes in steps of %.1f mm where the table is seen: a step under %.1f mm "
                    "(a plate's rim) cannot be told from them, so placements are refused only on larger ones",
                    1e3 * twin.support.resolution, 1e3 * twin.support.smallest_edge())
    return twin


def _sources(twin: Twin, args: argparse.Namespace) -> dict[str, Twin]:
    """Episode name -> the twin with that source demonstration, for ``--sources`` (all, or named)."""
    names = list(twin.demonstrations) if args.sources == "all" else [n.strip() for n in args.sources.split(",")]
    unknown = [n for n in names if n not in twin.demonstrations]
    if unknown or not names or len(set(names)) != len(names):
        raise AugmentError(f"--sources {args.sources}: the twin's demonstrations are {', '.join(twin.demonstrations)}"
                           + (f" ({', '.join(unknown)} is none of them)" if unknown else " (name each once)"))
    sources = {name: twin.source(name) for name in names}
    if len(sources) > 1:
        log.info("sources: %d demonstrations (%s), taken in turn", len(sources), ", ".join(sources))
    return sources


def _symmetries(twin: Twin, symmetries: dict[str, Symmetry]) -> dict[str, Symmetry]:
    """``--symmetry``, checked against the twin's objects and logged."""
    unknown = sorted(set(symmetries) - set(twin.objects))
    if unknown:
        raise AugmentError(f"--symmetry names {', '.join(unknown)}; the twin's objects are {', '.join(twin.objects)}")
    for name, symmetry in symmetries.items():
        turns = "any turn" if symmetry.order is None else f"turns of {360 / symmetry.order:g} deg"
        log.info("%s: the same shape after %s about the vertical: grasped on the face nearest the source's wrist",
                 name, turns)
    return symmetries


def _arms_planner(twin: Twin, args: argparse.Namespace) -> BimanualPlanner | None:
    """The planner of a twin of several arms (or cameras: a version 2 episode's), None for one arm."""
    if not isinstance(twin.robot, ArmSet):
        return None
    if args.poses:
        raise AugmentError(f"--poses: the twin has arms {', '.join(twin.arm_names)}; explicit poses are read for "
                           "one arm only (drop --poses to sample new poses)")
    try:
        return BimanualPlanner(twin)
    except Rejected as exc:
        raise AugmentError(f"{args.recon}: {exc.detail}") from exc


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


def _check_new_start(source: Twin, arms: BimanualPlanner | None) -> None:
    """--start-range needs a motion into every arm's first skill to plan from a new start."""
    augmenters = {None: augmenter_for(source)} if arms is None else \
        {name: augmenter_for(arm) for name, arm in arms.arms.items()}
    for name, augmenter in augmenters.items():
        if not augmenter.plans_first_motion:
            arm = "" if name is None else f" ({name} arm)"
            raise AugmentError(f"--start-range: {source.episode}'s first skill{arm} begins at its first frame, so no "
                               "motion leads into it from another start")


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


def _write_one(trajectory: NewTrajectory | BimanualTrajectory, source: str, path: str, seed: int,
               image_format: str) -> str:
    assert _WORKER_TWIN is not None
    write_demonstration(_WORKER_TWIN.source(source), trajectory, Path(path), seed=seed, image_format=image_format)
    return path


def _render_and_write(sources: dict[str, Twin], recon: Path, valid: list[Sample], out: Path, *, workers: int,
                      image_format: str, quiet: bool) -> None:
    """Render and write ``valid``, each with the twin of its source: here, or in ``workers``
    processes that each load the twin from ``recon``."""
    frames = sum(len(s.trajectory.t) for s in valid)
    bar = tqdm(total=frames if workers == 1 else len(valid), desc="rendering",
               unit="frame" if workers == 1 else "demo", disable=quiet)
    if workers == 1:
        for s in valid:
            write_demonstration(sources[s.source], s.trajectory, out / s.episode, seed=s.seed, image_format=image_format,
                                on_frame=lambda: bar.update(1))
    else:
        backend = next(iter(sources.values())).backend
        with ProcessPoolExecutor(max_workers=workers, initializer=_init_worker, initargs=(str(recon), backend)) as pool:
            futures = [pool.submit(_write_one, s.trajectory, s.source, str(out / s.episode), s.seed, image_format)
                       for s in valid]
            for future in as_completed(futures):
                future.result()
                bar.update(1)
    bar.close()


# ------------------------------------------------------------------ report and plot
def _report(twin: Twin, args: argparse.Namespace, samples: list[Sample], wanted: int, timing: dict,
            handover: bool = False) -> dict:
    valid = [s for s in samples if s.trajectory is not None]
    reasons: dict[str, int] = {}
    for s in samples:
        if s.reason:
            reasons[s.reason] = reasons.get(s.reason, 0) + 1
    arms = [arm for s in valid for arm in _per_arm(s.trajectory)]
    motions = [r for arm in arms for r in arm.planner["segments"]]
    skill_mm = [arm.validation.get("skill_error_mm", 0.0) for arm in arms]
    skill_deg = [arm.validation.get("skill_error_deg", 0.0) for arm in arms]
    several = [s.trajectory for s in valid if isinstance(s.trajectory, BimanualTrajectory)]
    clearances = [traj.validation["min_arm_clearance_m"] for traj in several]
    return {
        "parent": twin.episode, "recon": str(args.recon), "seed": args.seed, "sampling": args.sampling,
        "requested": wanted,
        "sources": dict(Counter(s.source for s in valid)),
        "drawn": len(samples), "valid": len(valid), "written": len(valid),
        "validity_rate": len(valid) / max(len(samples), 1), "reasons": reasons,
        "ranges": {"object": args.object_range, "target": args.target_range, "units": "m, m, deg",
                   **({"handover": args.handover_range, "handover_units": "m, m, m"} if handover else {})},
        "start_range_deg": args.start_range,
        "max_view_change_deg": args.max_view_change,
        "view_change_deg": _view_summary(valid),
        "speed": args.speed, "profile": args.profile, "workers": args.workers,
        "symmetry": {name: "round" if sym.order is None else sym.order for name, sym in args.symmetries.items()},
        "skill_error_max": {"mm": max(skill_mm, default=0.0), "deg": max(skill_deg, default=0.0)},
        "motions": {"planned": len(motions), "by_method": dict(Counter(r["method"] for r in motions)),
                    "joined_at_rest": sum(r.get("joined") == "at rest" for r in motions)},
        "timing_s": {k: round(v, 2) for k, v in timing.items()},
        "plan_s_per_sample": round(float(np.mean([s.plan_s for s in samples])) if samples else 0.0, 4),
        "samples": [{"index": s.index, "seed": s.seed, "source": s.source, "valid": s.trajectory is not None,
                     "episode": s.episode, "reason": s.reason, "detail": s.detail, "plan_s": round(s.plan_s, 4),
                     "view_change_deg": s.view_change_deg} for s in samples],
        **({"min_arm_clearance_m": min(clearances),  # and how many needed one arm to wait
            "arm_waited": sum("waited" in traj.validation for traj in several)} if clearances else {}),
    }


def _view_summary(valid: list[Sample]) -> dict | None:
    """The written demonstrations' view changes (:mod:`.views`): median, largest, how many above
    :data:`~manisplat.augment.views.UNSEEN_WARN_DEG`; None without a fixed camera."""
    worst = [max(s.view_change_deg.values(), default=0.0) for s in valid if s.view_change_deg]
    if not worst:
        return None
    return {"median": round(float(np.median(worst)), 2), "max": round(max(worst), 2),
            "above_warning": sum(w > UNSEEN_WARN_DEG for w in worst), "warning_deg": UNSEEN_WARN_DEG}


def _per_arm(traj: NewTrajectory | BimanualTrajectory) -> list[NewTrajectory]:
    return list(traj.arms.values()) if isinstance(traj, BimanualTrajectory) else [traj]


def _plot_tcp_paths(path: Path, twin: Twin, valid: list[Sample], sources: dict[str, Twin]) -> None:
    """Top view (x-y of the twin's frame, cm) of every new TCP path (every arm's) over the sources',
    with the new object poses."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 6))
    for k, s in enumerate(valid):
        for tcp in _tcp_xy_cm(twin, s.trajectory):
            ax.plot(tcp[:, 0], tcp[:, 1], lw=0.8, alpha=0.6, color=f"C{k % 10}")
        for name, poses in s.trajectory.object_poses.items():
            start, end = (to_centre_frame(twin, name, poses[f])[:2, 3] * 100 for f in (0, -1))
            ax.plot(*start, "o", ms=3, color=f"C{k % 10}")
            ax.plot(*end, "s", ms=3, mfc="none", color=f"C{k % 10}")
    paths = [xy for source in sources.values() for xy in _tcp_xy_cm(source, None)]
    for j, xy in enumerate(paths):
        ax.plot(xy[:, 0], xy[:, 1], "k--", lw=1.8 if len(sources) == 1 else 1.0,
                label=("source demonstration" if len(sources) == 1 else f"{len(sources)} source demonstrations")
                if j == 0 else None)
    ax.plot([], [], "o", color="grey", ms=3, label="object start")
    ax.plot([], [], "s", mfc="none", color="grey", ms=3, label="object end")
    frame = "robot base" if twin.frame == "base" else "world"
    ax.set(xlabel=f"x (cm, {frame})", ylabel="y (cm)", title=f"TCP paths of {len(valid)} new demonstrations",
           aspect="equal")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _tcp_xy_cm(twin: Twin, traj: NewTrajectory | BimanualTrajectory | None) -> list[np.ndarray]:
    """Each arm's TCP path [T, 2] (cm, the twin's frame) over ``traj`` (None: the source)."""
    import torch

    if traj is None:
        q = twin.q
    elif isinstance(traj, BimanualTrajectory):
        q = np.concatenate([traj.arms[name].q for name in twin.arm_names], axis=1)
    else:
        q = traj.q
    if not isinstance(twin.robot, ArmSet):
        return [twin.robot.tcp_pose(torch.as_tensor(q)).numpy()[:, :2, 3] * 100]
    tcp = twin.robot.tcp_poses(torch.as_tensor(q)).numpy()
    return [tcp[:, k, :2, 3] * 100 for k in range(tcp.shape[1])]


def _contact_sheet(episode: Path, path: Path, frames: int = 8) -> None:
    """Eight frames of a written demonstration in a 2 x 4 grid, each labelled with its index and time."""
    import cv2

    from manisplat.episode import Episode

    ep = Episode.open(episode)
    camera = next(name for name, c in ep.cameras.items() if c.mount in ("base", "world"))  # the fixed one
    t = ep.arm_frames(next(iter(ep.arms))).t
    chosen = np.linspace(0, len(ep) - 1, frames).round().astype(int)
    tiles = []
    for i in chosen:
        tile = cv2.cvtColor(ep.rgb(int(i), camera if len(ep.cameras) > 1 else None), cv2.COLOR_RGB2BGR)
        cv2.putText(tile, f"{i}  {t[i]:.2f} s", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1,
                    cv2.LINE_AA)
        tiles.append(tile)
    rows = [np.concatenate(tiles[r * 4:(r + 1) * 4], axis=1) for r in range(frames // 4)]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(rows, axis=0))
