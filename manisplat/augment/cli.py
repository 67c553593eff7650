"""manisplat-augment: many new, physically feasible demonstrations from one reconstruction.

Only argparse and light modules are imported until the arguments are accepted.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path

from manisplat.augment.draws import SAMPLINGS
from manisplat.augment.planning import MAX_CHECKS, SAFETY_TIMEOUT_S
from manisplat.augment.timing import PROFILES
from manisplat.cli_args import add_version, bounded, finite_numbers, positive
from manisplat.exit_codes import ExitCode, exit_status_help
from manisplat.output_folder import check_output_folder
from manisplat.threads import THREADS_HELP, use_threads

log = logging.getLogger("manisplat.augment")
REPORT = "augment_report.json"

EPILOG = """\
what it does, per demonstration: sample a new start pose for each manipulated object (and a new
  place pose for a pick-and-place) on the table plane within the ranges, or take them from
  --poses; move each Skill segment rigidly with its object (T_tcp' = T_new inv(T_src) T_tcp) and
  solve it by IK frame by frame (an object declared --symmetry is grasped on the face nearest the
  source's wrist); re-plan every Motion segment collision-free in joint space and time it under
  the joint velocity/acceleration limits x --speed; validate (limits, collisions
  along the densely sampled path, IK residuals, continuity, skill-relative poses); render RGB,
  depth and label masks from the twin; write an episode (docs/episode-format.md, source
  augmentation) with augmentation.json. Invalid samples are discarded and counted by reason.

several arms (a twin of a version 2 episode, e.g. a Cobot Magic's): each arm's skills move with
  the objects it handles and its motions are planned in its base frame (ranges along its base's
  axes); the arms then run together; where they (or an arm and the other's object) would come
  within 5 mm, one arm waits at its start (0.5-3 s, the shortest wait that clears), and a
  demonstration that no wait clears is discarded (arm_collision); every camera is rendered,
  a wrist camera from its link at the new joints; written as version 2 episodes (every arm's
  joints and commands). An object handed from one arm to the other: the handover skill (both
  grippers on it) moves rigidly as one to a handover point drawn within --handover-range, the
  giver picks the object at its new start and the taker places it at its new place, and the arm
  that would reach the handover first waits at its start. Not yet: --poses with several arms.

output: OUT/episode_NNNN/ (complete episodes only: each is written under a hidden name and
  renamed when complete), OUT/augment_report.json (validity rate, reasons, per-sample results,
  timings), OUT/tcp_paths.png (top view of every TCP path), OUT/sheets/ (contact sheets of the
  first five). OUT must be new or empty unless --overwrite (its episode_* folders, report,
  plot and sheets are removed first).

--poses FILE: a JSON list, one entry per demonstration, each mapping an object name to
  {"T_start": 4x4, "T_place": 4x4 or null} in the robot base frame (metres), in the object's
  centre frame (its bounding box's centre, the axes of its reconstructed frame), as
  augmentation.json writes them.

""" + exit_status_help({
    ExitCode.OK: "all requested demonstrations written",
    ExitCode.FAILED: "fewer valid demonstrations than requested (the valid ones are written)",
    ExitCode.BAD_INPUT: "bad arguments; a reconstruction that cannot be augmented or a --poses file that does\n"
                        "not fit it (named); an --out in use without --overwrite",
    ExitCode.INTERRUPTED: "interrupted (finished episodes stay; nothing half-written looks complete)",
})


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="manisplat-augment",
        description="Generate new demonstrations from one reconstruction (manisplat-reconstruct --out): the "
                    "objects moved, the skills moved with them, the motions re-planned collision-free, every "
                    "frame rendered from the twin, each written as an episode that manisplat-replay plays.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recon", type=Path, metavar="RECON_DIR", help="a manisplat-reconstruct output folder (twin.json)")
    p.add_argument("--n", type=positive(int), default=10, help="valid demonstrations to write (default %(default)s)")
    p.add_argument("--out", type=Path, required=True, help="output folder: new or empty unless --overwrite")
    p.add_argument("--seed", type=int, default=0, help="random seed of the sampled poses (default %(default)s)")
    p.add_argument("--sampling", choices=SAMPLINGS, default="even",
                   help="how the new poses (and starts) spread over their ranges: even (a scrambled Sobol sequence "
                        "seeded by --seed: as many samples cover the ranges without holes) or random (independent "
                        "draws, each sample made again from its seed alone; the default before 2026-12-03) "
                        "(default %(default)s)")
    p.add_argument("--object-range", type=finite_numbers((3,)), default=[0.08, 0.08, 45.0], metavar="X,Y,YAW",
                   help="each object's start pose is moved by up to +-X, +-Y metres and +-YAW degrees on the "
                        "table (default 0.08,0.08,45)")
    p.add_argument("--target-range", type=finite_numbers((3,)), default=[0.05, 0.05, 45.0], metavar="X,Y,YAW",
                   help="the place pose of a pick-and-place likewise (default 0.05,0.05,45)")
    p.add_argument("--handover-range", type=finite_numbers((3,)), default=[0.04, 0.04, 0.02], metavar="X,Y,Z",
                   help="an object handed from one arm to the other: the handover point is moved by up to +-X, +-Y, "
                        "+-Z metres along the world's axes (default 0.04,0.04,0.02)")
    p.add_argument("--start-range", type=bounded(0.0, 90.0), default=0.0, metavar="DEG",
                   help="each new demonstration starts with every arm joint moved from the source's first "
                        "position by up to +-DEG (uniformly), the first motion planned from there: demonstrations "
                        "that all start from one pose and run straight to their targets let a policy read the "
                        "target off its own joints instead of the image (default 0: the source's start; on a "
                        "two-arm twin, every arm)")
    p.add_argument("--max-view-change", type=bounded(0.0, 180.0), metavar="DEG",
                   help="discard a new demonstration that shows an object from more than DEG away from every view "
                        "the recording's fixed cameras had of it (a side the twin never saw: drawn in colours it "
                        "never fitted; above 15 deg it is reported and warned of; default: not discarded)")
    p.add_argument("--sources", default="all", metavar="all|EPISODE,...",
                   help="the source demonstrations of a twin of several episodes: all (the default), or those named; "
                        "sample k starts from the k-th of them in turn, and the report names each one's source")
    p.add_argument("--symmetry", action="append", default=[], metavar="OBJECT=ORDER|round",
                   help="OBJECT looks the same turned by 360/ORDER deg about the vertical (a square box: 4; a "
                        "rectangular one: 2) or by any angle (round: a can); its new grasps take the face that keeps "
                        "the wrist nearest the source's, and where it is left may differ from the place pose by "
                        "such a turn (repeatable; default: none, every grasp turns with its object)")
    p.add_argument("--poses", type=Path, metavar="FILE",
                   help="exact object poses per demonstration instead of sampling (see below; --n is ignored)")
    p.add_argument("--max-samples", type=positive(int),
                   help="give up after this many samples (default 3 x --n, at least 10)")
    p.add_argument("--speed", type=positive(), default=1.0,
                   help="fraction (0-1] of the joint velocity/acceleration limits for re-planned motions "
                        "(default %(default)s)")
    p.add_argument("--profile", choices=PROFILES, default=PROFILES[0],
                   help="how re-planned motions are timed: time-optimal (toppra: full acceleration at once) or "
                        "smooth (a quintic: speed rises and falls as a bell, as a teleoperated motion does; "
                        "longer) (default %(default)s)")
    p.add_argument("--planner-checks", type=positive(int), default=MAX_CHECKS,
                   help="collision checks the planner may spend on one motion before the sample is given up "
                        "(default %(default)s, about 1 s on one idle core; a budget of checks, not seconds, gives "
                        "the same demonstrations on a busy machine)")
    p.add_argument("--planner-timeout", type=positive(), default=SAFETY_TIMEOUT_S,
                   help="seconds the planner may spend on one motion in any case (default %(default)s)")
    p.add_argument("--workers", type=positive(int), default=1,
                   help="processes rendering and writing demonstrations in parallel (default %(default)s)")
    p.add_argument("--threads", type=positive(int), metavar="N",
                   help=THREADS_HELP + "; the --workers processes render with one each")
    p.add_argument("--image-format", choices=("png", "jpg"), default="png", help="rgb file format (default %(default)s)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace earlier results in --out (episode_* folders, report, plot; default: refused)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar, warnings only (default: off)")
    return add_version(p)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.speed > 1.0:
        parser.error(f"--speed must be in (0, 1]; got {args.speed}")
    try:
        from manisplat.augment.symmetry import parse_symmetries
        args.symmetries = parse_symmetries(args.symmetry)
    except ValueError as exc:
        parser.error(f"--symmetry: {exc}")
    if any(v < 0 for v in (*args.object_range, *args.target_range, *args.handover_range)):
        parser.error("--object-range, --target-range and --handover-range take non-negative half-widths")
    try:
        check_output_folder(args.out, allowed=args.overwrite,
                            refusal="; pass --overwrite to replace its demonstrations, or choose another folder")
    except ValueError as exc:
        parser.error(str(exc))
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(message)s")
    use_threads(args.threads)
    from manisplat.augment.run import AugmentError, run_augmentation

    try:
        report = run_augmentation(args)
    except AugmentError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return ExitCode.BAD_INPUT
    except KeyboardInterrupt:
        print("\ninterrupted: finished episodes stay in place; nothing half-written looks complete", file=sys.stderr)
        return ExitCode.INTERRUPTED
    print(summary(report, args.out))
    return ExitCode.OK if report["written"] >= report["requested"] else ExitCode.FAILED


def summary(report: dict, out: Path) -> str:
    """The closing lines: counts, validity rate and reasons, time split, files to look at."""
    lines = [f"{report['written']} of {report['requested']} demonstrations written to {out}/ "
             f"({report['valid']} valid of {report['drawn']} samples, validity {100 * report['validity_rate']:.0f} %)"]
    if report["reasons"]:
        lines.append("discarded: " + ", ".join(f"{k} {v}" for k, v in sorted(report["reasons"].items(),
                                                                               key=lambda kv: -kv[1])))
    timing = report["timing_s"]
    lines.append("time: " + ", ".join(f"{k} {v:.1f} s" for k, v in timing.items()))
    if report.get("skill_error_max"):
        err = report["skill_error_max"]
        lines.append(f"skill-relative TCP error max: {err['mm']:.4f} mm, {err['deg']:.4f} deg")
    if report.get("motions", {}).get("planned"):
        motions = report["motions"]
        lines.append(f"motions: {motions['planned']} (" + ", ".join(f"{v} {k}" for k, v in motions["by_method"].items())
                     + f"); {motions['joined_at_rest']} stopped at a skill to turn (joined at rest)")
    views = report.get("view_change_deg")
    if views:
        lines.append(f"view change from the recording: median {views['median']:.0f} deg, max {views['max']:.0f} deg; "
                     f"{views['above_warning']} above {views['warning_deg']:g} deg (sides the twin never saw)")
    lines.append(f"look at: {out / 'tcp_paths.png'}, {out / 'sheets'}/, {out / REPORT}")
    return "\n".join(lines)


def load_poses_file(path: Path) -> list[dict]:
    """``--poses``: a JSON list of {object: {"T_start": 4x4, "T_place": 4x4 | null}}."""
    try:
        entries = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"--poses {path}: unreadable ({exc})") from exc
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"--poses {path}: expected a non-empty JSON list of demonstrations")
    for k, entry in enumerate(entries):
        if not isinstance(entry, dict) or not entry:
            raise ValueError(f"--poses {path}: entry {k} is not an object mapping names to poses")
        for name, poses in entry.items():
            for key in ("T_start", "T_place"):
                value = poses.get(key) if isinstance(poses, dict) else None
                if value is None and key == "T_place":
                    continue
                if not (isinstance(value, list) and len(value) == 4 and all(
                        isinstance(r, list) and len(r) == 4 and all(isinstance(x, (int, float)) and math.isfinite(x)
                                                                    for x in r) for r in value)):
                    raise ValueError(f"--poses {path}: entry {k}, {name}.{key} must be a 4x4 list of finite numbers")
    return entries


if __name__ == "__main__":
    sys.exit(main())
