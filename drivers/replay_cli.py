"""``manisplat-replay``: play an episode back on a PiPER (or a simulated one), safely.

The pieces: :mod:`.piper.convention` (the episode's joint convention -> the arm's),
:mod:`.piper.trajectory` (targets and every check before anything moves), :mod:`.piper.streamer`
(the approach, the stream, the stops, the hold). Nothing beyond the standard library and
:mod:`manisplat.cli_args` is imported before the arguments are parsed, so ``--help`` and usage
errors answer at once.
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING

from manisplat.cli_args import add_version, bounded, finite_numbers, positive
from manisplat.exit_codes import ExitCode, exit_status_help

if TYPE_CHECKING:
    import numpy as np

    from manisplat.drivers.piper.streamer import ReplayReport

log = logging.getLogger("manisplat.replay")

MAX_CONVENTION_MM = 3.0  # a joint map that moves the TCP more than this is refused
SIM_START_OFFSET_DEG = 3.0

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

--sim replays on a simulated PiPER on a private virtual bus, which starts 3 deg away from the
episode's start on every joint (so the approach runs) unless --sim-start says where.

""" + exit_status_help({
    ExitCode.OK: "replayed to the end (or --dry-run: every check passed)",
    ExitCode.FAILED: "stopped during the replay (tracking error, lost feedback, an error); the arm is holding",
    ExitCode.BAD_INPUT: "bad arguments, or an episode that cannot be read (a missing file, NaN in K: named)",
    ExitCode.DEVICE: "the arm cannot be reached or sends no feedback",
    ExitCode.REFUSED: "refused before anything moved (a check failed, or the convention cannot be mapped)",
    ExitCode.INTERRUPTED: "interrupted by Ctrl-C / SIGTERM; the arm is holding",
})


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``manisplat-replay``."""
    p = argparse.ArgumentParser(
        prog="manisplat-replay", formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG,
        description="Play an episode's joint and gripper targets back on a PiPER over CAN, checked first, "
                    "stopped safely.")
    p.add_argument("episode", type=Path, help="the episode folder (docs/episode-format.md)")
    p.add_argument("--can", default="can0", metavar="CHANNEL", help="CAN channel of the arm (default can0)")
    p.add_argument("--interface", default="socketcan", metavar="NAME",
                   help="python-can interface: socketcan, slcan, gs_usb, pcan, virtual, ... (default socketcan)")
    p.add_argument("--sim", action="store_true",
                   help="replay on a simulated PiPER (no hardware; default: the arm on --can)")
    p.add_argument("--sim-start", type=finite_numbers((6,)), default=None, metavar="J1,..,J6",
                   help="--sim: the simulated arm's initial joints, 6 angles in degrees (arm convention; default "
                        "3 deg from the episode's start on every joint)")
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


def _describe_checks(figures: dict[str, float], speed: float, source: str, convention: str, tcp_mm: float) -> str:
    lines = [f"convention: {convention} -> piper_sdk (TCP agrees within {tcp_mm:.2f} mm)",
             f"targets: {source}, {int(figures['frames'])} frames, {figures['duration_s']:.2f} s at speed {speed:g}",
             f"peak velocity {figures['peak_velocity_of_limit'] * 100:.0f} % of the limit"]
    if "peak_acceleration_of_limit" in figures:
        lines[-1] += f", peak acceleration {figures['peak_acceleration_of_limit'] * 100:.0f} % of the limit"
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run ``manisplat-replay`` with ``argv``; returns the exit status (``--help`` lists them)."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.verbose == 0 else logging.INFO if args.verbose == 1
                        else logging.DEBUG, format="%(levelname)s %(name)s: %(message)s")
    import numpy as np

    from manisplat.drivers.base import DriverError
    from manisplat.drivers.piper.arm import PiperArm
    from manisplat.drivers.piper.convention import ConventionError, convention_for, tcp_discrepancy_mm
    from manisplat.drivers.piper.streamer import StreamConfig, replay
    from manisplat.drivers.piper.trajectory import (ReplayLimits, check_trajectory, trajectory_figures,
                                                    trajectory_from_episode)
    from manisplat.episode import Episode, EpisodeFormatError
    from manisplat.robot import builtin_piper

    try:
        episode = Episode.open(args.episode)
        description = episode.meta.robot.description
        convention = convention_for(description, episode.path)
        traj = trajectory_from_episode(episode, convention, args.speed, args.source)
        tcp_mm = tcp_discrepancy_mm(convention, description, episode.path,
                                    episode.frames.actions[:, :6] if traj.source == "actions" else episode.frames.q)
    except (EpisodeFormatError, FileNotFoundError) as exc:
        print(f"manisplat-replay: {exc}", file=sys.stderr)
        return ExitCode.BAD_INPUT
    except (ConventionError, ValueError) as exc:
        print(f"manisplat-replay: refused: {exc}", file=sys.stderr)
        return ExitCode.REFUSED
    if tcp_mm > MAX_CONVENTION_MM:
        print(f"manisplat-replay: refused: mapping {description} to the arm's convention moves the TCP by "
              f"{tcp_mm:.1f} mm (> {MAX_CONVENTION_MM} mm)", file=sys.stderr)
        return ExitCode.REFUSED

    robot = builtin_piper(with_geometry=False)
    limits = ReplayLimits(arm_speed_pct=args.arm_speed_pct, max_step_deg=args.max_step_deg,
                          max_start_distance_deg=args.max_start_distance_deg)
    offline = check_trajectory(traj, robot, limits)
    if offline:
        print("manisplat-replay: refused, nothing was sent:\n" + "\n".join(f"  - {p}" for p in offline),
              file=sys.stderr)
        return ExitCode.REFUSED

    stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    sim: SimArm | None = None
    arm: PiperArm | None = None
    try:
        try:
            if args.sim:
                start = np.radians(args.sim_start) if args.sim_start is not None else np.clip(
                    traj.q[0] + math.radians(SIM_START_OFFSET_DEG), robot.lower, robot.upper)
                sim = SimArm(start, float(traj.gripper[0]))
                arm = sim.arm
            else:
                arm = PiperArm.open(args.can, args.interface, read_only=args.dry_run)
            current = arm.wait_for_joint_state(timeout=2.0).q
        except (DriverError, TimeoutError, OSError) as exc:
            print(f"manisplat-replay: cannot read the arm's state: {exc}", file=sys.stderr)
            return ExitCode.DEVICE
        problems = check_trajectory(traj, robot, limits, current_q=current)
        print(_describe_checks(trajectory_figures(traj, robot, limits), args.speed, traj.source, convention.name,
                               tcp_mm))
        if problems:
            print("manisplat-replay: refused, nothing was sent:\n" + "\n".join(f"  - {p}" for p in problems),
                  file=sys.stderr)
            return ExitCode.REFUSED
        print(f"start is {np.degrees(np.abs(traj.q[0] - current)).max():.1f} deg from the arm's state: all checks pass")
        if args.dry_run:
            print("dry run: nothing was sent")
            return ExitCode.OK
        config = StreamConfig(arm_speed_pct=args.arm_speed_pct, max_tracking_error_deg=args.max_tracking_error_deg,
                              feedback_timeout_s=args.feedback_timeout_ms / 1e3)
        progress = _Progress() if sys.stderr.isatty() else None
        report: ReplayReport = replay(arm, traj, config, stop, on_progress=progress)
        if progress is not None:
            progress.end()
        print(report)
    finally:
        if sim is not None:
            sim.close()
            print(f"simulated bus: {sim.audit.resets} resets (0x150 B0=2), {sim.audit.disables} disables "
                  f"(0x471 01), {sim.audit.estops} e-stops, {sim.audit.joint_targets} joint targets")
        elif arm is not None:
            arm.close()
        for s, handler in previous.items():
            signal.signal(s, handler)
    return {"completed": ExitCode.OK, "interrupted": ExitCode.INTERRUPTED}.get(report.outcome, ExitCode.FAILED)


class _Progress:
    def __call__(self, done: float, total: float) -> None:
        sys.stderr.write(f"\rreplaying {done:6.2f} / {total:.2f} s")
        sys.stderr.flush()

    def end(self) -> None:
        sys.stderr.write("\n")


if __name__ == "__main__":
    sys.exit(main())
