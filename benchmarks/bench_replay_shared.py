"""manisplat-replay on every shared/data episode: convention map, checks, and tracking error on the simulated PiPER.

Each episode names AgileX's piper_description URDF (the old CAD) in robot.description; its
angles are mapped to the arm's (piper_sdk's) convention (``manisplat.drivers.piper.convention``),
checked by FK (TCP discrepancy), then the action columns are checked (limits, velocity at 100 %,
acceleration, jumps, start distance) and streamed at 200 Hz in MOVE J to a ``SimulatedPiper``
(first-order lag, tau 50 ms) that starts 3 deg away from the start on every joint. An episode
refused at speed 1 is reported as such and replayed at the highest speed its checks allow.
Tracking error per joint, deg: max and RMS against the target in effect, and after removing the
best constant lag; the final error after settling; and the commands that must never appear.
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

from benchmarks._harness import BenchContext
from manisplat.drivers.piper.convention import convention_for, tcp_discrepancy_mm
from manisplat.drivers.piper.streamer import StreamConfig, replay
from manisplat.drivers.piper.trajectory import ReplayLimits, check_trajectory, trajectory_from_episode
from manisplat.drivers.replay_cli import SIM_START_OFFSET_DEG, SimArm
from manisplat.episode import Episode
from manisplat.robot import builtin_piper

THREADED = False


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    data = ctx.require_shared("data")
    robot = builtin_piper(with_geometry=False)
    rows = []
    for path in sorted(p for p in data.iterdir() if (p / "episode.json").is_file()):
        rows += replay_rows(path, robot, ReplayLimits())
    ctx.notes.append("max/rms: worst joint; 'lag' columns after removing the best constant delay (the simulated "
                     "MOVE J planner lags by ~tau); the sim's gripper follows at 0.1 m/s, hence its error")
    return rows


def replay_rows(path, robot, limits: ReplayLimits) -> list[dict[str, Any]]:
    """One episode streamed on the simulated PiPER (3 deg away at the start): a "refused" row when
    speed 1 fails the checks (then replayed at the highest speed they allow), and the result row."""
    rows = []
    ep = Episode.open(path)
    conv = convention_for(ep.meta.robot.description, ep.path)
    speed = 1.0
    traj = trajectory_from_episode(ep, conv, speed)
    source_q = ep.frames.actions[:, :6] if traj.source == "actions" else ep.frames.q
    tcp_mm = tcp_discrepancy_mm(conv, ep.meta.robot.description, ep.path, source_q)
    problems = check_trajectory(traj, robot, limits)
    if problems:
        rows.append({"episode": path.name, "speed": speed, "outcome": "refused", "detail": problems[0][:90]})
        speed = min(float(m) for p in problems for m in re.findall(r"--speed ([0-9.]+)", p))
        traj = trajectory_from_episode(ep, conv, speed)
        assert check_trajectory(traj, robot, limits) == []
    sim = SimArm(np.clip(traj.q[0] + math.radians(SIM_START_OFFSET_DEG), robot.lower, robot.upper),
                 float(traj.gripper[0]))
    try:
        report = replay(sim.arm, traj, StreamConfig())
    finally:
        sim.close()
    tr = report.tracking
    rows.append({"episode": path.name, "speed": speed, "outcome": report.outcome, "detail": conv.name[:45],
                 "tcp_map_mm": tcp_mm, "duration_s": traj.duration, "approach_s": report.approach_s,
                 "max_deg": float(tr.max_deg.max()), "rms_deg": float(tr.rms_deg.max()),
                 "lag_ms": tr.lag_s * 1e3, "lag_max_deg": float(tr.lag_max_deg.max()),
                 "lag_rms_deg": float(tr.lag_rms_deg.max()), "gripper_settled_max_mm": tr.gripper.settled_max_mm,
                 "final_deg": float(report.final_error_deg.max()) if report.final_error_deg is not None else None,
                 "resets": sim.audit.resets, "disables": sim.audit.disables, "late_ticks": report.late_ticks})
    return rows
