"""``manisplat-replay``: play an episode back on a PiPER (or a simulated one), safely.

Every arm of the episode is replayed (one, or several named ones of a version 2 episode). The
pieces: :mod:`.piper.convention` (the episode's joint convention -> the arm's),
:mod:`.piper.trajectory` (targets and every check of one arm before anything moves),
:mod:`.piper.replay_plan` and :mod:`.piper.clearance` (each arm's plan; the arms against each
other), :mod:`.piper.streamer` (the approach, the lock-step stream, the stops, the hold).
Nothing beyond the standard library and :mod:`manisplat.cli_args` is imported before the
arguments are parsed, so ``--help`` and usage errors answer at once.
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from manisplat.cli_args import add_version, bounded, finite_numbers, non_negative, positive
from manisplat.exit_codes import ExitCode, exit_status_help

if TYPE_CHECKING:
    import numpy as np

    from manisplat.drivers.piper.tracking import ReplayReport

log = logging.getLogger("manisplat.replay")

MAX_CONVENTION_MM = 3.0  # a joint map that moves the TCP more than this is refused
SIM_START_OFFSET_DEG = 3.0
DEFAULT_ARM_CLEARANCE_MM = 10.0  # several arms: the least distance allowed between two arms' links

EPILOG = """\
Before anything moves, the whole trajectory is checked: joint and gripper limits, velocity (against
the speed limits x --arm-speed-pct) and acceleration, jumps between frames (--max-step-deg), and
the distance from the arm's current state to the start (--max-start-distance-deg). Every problem
is listed and nothing is sent. The episode's joint convention (robot.description) is converted
to the arm's (piper_sdk's) explicitly; an unknown description is refused.

Then the arm is enabled if needed (never reset), moved slowly to the start, and the targets
(actions a1..a6,a_gripper when frames.csv has them, else q1..q6,gripper) are streamed at 200 Hz
in MOVE J. The stream stops on a tracking error above --max-tracking-error-deg, on lost feedback
(--feedback-timeout-ms), on Ctrl-C / SIGTERM, or on any error, and the arm is left holding
(on its measured position; on the last target when the feedback is lost). Reset (0x150 B0=2) and
disable (0x471 07 01) are never sent: both drop the arm.

An episode with several arms (format version 2) needs every arm's channel (--arm NAME=CHANNEL);
each arm gets every check above, and before anything moves the arms are checked against each
other: each arm's links (the convex hulls of its description's geometry, placed by its forward
kinematics and its T_world_base; the fingers at the recorded opening) must stay
--min-arm-clearance-mm apart from every other arm's over every frame, and over the move of all
arms to their starts. A refusal names the frame, the two links and their distance. The arms are
then moved and streamed in lock-step from one clock; a stop on one arm stops them all.

--sim replays on simulated PiPERs, one per arm, each on its own private virtual bus, starting 3 deg
away from the episode's start on every joint (so the approach runs) unless --sim-start says where.

