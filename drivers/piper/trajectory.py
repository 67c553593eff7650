"""What a replay will command, and every check it must pass before anything moves. Pure.

A :class:`Trajectory` is an episode's joint and gripper targets in the arm's convention
(:mod:`.convention`), from its action columns when present (``a1..a6, a_gripper``: what was
commanded) else its measured joints, on a time axis scaled by ``speed``.
:func:`check_trajectory` lists every problem (all of them, not the first):

* non-finite values, times not strictly increasing;
* joint positions outside the robot's limits, gripper outside its range;
* velocity (finite differences between frames) above the robot's speed limits x the MOVE J speed
  % the arm is given; acceleration (second differences) above its acceleration limits; both say
  which ``--speed`` would pass;
* a jump between consecutive frames larger than ``max_step_deg`` (whatever the time between);
* a start further than ``max_start_distance_deg`` from the arm's current state.

:func:`approach` is the slow move from the current state to the start (a cosine ramp at a
fraction of the speed limits); :func:`sample` interpolates targets at the streaming rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from manisplat.drivers.piper.convention import JointConvention
from manisplat.episode import Episode
from manisplat.robot import RobotModel


@dataclass(frozen=True)
class Trajectory:
    """Targets in the arm's convention.

    Attributes:
        t: (N,) s from the first target, after scaling by ``speed``.
        q: (N, 6) rad; gripper: (N,) m.
        source: ``"actions"`` or ``"joints"`` (which frames.csv columns).
        speed: the time scale applied (2 = twice as fast).
    """

    t: np.ndarray
    q: np.ndarray
    gripper: np.ndarray
    source: str
    speed: float

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0]) if len(self.t) else 0.0


@dataclass(frozen=True)
class ReplayLimits:
    """Check settings.

    Attributes:
        arm_speed_pct: MOVE J speed % the arm is given (0x151 B2); velocity limits scale with it.
        max_step_deg: largest joint change between consecutive frames, deg.
        max_start_distance_deg: largest distance (any joint) between the arm and the start, deg.
    """

    arm_speed_pct: int = 100
    max_step_deg: float = 10.0
    max_start_distance_deg: float = 30.0


def trajectory_from_episode(episode: Episode, convention: JointConvention, speed: float = 1.0,
                            source: str = "auto", arm: str | None = None) -> Trajectory:
    """The targets of the episode's ``arm`` (None: its one arm; see the module docstring);
    ``source`` ``"auto"``, ``"actions"`` or ``"joints"``. ValueError for a bad speed, a missing
    action column or fewer than 2 frames."""
    if not (math.isfinite(speed) and speed > 0):
        raise ValueError(f"speed must be > 0, got {speed}")
    frames = episode.frames if arm is None else episode.arm_frames(arm)
    if len(frames) < 2:
        raise ValueError(f"{episode.path}: {len(frames)} frame(s); a replay needs at least 2")
    actions = frames.actions
    if source == "actions" and actions is None:
        names = episode.layout.arm(arm if arm is not None else episode.meta.robot.name).actions
        raise ValueError(f"{episode.path}: frames.csv has no action columns ({names[0]}..{names[5]}, {names[6]})")
    if source not in ("auto", "actions", "joints"):
        raise ValueError(f"source must be auto, actions or joints; got {source!r}")
    use_actions = actions is not None and source != "joints"
    q = actions[:, :6] if use_actions else frames.q
    gripper = actions[:, 6] if use_actions else frames.gripper
    t = (frames.t - frames.t[0]) / speed
    return Trajectory(t, convention.to_arm(q), gripper.copy(), "actions" if use_actions else "joints", float(speed))


def _floor3(x: float) -> str:
    """``x`` rounded down to 3 decimals (a speed that passes, as printed)."""
    return f"{math.floor(x * 1000) / 1000:.3f}"


def _joint_list(values: np.ndarray, fmt: str) -> str:
    return ", ".join(f"J{j + 1} {fmt.format(v)}" for j, v in enumerate(values))


def check_trajectory(traj: Trajectory, robot: RobotModel, limits: ReplayLimits,
                     current_q: np.ndarray | None = None) -> list[str]:
    """Every problem of ``traj`` for ``robot`` (empty when it may be replayed); see the module
    docstring. ``current_q`` (6,) rad is the arm's state (None: that check is not made)."""
    problems: list[str] = []
    t, q, g = traj.t, traj.q, traj.gripper
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q)) and np.all(np.isfinite(g))):
        return ["the trajectory holds NaN or infinite values"]
    dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.flatnonzero(dt <= 0)[0])
        return [f"frame {k + 1}: time {t[k + 1]:.6f} s is not after frame {k}'s {t[k]:.6f} s"]

    lo, hi = robot.lower, robot.upper
    for j in range(6):
        bad = np.flatnonzero((q[:, j] < lo[j] - 1e-9) | (q[:, j] > hi[j] + 1e-9))
        if bad.size:
            k = int(bad[0])
            problems.append(f"joint{j + 1} leaves its limits [{math.degrees(lo[j]):.2f}, "
                            f"{math.degrees(hi[j]):.2f}] deg on {bad.size} frame(s), first frame {k} at "
                            f"{math.degrees(q[k, j]):.2f} deg")
    g_lo, g_hi = robot.gripper.width_range if robot.gripper else (0.0, 0.07)
    bad = np.flatnonzero((g < g_lo - 1e-9) | (g > g_hi + 1e-9))
    if bad.size:
        problems.append(f"gripper leaves [{g_lo * 1e3:.1f}, {g_hi * 1e3:.1f}] mm on {bad.size} frame(s), "
                        f"first frame {int(bad[0])} at {g[bad[0]] * 1e3:.2f} mm")

    step = np.abs(np.diff(q, axis=0))
    max_step = math.radians(limits.max_step_deg)
    if np.any(step > max_step):
        k, j = np.unravel_index(int(np.argmax(step)), step.shape)
        problems.append(f"a jump of {math.degrees(step[k, j]):.2f} deg on joint{j + 1} between frames {k} and {k + 1} "
                        f"(more than {limits.max_step_deg:g} deg between two frames)")

    vmax = robot.velocity_limits * limits.arm_speed_pct / 100.0
    v = np.diff(q, axis=0) / dt[:, None]
    ratio_v = np.abs(v) / vmax
    if ratio_v.max() > 1.0 + 1e-9:
        k, j = np.unravel_index(int(np.argmax(ratio_v)), ratio_v.shape)
        problems.append(f"velocity {abs(v[k, j]):.3f} rad/s on joint{j + 1} between frames {k} and {k + 1} exceeds "
                        f"{vmax[j]:.3f} rad/s (speed limit x {limits.arm_speed_pct} %); "
                        f"replay with --speed {_floor3(traj.speed / ratio_v.max())} or lower")
    if len(t) >= 3:
        amax = robot.acceleration_limits
        a = (v[1:] - v[:-1]) / (0.5 * (dt[1:] + dt[:-1]))[:, None]
        ratio_a = np.abs(a) / amax
        if ratio_a.max() > 1.0 + 1e-9:
            k, j = np.unravel_index(int(np.argmax(ratio_a)), ratio_a.shape)
            passes = _floor3(traj.speed / math.sqrt(ratio_a.max()))
            problems.append(f"acceleration {abs(a[k, j]):.3f} rad/s^2 on joint{j + 1} at frame {k + 1} exceeds "
                            f"{amax[j]:.3f} rad/s^2; replay with --speed {passes} or lower")
    if current_q is not None:
        distance = np.abs(q[0] - np.asarray(current_q, dtype=np.float64))
        if np.degrees(distance.max()) > limits.max_start_distance_deg:
            problems.append(f"the start is {math.degrees(distance.max()):.1f} deg from the arm's current state "
                            f"(more than {limits.max_start_distance_deg:g} deg; per joint: "
                            f"{_joint_list(np.degrees(distance), '{:.1f}')}); move the arm closer first")
    return problems


