"""Live capture of a calibration episode: (joint state, image) pairs at still robot poses, with
advice on which poses still add information.

The arm is only read, never commanded: the user moves it (teach mode or any controller). Every
camera frame is paired with the arm state interpolated at the frame's timestamp. A pose is
*still* when no joint moved more than ``still_tol_rad`` over the last ``settle_s`` seconds.
In ``auto`` mode a still pose is recorded when the board is detected and the pose adds
information (:class:`PoseAdvisor`); otherwise the user presses Enter to record the current
pose (``q`` + Enter finishes). Each recorded pose writes ``frames_per_pose`` frames with a
``pose`` column, so ``manisplat-calibrate solve`` reads the result like any episode.
"""

from __future__ import annotations

import collections
import queue
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from manisplat.calib.board import BoardSpec
from manisplat.calib.camera import CameraModel
from manisplat.calib.detect import BoardDetector
from manisplat.calib.handeye import motion_diversity
from manisplat.calib.poses import rotation_deg
from manisplat.drivers.base import Arm, Camera, JointState
from manisplat.episode import CameraInfo, EpisodeWriter, RobotInfo
from manisplat.robot import RobotModel

MIN_NEW_ANGLE_DEG = 15.0


@dataclass(frozen=True)
class Advice:
    """What a candidate pose would add.

    Attributes:
        adds: True when the pose is at least ``min_new_angle_deg`` from every recorded pose
            or widens the rotation-axis spread by 2 deg or more.
        nearest_deg: rotation to the nearest recorded pose (inf for the first).
        spread_before_deg, spread_after_deg: rotation-axis spread without / with it.
        message: one line for the user.
    """

    adds: bool
    nearest_deg: float
    spread_before_deg: float
    spread_after_deg: float
    message: str


class PoseAdvisor:
    """Keeps the recorded robot poses and judges new ones (rotation diversity)."""

    def __init__(self, min_new_angle_deg: float = MIN_NEW_ANGLE_DEG) -> None:
        self.min_new_angle_deg = min_new_angle_deg
        self.poses: list[np.ndarray] = []

    def assess(self, T_base_link: np.ndarray) -> Advice:
        """Advice for a candidate pose (4, 4)."""
        if not self.poses:
            return Advice(True, float("inf"), 0.0, 0.0, "first pose: record it")
        P = np.stack(self.poses)
        nearest = float(rotation_deg(np.swapaxes(P[:, :3, :3], -1, -2) @ T_base_link[:3, :3]).min())
        before = motion_diversity(P)
        after = motion_diversity(np.concatenate([P, T_base_link[None]]))
        adds = nearest >= self.min_new_angle_deg or after.axis_spread_deg >= before.axis_spread_deg + 2.0
        axis = np.round(before.weakest_axis, 2).tolist()
        if adds:
            msg = (f"adds information: {nearest:.0f} deg from the nearest pose; axis spread "
                   f"{before.axis_spread_deg:.0f} -> {after.axis_spread_deg:.0f} deg")
        else:
            msg = (f"little new information: only {nearest:.0f} deg from a recorded pose; tilt the gripper "
                   f"20-45 deg, preferably about {axis} (link frame, least covered so far)")
        return Advice(adds, nearest, before.axis_spread_deg, after.axis_spread_deg, msg)

    def add(self, T_base_link: np.ndarray) -> None:
        self.poses.append(np.asarray(T_base_link, dtype=np.float64))

    def summary(self) -> str:
        if len(self.poses) < 2:
            return f"{len(self.poses)} pose(s) recorded"
        d = motion_diversity(np.stack(self.poses))
        ok = "enough" if len(self.poses) >= 10 and d.axis_spread_deg >= 15 else "more needed (aim for 15-25)"
        return (f"{len(self.poses)} poses, axis spread {d.axis_spread_deg:.0f} deg, largest rotation "
                f"{d.max_angle_deg:.0f} deg: {ok}")


