"""A built-in sample episode: the built-in PiPER picks a 4 cm box and places it 18 cm away,
seen by a fixed camera, with exact ground truth. No files, devices or GPU needed.

The motion is scripted in task space (TCP keyframes pointing down), solved by IK and joined by
minimum-jerk joint moves; the box rides in the gripper between grasp and release. Images come
from :mod:`manisplat.render.painter` (flat shading, a checkered table). Written through
:class:`EpisodeWriter`, so the sample is exactly what a recorder would leave, plus ``gt.npz``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from manisplat.episode.format import GT_FILE
from manisplat.episode.groundtruth import write_gt
from manisplat.episode.meta import CameraInfo, RobotInfo
from manisplat.episode.writer import EpisodeWriter
from manisplat.robot import builtin_piper, solve_ik
from manisplat.render.painter import Camera, GroundPlane, MeshItem, look_at, render

BOX_SIZE = 0.04
OPEN, GRASP = 0.07, 0.038  # gripper widths (m): fully open, closed on the 4 cm box
TABLE_LABEL, BOX_LABEL = 11, 10
PICK_XY, PLACE_XY = (0.30, -0.09), (0.28, 0.09)  # the box's start and goal (m, base frame)
TASKS = {"pick_place": "pick the box and place it to the left", "reach": "reach above the box and come back"}
LINK_COLORS = {
    "base_link": (60, 60, 66), "link1": (210, 210, 215), "link2": (215, 215, 220), "link3": (205, 205, 210),
    "link4": (70, 70, 76), "link5": (200, 200, 205), "link6": (55, 55, 60), "link7": (90, 90, 95),
    "link8": (90, 90, 95),
}


@dataclass(frozen=True)
class Keyframe:
    """A scripted instant: TCP position (m, base frame), gripper width (m) and phase name."""

    time: float
    position: tuple[float, float, float]
    gripper: float
    phase: str


def _script(duration: float, task: str = "pick_place", pick: tuple[float, float] = PICK_XY,
            place: tuple[float, float] = PLACE_XY) -> list[Keyframe]:
    """Pick at ``pick``, place at ``place`` ((x, y) m, base frame); or, for "reach", hover 4 cm
    above the box and come back with the gripper open. Times scaled to ``duration`` seconds."""
    z_grasp, z_up = BOX_SIZE / 2, 0.14
    if task == "reach":
        raw = [
            (0.00, (0.25, 0.0, 0.24), OPEN, "approach"),
            (0.30, (*pick, z_up), OPEN, "approach"),
            (0.50, (*pick, BOX_SIZE + 0.04), OPEN, "descend"),
            (0.65, (*pick, BOX_SIZE + 0.04), OPEN, "hover"),
            (0.85, (*pick, z_up), OPEN, "ascend"),
            (1.00, (0.25, 0.0, 0.24), OPEN, "return"),
        ]
        return [Keyframe(f * duration, p, g, phase) for f, p, g, phase in raw]
    if task != "pick_place":
        raise ValueError(f"task must be 'pick_place' or 'reach', got {task!r}")
    raw = [
        (0.00, (0.25, 0.0, 0.24), OPEN, "approach"),
        (0.18, (*pick, z_up), OPEN, "approach"),
        (0.30, (*pick, z_grasp), OPEN, "descend"),
        (0.38, (*pick, z_grasp), GRASP, "grasp"),
        (0.50, (*pick, z_up), GRASP, "lift"),
        (0.66, (*place, z_up), GRASP, "transfer"),
        (0.78, (*place, z_grasp), GRASP, "lower"),
        (0.86, (*place, z_grasp), OPEN, "release"),
        (1.00, (*place, 0.20), OPEN, "retreat"),
    ]
    return [Keyframe(f * duration, p, g, phase) for f, p, g, phase in raw]


def _tcp_down(position, tilt_deg: float = 25.0) -> np.ndarray:
    """TCP pose approaching downwards, leaning ``tilt_deg`` outward from the base (straight down
    is out of joint 5's +-70 deg range over most of the table), closing tangentially."""
    p = np.asarray(position, dtype=np.float64)
    radial = np.array([p[0], p[1], 0.0]) / np.hypot(p[0], p[1])
    tilt = math.radians(tilt_deg)
    z = math.sin(tilt) * radial - math.cos(tilt) * np.array([0.0, 0.0, 1.0])
    y = np.cross([0.0, 0.0, 1.0], radial)
    T = np.eye(4)
    T[:3, :3] = np.stack([np.cross(y, z), y, z], axis=1)
    T[:3, 3] = p
    return T


def _min_jerk(s: np.ndarray) -> np.ndarray:
    return s**3 * (10 - 15 * s + 6 * s**2)


@dataclass(frozen=True)
class SampleTrajectory:
    """Joint and gripper trajectory of the sample, a continuous function of time."""

    times: np.ndarray  # (K,) keyframe times, s
    q: np.ndarray  # (K, 6) keyframe joints, rad
    gripper: np.ndarray  # (K,) keyframe widths, m
    phases: list[str]

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joints (N, 6), gripper (N,) and phase (N,) at times ``t`` (N,), min-jerk between keyframes."""
        k = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 2)
        s = _min_jerk(np.clip((t - self.times[k]) / (self.times[k + 1] - self.times[k]), 0.0, 1.0))
        q = self.q[k] + s[:, None] * (self.q[k + 1] - self.q[k])
        g = self.gripper[k] + s * (self.gripper[k + 1] - self.gripper[k])
        return q, g, np.array([self.phases[i + 1] for i in k])


def sample_trajectory(duration: float, task: str = "pick_place", pick: tuple[float, float] = PICK_XY,
                      place: tuple[float, float] = PLACE_XY) -> SampleTrajectory:
    """Solve the keyframes of :func:`_script` by IK, each seeded by the previous one (one continuous branch)."""
    return solve_keyframes(_script(duration, task, pick, place))


def solve_keyframes(keys: list[Keyframe]) -> SampleTrajectory:
    """The built-in PiPER's joints at each keyframe (TCP pointing down, :func:`_tcp_down`), by IK
    seeded with the previous keyframe's solution."""
    robot = builtin_piper(with_geometry=False)
    seed = torch.tensor([0.0, 1.2, -1.3, 0.0, 0.6, 0.0], dtype=torch.float64)
    qs = []
    for key in keys:
        result = solve_ik(robot, torch.tensor(_tcp_down(key.position)), q_init=seed)
        if not bool(result.success):
            raise RuntimeError(f"sample script: keyframe {key.phase} at {key.position} is not reachable")
        seed = result.q
        qs.append(result.q.numpy())
    return SampleTrajectory(
        np.array([k.time for k in keys]), np.stack(qs), np.array([k.gripper for k in keys]), [k.phase for k in keys]
    )


def _box_poses(trajectory: SampleTrajectory, robot, t: np.ndarray, start_xy) -> np.ndarray:
    """T_base_box [N, 4, 4] at times ``t`` (s): it rests until the grasp keyframe, rides rigidly in
    the gripper until the end of the "lower" keyframe, then rests there (times of the continuous
    trajectory, not of the frames: at a low frame rate no frame falls on the release)."""
    rest = np.eye(4)
    rest[:3, 3] = (*start_xy, BOX_SIZE / 2)
    out = np.repeat(rest[None], len(t), axis=0)
    if "grasp" not in trajectory.phases or "lower" not in trajectory.phases:
        return out  # a reach: the box never moves

    def tcp_at(times: np.ndarray) -> np.ndarray:
        return robot.tcp_pose(torch.tensor(trajectory.at(np.asarray(times, np.float64))[0])).numpy()

    t_pick = trajectory.times[trajectory.phases.index("grasp")]
    t_place = trajectory.times[trajectory.phases.index("lower")]
    T_rel = np.linalg.inv(tcp_at([t_pick])[0]) @ rest
    carried = (t > t_pick) & (t < t_place)
    if carried.any():
        out[carried] = tcp_at(t[carried]) @ T_rel
    out[t >= t_place] = tcp_at([t_place])[0] @ T_rel
    return out


def write_sample_episode(
    out: str | Path, *, frames: int = 64, fps: float = 8.0, width: int = 160, height: int = 120, seed: int = 0,
    task: str = "pick_place", overwrite: bool = False, exact_depth: bool = True,
    pick: tuple[float, float] = PICK_XY, camera_shift: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> Path:
    """Write the sample episode to ``out`` and return its path.

    Args:
        frames: number of camera frames (the motion is stretched to ``frames / fps`` seconds; the
            defaults, 64 frames at 8 fps, keep every joint within 80 % of the PiPER's acceleration
            limit, so the sample replays at speed 1: ``manisplat-replay``'s checks pass).
        seed: perturbs the camera position by up to 5 cm (0: the nominal view).
        task: "pick_place" (the box is moved) or "reach" (the arm hovers over it; it never moves).
        exact_depth: depth exact on the meshes (:func:`manisplat.render.painter.render`), so that the
            reconstruction's checks against the robot model (extrinsic, tracking, slip) hold as on a
            good recording; False: one depth per triangle, off by several millimetres on the
            robot's long faces (for tests of the checks that must notice such depth).
        pick: the box's start (x, y) m in the base frame (the arm picks it there).
        camera_shift: the camera that takes the images sits this far (x, y, z m, base frame) from
            where the episode says it is: a mount bumped after calibration (``gt.npz`` has the true one).
    """
    if frames < 8:
        raise ValueError(f"the sample needs at least 8 frames, got {frames}")
    duration = (frames - 1) / fps
    trajectory = sample_trajectory(duration, task, pick=pick)
    robot = builtin_piper()
    rng = np.random.default_rng(seed)
    eye = np.array([0.95, -0.62, 0.62]) + (rng.uniform(-0.05, 0.05, 3) if seed else 0.0)
    f = 0.85 * width
    K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    calibrated = Camera(K, width, height, look_at(eye, (0.18, 0.0, 0.17)))
    shifted = np.eye(4)
    shifted[:3, 3] = camera_shift
    camera = Camera(K, width, height, shifted @ calibrated.T_world_cam)
    ground = GroundPlane((-0.4, 1.2, -0.9, 0.9), 0.05, ((178, 150, 112), (150, 124, 90)), TABLE_LABEL)
    labels = {0: "background", TABLE_LABEL: "table", BOX_LABEL: "object/box"}
    labels.update({i + 1: f"robot/{name}" for i, name in enumerate(robot.link_names)})
    box_mesh = trimesh.creation.box(extents=(BOX_SIZE,) * 3)

    t_frames = np.arange(frames) / fps
    q, g, phase = trajectory.at(t_frames)
    T_tcp = robot.tcp_pose(torch.tensor(q)).numpy()
    T_box = _box_poses(trajectory, robot, t_frames, pick)
    links = robot.forward_kinematics(torch.tensor(q), torch.tensor(g)).numpy()  # [T, L, 4, 4]

    out = Path(out)
    with EpisodeWriter(
        out, CameraInfo("ego", width, height, K, mount="base", T_mount_cam=calibrated.T_world_cam),
        RobotInfo(description="builtin:agilex_piper"), fps, source="simulation", depth_scale=1e-4,
        labels=labels, objects=["box"], extra_frame_columns=("a1", "a2", "a3", "a4", "a5", "a6", "a_gripper"),
        extra_meta={"task": TASKS[task], "generator": "manisplat.episode.synthetic"},
        overwrite=overwrite,
    ) as writer:
        t_joint = np.arange(0.0, duration + 1e-9, 0.005)
        qj, gj, _ = trajectory.at(t_joint)
        for tj, qi, gi in zip(t_joint, qj, gj):
            writer.add_joint_sample(float(tj), qi, float(gi))
        action_q, action_g, _ = trajectory.at(np.minimum(t_frames + 1.0 / fps, duration))
        for k in range(frames):
            meshes = [_posed(box_mesh, T_box[k], (200, 60, 50), BOX_LABEL)]
            for i, name in enumerate(robot.link_names):
                for visual in robot.visuals.get(name, []):
                    meshes.append(_posed(visual.mesh, links[k, i], LINK_COLORS[name], i + 1))
            rgb, depth, mask = render(camera, meshes, ground, exact_depth=exact_depth)
            action = dict(zip(("a1", "a2", "a3", "a4", "a5", "a6"), action_q[k].tolist()))
            action["a_gripper"] = float(action_g[k])
            writer.add_frame(float(t_frames[k]), q[k], float(g[k]), rgb, depth=depth, mask=mask, extra=action)
    _write_gt(out, t_frames, q, g, T_tcp, T_box, phase, K, np.linalg.inv(camera.T_world_cam), links, robot.link_names)
    return out


def _posed(mesh: trimesh.Trimesh, T: np.ndarray, color, label: int) -> MeshItem:
    vertices = mesh.vertices @ T[:3, :3].T + T[:3, 3]
    return MeshItem(vertices, np.asarray(mesh.faces), color, label)


def _write_gt(out: Path, t, q, g, T_tcp, T_box, phase, K, T_cam_base, links, link_names) -> None:
    """``gt.npz`` as ``docs/episode-format.md`` lists it, written atomically."""
    arrays = {"t": t, "q": q, "gripper": g, "T_base_tcp": T_tcp, "T_base_box": T_box, "phase": phase.astype(str),
              "K": K, "T_cam_base": T_cam_base, "T_base_links": links, "link_names": np.array(link_names)}
    write_gt(out / GT_FILE, arrays, compressed=False)


__all__ = ["SampleTrajectory", "sample_trajectory", "write_sample_episode"]