def trajectory_figures(traj: Trajectory, robot: RobotModel, limits: ReplayLimits) -> dict[str, float]:
    """Peak velocity and acceleration as fractions of the limits, the duration and the frames."""
    dt = np.diff(traj.t)
    v = np.diff(traj.q, axis=0) / dt[:, None]
    out = {"frames": float(len(traj.t)), "duration_s": traj.duration,
           "peak_velocity_of_limit": float((np.abs(v) / (robot.velocity_limits * limits.arm_speed_pct / 100)).max())}
    if len(dt) >= 2:
        a = (v[1:] - v[:-1]) / (0.5 * (dt[1:] + dt[:-1]))[:, None]
        out["peak_acceleration_of_limit"] = float((np.abs(a) / robot.acceleration_limits).max())
    return out


def sample(traj: Trajectory, t: float) -> tuple[np.ndarray, float]:
    """Targets at ``t`` s (linear between frames, held at the ends): (6,) rad and gripper m."""
    q = np.array([np.interp(t, traj.t, traj.q[:, j]) for j in range(6)])
    return q, float(np.interp(t, traj.t, traj.gripper))


def approach(q_from: np.ndarray, q_to: np.ndarray, robot: RobotModel, fraction: float = 0.1,
             min_duration_s: float = 1.0) -> tuple[float, Callable[[float], np.ndarray]]:
    """A slow move from ``q_from`` to ``q_to``: ``(duration s, q(s) for s in [0, duration])``, a
    cosine ramp whose peak speed is ``fraction`` of each joint's speed limit."""
    q_from = np.asarray(q_from, dtype=np.float64)
    delta = np.asarray(q_to, dtype=np.float64) - q_from
    duration = max(min_duration_s, float((math.pi / 2 * np.abs(delta) / (robot.velocity_limits * fraction)).max()))

    def at(s: float) -> np.ndarray:
        x = min(max(s / duration, 0.0), 1.0)
        return q_from + delta * 0.5 * (1.0 - math.cos(math.pi * x))

    return duration, at