class _ArmHistory:
    """Recent joint states, read up to a given time, interpolated at frame timestamps.

    ``clock="source"`` compares ``JointState.t`` with the frame time (replays share one clock);
    ``"host"`` uses ``JointState.t_host`` (a live CAN arm stamps on the bus clock, an OAK frame
    on the host's monotonic clock).
    """

    def __init__(self, arm: Arm, window_s: float, clock: str = "source") -> None:
        if clock not in ("source", "host"):
            raise ValueError(f"clock must be 'source' or 'host'; got {clock!r}")
        self.arm = arm
        self.window_s = window_s
        self.states: collections.deque[JointState] = collections.deque()
        self.times: collections.deque[float] = collections.deque()
        self.last_seq = -1
        self.host = clock == "host"

    def read_until(self, t: float, timeout: float = 1.0) -> None:
        while not self.times or self.times[-1] < t:
            s = self.arm.wait_for_joint_state(self.last_seq, timeout)
            self.last_seq = s.seq
            self.states.append(s)
            self.times.append(s.t_host if self.host else s.t)
        while len(self.times) > 2 and self.times[-1] - self.times[0] > self.window_s:
            self.states.popleft()
            self.times.popleft()

    def q_at(self, t: float) -> np.ndarray:
        ts = np.array(self.times)
        qs = np.stack([s.q for s in self.states])
        return np.array([np.interp(t, ts, qs[:, j]) for j in range(qs.shape[1])])

    def gripper_at(self, t: float) -> float:
        g = self.states[-1].gripper
        return float(g) if np.isfinite(g) else 0.0

    def still(self, settle_s: float, tol: float) -> bool:
        if not self.times or self.times[-1] - self.times[0] < settle_s * 0.95:
            return False
        t_end = self.times[-1]
        recent = np.stack([s.q for s, t in zip(self.states, self.times) if t >= t_end - settle_s])
        return bool(np.abs(recent - recent[-1]).max() <= tol)


def _stdin_commands() -> "queue.Queue[str]":
    q: queue.Queue[str] = queue.Queue()

    def reader() -> None:
        while True:
            try:
                line = input()
            except EOFError:
                q.put("q")
                return
            q.put(line.strip().lower() or "take")

    threading.Thread(target=reader, daemon=True).start()
    return q


def capture(arm: Arm, camera: Camera, robot: RobotModel, spec: BoardSpec, out: str | Path, *, link: str = "link6",
            mount: str = "base", auto: bool = False, settle_s: float = 1.0, still_tol_rad: float = 0.002,
            frames_per_pose: int = 3, max_poses: int = 25, min_new_angle_deg: float = MIN_NEW_ANGLE_DEG,
            commands: "queue.Queue[str] | None" = None, say: Callable[[str], None] = print,
            description: str = "builtin:agilex_piper", overwrite: bool = False, clock: str = "source") -> int:
    """Record a calibration episode into ``out``; returns the number of poses recorded.

    ``clock``: see :class:`_ArmHistory` (``"host"`` for a live CAN arm with an OAK camera).
    Ends when ``max_poses`` are recorded, the camera ends (replays), ``q`` is entered, or on
    Ctrl-C; the episode is closed properly in every case.
    """
    cam_model = CameraModel(K=camera.K, dist=camera.dist, width=camera.width, height=camera.height)
    detector = BoardDetector(spec)
    advisor = PoseAdvisor(min_new_angle_deg)
    history = _ArmHistory(arm, window_s=max(2.0 * settle_s, 1.0), clock=clock)
    commands = commands if commands is not None or auto else _stdin_commands()
    info = CameraInfo(name="calibration", width=camera.width, height=camera.height, K=camera.K, dist=camera.dist,
                      mount=mount)
    poses = 0
    pending = 0  # frames still to record for the current pose
    want = False
    last_advice = ""
    with EpisodeWriter(out, info, RobotInfo(description=description), fps=30.0, extra_frame_columns=("pose",),
                       overwrite=overwrite) as writer:
        say("move the arm to a pose with the board in view and hold it still; "
            + ("poses that add information are recorded automatically" if auto else "press Enter to record, q to finish"))
        try:
            while poses < max_poses:
                while commands is not None and not commands.empty():
                    c = commands.get_nowait()
                    if c == "q":
                        raise StopIteration
                    want = True
                frame = camera.read()
                if frame is None:
                    break
                history.read_until(frame.t)
                q = history.q_at(frame.t)
                if pending:
                    writer.add_frame(frame.t, q, history.gripper_at(frame.t), frame.rgb, extra={"pose": poses - 1})
                    pending -= 1
                    continue
                if not history.still(settle_s, still_tol_rad) or not (auto or want):
                    continue
                T = robot.link_pose(q, link).numpy()
                advice = advisor.assess(T)
                det = detector.detect(frame.rgb)
                view, why = detector.view(frame.seq, det, cam_model)
                if view is None:
                    if want or advice.message != last_advice:
                        say(f"board not usable here ({why}); move it into view")
                    want, last_advice = False, advice.message
                    continue
                if auto and not advice.adds:
                    if advice.message != last_advice:
                        say(advice.message)
                    last_advice = advice.message
                    continue
                advisor.add(T)
                poses += 1
                writer.add_frame(frame.t, q, history.gripper_at(frame.t), frame.rgb, extra={"pose": poses - 1})
                pending = frames_per_pose - 1
                want = False
                say(f"pose {poses}: {advice.message}. {advisor.summary()}")
        except (StopIteration, KeyboardInterrupt):
            pass
        except TimeoutError as exc:
            say(f"stopped: no joint state ({exc})")
    say(f"wrote {out}: {advisor.summary()}")
    return poses
