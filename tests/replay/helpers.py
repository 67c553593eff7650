"""Small episodes and PiPER URDFs (joints only) for the replay tests, made in tmp folders."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from manisplat.episode import ACTION_COLUMNS, ArmInfo, CameraInfo, EpisodeWriter, EpisodeWriterV2, RobotInfo

# joint1..joint6 (xyz, rpy, axis, lower, upper) of AgileX piper_description (ros-noetic-no-aloha @4f22c61)
OLD_URDF = [((0, 0, 0.123), (0, 0, -1.5708), (0, 0, 1), -2.618, 2.618),
            ((0, 0, 0), (1.5708, -0.10095, -1.5708), (0, 0, 1), 0, 3.14),
            ((0.28503, 0, 0), (0, 0, 1.3826), (0, 0, 1), -2.967, 0),
            ((0.021984, 0.25075, 0), (-1.5708, 0, 0), (0, 0, -1), -1.832, 1.832),
            ((0, 0, 0), (1.5708, -0.087266, 0), (0, 0, 1), -1.22, 1.22),
            ((0, 0.091, 0.0014165), (-1.5708, -1.5708, 0), (0, 0, -1), -3.14, 3.14)]
# the same of robot_description/piper_description @116596ce (reference piper_can.md 1.9)
NEW_URDF = [((0, 0, 0.123), (0, 0, 0), (0, 0, 1), -2.618, 2.618),
            ((0, 0, 0), (1.5708, -0.1359, -3.1416), (0, 0, 1), 0, 3.14),
            ((0.28503, 0, 0), (0, 0, -1.7939), (0, 0, 1), -2.967, 0),
            ((-0.021984, -0.25075, 0), (1.5708, 0, 0), (0, 0, 1), -1.745, 1.745),
            ((0, 0, 0), (-1.5708, 0, 0), (0, 0, 1), -1.22, 1.22),
            ((8.8259e-05, -0.091, 0), (1.5708, 0, 0), (0, 0, 1), -2.0944, 2.0944)]


def write_urdf(path: Path, joints: list, name: str = "piper") -> Path:
    """A PiPER URDF with these arm joints and two prismatic fingers (no meshes)."""
    v = lambda xs: " ".join(repr(float(x)) for x in xs)  # noqa: E731
    links = "".join(f'<link name="{n}"/>' for n in ["base_link"] + [f"link{i}" for i in range(1, 9)])
    parts = []
    for i, (xyz, rpy, axis, lo, hi) in enumerate(joints, start=1):
        parent = "base_link" if i == 1 else f"link{i - 1}"
        parts.append(f'<joint name="joint{i}" type="revolute"><origin xyz="{v(xyz)}" rpy="{v(rpy)}"/>'
                     f'<parent link="{parent}"/><child link="link{i}"/><axis xyz="{v(axis)}"/>'
                     f'<limit lower="{lo}" upper="{hi}" effort="100" velocity="1"/></joint>')
    for i, (rpy, axis, lo, hi) in ((7, ("1.5708 0 1.5708", "0 0 -1", -0.038, 0)),
                                   (8, ("-1.5708 0 1.5708", "0 0 1", 0, 0.038))):
        parts.append(f'<joint name="joint{i}" type="prismatic"><origin xyz="0 0 0.13503" rpy="{rpy}"/>'
                     f'<parent link="link6"/><child link="link{i}"/><axis xyz="{axis}"/>'
                     f'<limit lower="{lo}" upper="{hi}" effort="100" velocity="1"/></joint>')
    path.write_text(f'<?xml version="1.0"?><robot name="{name}">{links}{"".join(parts)}</robot>\n')
    return path


def write_episode(path: Path, t: np.ndarray, q: np.ndarray, gripper: np.ndarray, *,
                  description: str = "builtin:agilex_piper", actions: np.ndarray | None = None) -> Path:
    """An episode with these joints (rad) and gripper (m) at times ``t`` (s), 8x6 images."""
    K = np.array([[8.0, 0, 3.5], [0, 8.0, 2.5], [0, 0, 1]])
    columns = ACTION_COLUMNS if actions is not None else ()
    with EpisodeWriter(path, CameraInfo("c", 8, 6, K), RobotInfo(description=description), 10.0,
                       extra_frame_columns=columns) as writer:
        for i in range(len(t)):
            extra = dict(zip(ACTION_COLUMNS, actions[i])) if actions is not None else None
            writer.add_frame(t[i], q[i], gripper[i], np.zeros((6, 8, 3), np.uint8), extra=extra)
    return path


def base_at(y: float) -> np.ndarray:
    """``T_world_base`` (4, 4) of an arm standing at ``y`` m on the world's y axis (a Cobot Magic's arms: +-0.3)."""
    T = np.eye(4)
    T[1, 3] = y
    return T


def write_arms_episode(path: Path, t: np.ndarray, q: dict[str, np.ndarray], gripper: dict[str, np.ndarray],
                       bases: dict[str, np.ndarray], *, description: str = "builtin:agilex_piper") -> Path:
    """A version 2 episode of these named arms (joints (T, 6) rad, gripper (T,) m, bases (4, 4)) at
    times ``t`` (s), one 8x6 camera on the world; the joints are the actions as well."""
    K = np.array([[8.0, 0, 3.5], [0, 8.0, 2.5], [0, 0, 1]])
    arms = [ArmInfo(name=n, description=description, T_world_base=bases[n]) for n in q]
    camera = CameraInfo("cam_high", 8, 6, K, mount="world", T_mount_cam=np.eye(4))
    with EpisodeWriterV2(path, arms, [camera], 10.0, source="simulation", actions=True) as writer:
        for i in range(len(t)):
            state = {n: np.r_[q[n][i], gripper[n][i]] for n in q}
            writer.add_frame(t[i], state, {"cam_high": np.zeros((6, 8, 3), np.uint8)}, actions=state)
    return path


def smooth_motion(duration: float = 1.5, fps: float = 20.0, amplitude_deg: float = 8.0,
                  start: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(t, q, gripper)``: every joint swings by ``amplitude_deg`` and back (1 - cos), from
    ``start`` (default: J2 60 deg, J3 -60 deg), the gripper from 60 to 40 mm."""
    t = np.arange(0.0, duration + 1e-9, 1.0 / fps)
    base = np.radians([0.0, 60.0, -60.0, 0.0, 0.0, 0.0]) if start is None else start
    s = 0.5 * (1 - np.cos(2 * np.pi * t / duration))
    q = base + np.radians(amplitude_deg) * s[:, None] * np.array([1, 1, -1, 1, 1, 1])
    return t, q, 0.06 - 0.02 * s