""" + exit_status_help({
    ExitCode.OK: "replayed to the end (or --dry-run: every check passed)",
    ExitCode.FAILED: "stopped during the replay (tracking error, lost feedback, an error); the arm is holding",
    ExitCode.BAD_INPUT: "bad arguments, or an episode that cannot be read (a missing file, NaN in K: named)",
    ExitCode.DEVICE: "the arm cannot be reached or sends no feedback",
    ExitCode.REFUSED: "refused before anything moved (a check failed, e.g. two arms too close, or the "
                      "convention cannot be mapped)",
    ExitCode.INTERRUPTED: "interrupted by Ctrl-C / SIGTERM; the arm is holding",
})


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``manisplat-replay``."""
    p = argparse.ArgumentParser(
        prog="manisplat-replay", formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG,
        description="Play an episode's joint and gripper targets back on a PiPER over CAN, checked first, "
                    "stopped safely.")
    p.add_argument("episode", type=Path, help="the episode folder (docs/episode-format.md)")
    p.add_argument("--can", default=None, metavar="CHANNEL",
                   help="CAN channel of the arm of a one-arm episode (default can0)")
    p.add_argument("--arm", type=_named("--arm", "CHANNEL"), action="append", metavar="NAME=CHANNEL",
                   help="CAN channel of the episode's arm NAME; repeat for every arm of a several-arm episode "
                        "(--arm left=can_left --arm right=can_right)")
    p.add_argument("--interface", default="socketcan", metavar="NAME",
                   help="python-can interface: socketcan, slcan, gs_usb, pcan, virtual, ... (default socketcan)")
    p.add_argument("--sim", action="store_true",
                   help="replay on a simulated PiPER (no hardware; default: the arm on --can)")
    p.add_argument("--sim-start", type=_sim_start, action="append", metavar="[NAME=]J1,..,J6",
                   help="--sim: a simulated arm's initial joints, 6 angles in degrees (arm convention; default "
                        "3 deg from the episode's start on every joint); NAME= says which arm (needed with several)")
    p.add_argument("--speed", type=positive(), default=1.0,
                   help="time scale: 0.5 replays at half speed, 2 at twice (default 1)")
    p.add_argument("--dry-run", action="store_true",
                   help="check everything (reading the arm's current state) and send nothing")
    p.add_argument("--source", choices=("auto", "actions", "joints"), default="auto",
                   help="targets from the action columns (actions), the measured joints (joints), or the actions "
                        "when frames.csv has them, else the joints (default auto)")
    p.add_argument("--arm-speed-pct", type=bounded(1, 100, int), default=100, metavar="PCT",
                   help="MOVE J speed %% given to the arm (1..100, default 100); velocities are checked against "
                        "the speed limits times this")
    p.add_argument("--max-tracking-error-deg", type=positive(), default=10.0, metavar="DEG",
                   help="stop when a joint is further than this from its target (default 10)")
    p.add_argument("--max-start-distance-deg", type=positive(), default=30.0, metavar="DEG",
                   help="refuse when the start is further than this from the arm's state (default 30)")
    p.add_argument("--max-step-deg", type=positive(), default=10.0, metavar="DEG",
                   help="refuse a jump larger than this between two frames (default 10)")
    p.add_argument("--min-arm-clearance-mm", type=non_negative(), default=DEFAULT_ARM_CLEARANCE_MM, metavar="MM",
                   help="several arms: refuse when links of two arms come closer than this (convex hulls of the "
                        f"links; default {DEFAULT_ARM_CLEARANCE_MM:g})")
    p.add_argument("--feedback-timeout-ms", type=positive(), default=100.0, metavar="MS",
                   help="stop when no joint feedback arrives for this long (default 100)")
    p.add_argument("-v", "--verbose", action="count", default=0,
                   help="more log output: -v info, -vv debug (default: warnings only)")
    return add_version(p)


class SimArm:
    """A simulated PiPER on a private virtual bus (started), with a commanding PiperArm and an
    audit of every command on the bus."""

    def __init__(self, q0: np.ndarray, gripper0: float) -> None:
        import uuid

        import can

        from manisplat.drivers.piper import PiperArm, SimConfig, SimulatedPiper
        from manisplat.drivers.piper.streamer import CommandAudit

        channel = f"manisplat-replay-sim-{uuid.uuid4().hex}-bus"
        self.sim_bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        self.sim = SimulatedPiper(self.sim_bus, config=SimConfig(q0=q0, gripper0=gripper0))
        self.audit = CommandAudit()
        self._audit_bus = can.Bus(interface="virtual", channel=channel)
        self._notifier = can.Notifier(self._audit_bus, [self.audit], timeout=0.1)
        self.arm = PiperArm(can.Bus(interface="virtual", channel=channel), own_bus=True)
        self.sim.start()

    def close(self) -> None:
        self.arm.close()
        if self.sim._thread is not None:  # running: let the hold reach the simulated arm
            try:
                self.sim.wait_cycles(20, timeout=2.0)
            except TimeoutError:
                log.warning("the simulated arm did not run 20 cycles in 2 s while closing")
        self.sim.stop()
        self._notifier.stop()
        self._audit_bus.shutdown()
        self.sim_bus.shutdown()


class UsageError(ValueError):
    """Arguments that do not fit the episode (exit 2)."""


def _named(option: str, value_name: str) -> Callable[[str], tuple[str, str]]:
    """An argparse type: ``NAME=VALUE`` -> (name, value)."""
    def parse(text: str) -> tuple[str, str]:
        name, sep, value = text.partition("=")
        if not (sep and name and value):
            raise argparse.ArgumentTypeError(f"{option} {text!r}: expected NAME={value_name}")
        return name, value
    return parse


def _sim_start(text: str) -> tuple[str | None, list[float]]:
    """``[NAME=]J1,..,J6`` -> (name or None, 6 angles in degrees)."""
    name, sep, angles = text.rpartition("=")
    return (name if sep else None), finite_numbers((6,))(angles)


def _channels(args: argparse.Namespace, arms: list[str]) -> dict[str, str]:
    """Each arm's CAN channel from ``--arm NAME=CHANNEL`` (or ``--can`` for a one-arm episode)."""
    if args.arm and args.can is not None:
        raise UsageError("give --can (one arm) or --arm NAME=CHANNEL (each arm), not both")
    if not args.arm:
        if len(arms) > 1:
            raise UsageError(f"the episode has the arms {', '.join(arms)}: give each one's CAN channel with "
                             + " ".join(f"--arm {a}=CHANNEL" for a in arms) + " (or replay them on simulated arms "
                             "with --sim)")
        return {arms[0]: args.can if args.can is not None else "can0"}
    channels = dict(args.arm)
    if len(channels) < len(args.arm):
        raise UsageError("--arm names an arm twice")
    unknown = [a for a in channels if a not in arms]
    missing = [a for a in arms if a not in channels]
    if unknown or missing:
        raise UsageError(f"--arm must name every arm of the episode ({', '.join(arms)}) once"
                         + (f"; unknown: {', '.join(unknown)}" if unknown else "")
                         + (f"; missing: {', '.join(missing)}" if missing else "")
                         + ". To replay one arm of several, import that arm alone (manisplat-episode import-act "
                           "--arm NAME)")
    return channels


def _sim_starts(args: argparse.Namespace, arms: list[str]) -> dict[str, list[float]]:
    """The ``--sim-start`` angles (deg) per arm; an unnamed one is the one arm's."""
    starts: dict[str, list[float]] = {}
    for name, angles in args.sim_start or []:
        if name is None and len(arms) > 1:
            raise UsageError(f"--sim-start: name the arm ({', '.join(arms)}): --sim-start NAME=J1,..,J6")
        name = arms[0] if name is None else name
        if name not in arms or name in starts:
            raise UsageError(f"--sim-start {name}=...: " + ("given twice" if name in starts else
                                                            f"no such arm; the episode's: {', '.join(arms)}"))
        starts[name] = angles
    return starts


def _describe_checks(figures: dict[str, float], speed: float, source: str, convention: str, tcp_mm: float) -> str:
    lines = [f"convention: {convention} -> piper_sdk (TCP agrees within {tcp_mm:.2f} mm)",
             f"targets: {source}, {int(figures['frames'])} frames, {figures['duration_s']:.2f} s at speed {speed:g}",
             f"peak velocity {figures['peak_velocity_of_limit'] * 100:.0f} % of the limit"]
    if "peak_acceleration_of_limit" in figures:
        lines[-1] += f", peak acceleration {figures['peak_acceleration_of_limit'] * 100:.0f} % of the limit"
    return "\n".join(lines)


def _by_arm(texts: dict[str, str]) -> str:
    """One arm's text as it is; several arms' each under ``arm NAME:``, indented."""
    if len(texts) == 1:
        return next(iter(texts.values()))
    return "\n".join(f"arm {name}:\n" + "\n".join("  " + line for line in text.split("\n"))
                     for name, text in texts.items())


def _refused(problems: dict[str, list[str]]) -> int:
    """Print every arm's problems (named when there are several) as the refusal; REFUSED."""
    several = len(problems) > 1
    lines = [f"  - {name + ': ' if several and name else ''}{p}" for name, ps in problems.items() for p in ps]
    print("manisplat-replay: refused, nothing was sent:\n" + "\n".join(lines), file=sys.stderr)
    return ExitCode.REFUSED


def main(argv: list[str] | None = None) -> int:
    """Run ``manisplat-replay`` with ``argv``; returns the exit status (``--help`` lists them)."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.verbose == 0 else logging.INFO if args.verbose == 1
                        else logging.DEBUG, format="%(levelname)s %(name)s: %(message)s")
    import numpy as np

    from manisplat.drivers.base import DriverError
    from manisplat.drivers.piper.arm import PiperArm
    from manisplat.drivers.piper.convention import ConventionError
    from manisplat.drivers.piper.replay_plan import (approach_clearance, arm_clearance, clearance_problem,
                                                     describe_closest, plan_arms, trajectory_clearance)
    from manisplat.drivers.piper.streamer import StreamConfig, replay_arms
    from manisplat.drivers.piper.trajectory import ReplayLimits, check_trajectory, trajectory_figures
    from manisplat.episode import Episode, EpisodeFormatError
    from manisplat.robot import builtin_piper

    try:
        episode = Episode.open(args.episode)
        names = list(episode.arms)
        if args.sim and args.arm:
            raise UsageError("--sim replays on simulated arms: --arm NAME=CHANNEL names real ones")
        channels = {} if args.sim else _channels(args, names)
        sim_starts = _sim_starts(args, names)
        plans = plan_arms(episode, args.speed, args.source)
    except UsageError as exc:
        print(f"manisplat-replay: {exc}", file=sys.stderr)
        return ExitCode.BAD_INPUT
    except (EpisodeFormatError, FileNotFoundError) as exc:
        print(f"manisplat-replay: {exc}", file=sys.stderr)
        return ExitCode.BAD_INPUT
    except (ConventionError, ValueError) as exc:
        print(f"manisplat-replay: refused: {exc}", file=sys.stderr)
        return ExitCode.REFUSED
    several = len(plans) > 1
    for name, plan in plans.items():
        if plan.tcp_mm > MAX_CONVENTION_MM:
            print(f"manisplat-replay: refused: {'arm ' + name + ': ' if several else ''}mapping {plan.description} "
                  f"to the arm's convention moves the TCP by {plan.tcp_mm:.1f} mm (> {MAX_CONVENTION_MM} mm)",
                  file=sys.stderr)
            return ExitCode.REFUSED

    robot = builtin_piper(with_geometry=False)
    limits = ReplayLimits(arm_speed_pct=args.arm_speed_pct, max_step_deg=args.max_step_deg,
                          max_start_distance_deg=args.max_start_distance_deg)
    offline = {name: check_trajectory(p.traj, robot, limits) for name, p in plans.items()}
    if any(offline.values()):
        return _refused(offline)
    clearance = None
    if several:
        try:
            clearance = arm_clearance(episode)
        except ValueError as exc:
            print(f"manisplat-replay: refused, nothing was sent: {exc}", file=sys.stderr)
            return ExitCode.REFUSED
        closest = trajectory_clearance(clearance, plans)
        t = episode.arm_frames(names[0]).t

        def frame(i: int) -> str:
            return f"frame {i} (t {t[i] - t[0]:.2f} s)"

        problem = clearance_problem(closest, args.min_arm_clearance_mm, frame)
        if problem:
            return _refused({"": [problem]})

    stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    sims: dict[str, SimArm] = {}
    arms: dict[str, PiperArm] = {}
    reports: dict[str, ReplayReport] = {}
    try:
        try:
            for name, plan in plans.items():
                if args.sim:
                    traj = plan.traj
                    start = np.radians(sim_starts[name]) if name in sim_starts else np.clip(
                        traj.q[0] + math.radians(SIM_START_OFFSET_DEG), robot.lower, robot.upper)
                    sims[name] = SimArm(start, float(traj.gripper[0]))
                    arms[name] = sims[name].arm
                else:
                    arms[name] = PiperArm.open(channels[name], args.interface, read_only=args.dry_run)
            current = {}
            for name, arm in arms.items():
                current[name] = arm.wait_for_joint_state(timeout=2.0).q
        except (DriverError, TimeoutError, OSError) as exc:
            print(f"manisplat-replay: cannot read the arm's state{' (arm ' + name + ')' if several else ''}: {exc}",
                  file=sys.stderr)
            return ExitCode.DEVICE
        problems = {name: check_trajectory(p.traj, robot, limits, current_q=current[name]) for name, p in plans.items()}
        print(_by_arm({name: _describe_checks(trajectory_figures(p.traj, robot, limits), args.speed, p.traj.source,
                                              p.convention.name, p.tcp_mm) for name, p in plans.items()}))
        if clearance is not None:
            moving, times = approach_clearance(clearance, plans, current, robot, StreamConfig().approach_fraction)
            problem = clearance_problem(moving, args.min_arm_clearance_mm,
                                        lambda i: f"{times[i]:.2f} s into the move to the start")
            if problem:
                problems[""] = [problem]
            print(f"arms' closest approach: {describe_closest(closest)} at {frame(closest.frame)}; "
                  f"{describe_closest(moving)} while moving to the start")
        if any(problems.values()):
            return _refused(problems)
        distance = max(np.degrees(np.abs(p.traj.q[0] - current[n])).max() for n, p in plans.items())
        print(f"starts are at most {distance:.1f} deg from the arms' states: all checks pass" if several
              else f"start is {distance:.1f} deg from the arm's state: all checks pass")
        if args.dry_run:
            print("dry run: nothing was sent")
            return ExitCode.OK
        config = StreamConfig(arm_speed_pct=args.arm_speed_pct, max_tracking_error_deg=args.max_tracking_error_deg,
                              feedback_timeout_s=args.feedback_timeout_ms / 1e3)
        progress = _Progress() if sys.stderr.isatty() else None
        reports = replay_arms({name: (arms[name], p.traj) for name, p in plans.items()}, config, stop,
                              on_progress=progress)
        if progress is not None:
            progress.end()
        print(_by_arm({name: str(r) for name, r in reports.items()}))
    finally:
        for name, arm in arms.items():
            if name in sims:
                sim = sims[name]
                sim.close()
                print(f"simulated bus{' of ' + name if several else ''}: {sim.audit.resets} resets (0x150 B0=2), "
                      f"{sim.audit.disables} disables (0x471 01), {sim.audit.estops} e-stops, "
                      f"{sim.audit.joint_targets} joint targets")
            else:
                arm.close()
        for s, handler in previous.items():
            signal.signal(s, handler)
    outcome = next(iter(reports.values())).outcome
    return {"completed": ExitCode.OK, "interrupted": ExitCode.INTERRUPTED}.get(outcome, ExitCode.FAILED)


class _Progress:
    def __call__(self, done: float, total: float) -> None:
        sys.stderr.write(f"\rreplaying {done:6.2f} / {total:.2f} s")
        sys.stderr.flush()

    def end(self) -> None:
        sys.stderr.write("\n")


if __name__ == "__main__":
    sys.exit(main())
