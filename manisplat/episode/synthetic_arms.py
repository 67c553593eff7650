"""A built-in two-arm sample episode (format version 2): two built-in PiPERs 0.6 m apart, facing
+x, each picks its own 4 cm box and places it 12 cm further towards its own side, seen by one
world-fixed camera from behind and above (and, on request, by a wrist camera on each arm's link6,
as on an AgileX Cobot Magic), with exact ground truth. No files, devices or GPU needed.

The two-arm counterpart of :mod:`manisplat.episode.synthetic`, whose script (TCP keyframes, IK,
minimum-jerk moves, the box riding in the gripper) each arm runs in its own base frame; the right
arm starts 0.3 s later. Written through :class:`EpisodeWriterV2`, plus ``gt.npz``.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
import trimesh

from manisplat.episode.format import GT_FILE
from manisplat.episode.groundtruth import write_gt
from manisplat.episode.meta import ArmInfo, CameraInfo
from manisplat.episode.synthetic import BOX_SIZE, LINK_COLORS, SampleTrajectory, _box_poses, _posed, sample_trajectory
from manisplat.episode.writer_v2 import EpisodeWriterV2
from manisplat.robot import builtin_piper
from manisplat.robot.arms import ArmSet
from manisplat.render.painter import Camera, GroundPlane, look_at, render

CAMERA = "cam_high"
# where cam_high stands and looks (m, world): behind the bases, 29 deg down, both arms whole in view;
# steeper views lose the carried boxes behind their grippers
CAMERA_EYE, CAMERA_TARGET = (-0.65, 0.0, 0.60), (0.30, 0.0, 0.08)
BASE_Y = {"left": 0.30, "right": -0.30}  # arm -> its base's y (m, world); at x = z = 0, facing +x
BOX_START = {"left": (0.30, 0.12), "right": (0.30, -0.12)}  # arm -> its box's start (x, y) (m, world)
PLACE_SHIFT = 0.12  # each box is placed this far further from y = 0 (m)
DELAY = {"left": 0.0, "right": 0.3}  # arm -> when it starts to move (s)
BOX_COLORS = {"left": (200, 60, 50), "right": (40, 110, 215)}  # red, blue
TASK = "each arm picks its own box and places it 12 cm further to its side"
WRIST_CAMERAS = {"left": "cam_left_wrist", "right": "cam_right_wrist"}  # arm -> its wrist camera (on link6)
WRIST_FOV_DEG = 70.0  # the wrist cameras' vertical field of view
# A Cobot Magic wrist camera's calibration: the OpenCV camera in AgileX's URDF link6 frame (m): 7.5 cm
# off the flange axis along URDF y, 5 cm along it, tilted 32 deg back towards the fingers.
COBOT_MAGIC_T_LINK6_CAM = np.array([[-1.0, 0.0, 0.0, 0.0],
                                    [0.0, -0.847998304005, -0.529998940003, 0.075],
                                    [0.0, -0.529998940003, 0.847998304005, 0.05],
                                    [0.0, 0.0, 0.0, 1.0]])
# The built-in model's link6 is the DH flange, which AgileX's URDF link6 is rotated from by +90 deg
# about z (see manisplat.robot.piper; the URDF's fingers close along its x, the built-in's along y):
# the same mount there is Rz(+90 deg) @ the URDF value, 7.5 cm off the axis along -x, across the
# closing direction, so both fingertips show at the bottom of the image with the box between them.
# Taken as it stands, the URDF value would put the camera in line with one finger, which then hides
# the box at the grasp.
T_LINK6_WRIST_CAM = np.array([[0.0, -1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0],
                              [0.0, 0.0, 0.0, 1.0]]) @ COBOT_MAGIC_T_LINK6_CAM


def _T_world_base(arm: str) -> np.ndarray:
    T = np.eye(4)
    T[1, 3] = BASE_Y[arm]
    return T


def _arm_trajectory(arm: str, span: float) -> tuple[SampleTrajectory, tuple[float, float]]:
    """The arm's pick-and-place over ``span`` s (delayed by ``DELAY[arm]``) and its box's start
    (x, y) in its base frame (m)."""
    x, y = BOX_START[arm]
    pick = (x, y - BASE_Y[arm])
    place = (x, pick[1] + (PLACE_SHIFT if y > 0 else -PLACE_SHIFT))
    trajectory = sample_trajectory(span - DELAY[arm], "pick_place", pick, place)
    return replace(trajectory, times=trajectory.times + DELAY[arm]), pick


def _intrinsics(f: float, width: int, height: int) -> np.ndarray:
    """K (3, 3): focal length ``f`` (px), principal point at the image centre."""
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def write_two_arm_sample_episode(out: Path, *, duration: float = 4.0, fps: float = 10.0, width: int = 160,
                                 height: int = 120, wrist_cameras: bool = False) -> Path:
    """Write the two-arm sample episode to ``out`` (a new folder) and return its path.

    Args:
        duration: episode length (s): ``round(duration * fps)`` frames; the motion ends at the last.
        fps: frame rate (Hz); joint streams ``joints_<arm>.csv`` at 200 Hz.
        width, height: image size (px) of ``cam_high`` (rgb, z-depth at 0.1 mm, masks labelled
            ``robot/<arm>/<link>``, ``object/box_<arm>``, ``table``), and of the wrist cameras.
        wrist_cameras: also ``cam_left_wrist`` and ``cam_right_wrist`` (mounts ``<arm>/link6``,
            ``T_mount_cam`` :data:`T_LINK6_WRIST_CAM`, 70 deg vertical field of view), rendered
            like ``cam_high``.

    ``gt.npz`` holds per frame ``t`` (T,) s, ``T_world_tcp_<arm>`` and ``T_world_box_<arm>``
    (T, 4, 4) float64 for arms ``left`` and ``right``; with ``wrist_cameras`` also
    ``T_world_cam_<camera>`` (T, 4, 4) float64 for every camera (``cam_high``'s constant). At the
    default 4 s the joints accelerate up to about 3.7 times the PiPER's limit (5 rad/s^2): a sample
    to look at and reconstruct, not to replay on real arms at speed 1 (that takes about 8 s).
    """
    frames = round(duration * fps)
    if frames < 8:
        raise ValueError(f"the sample needs at least 8 frames, got {frames} ({duration} s at {fps} fps)")
    span = (frames - 1) / fps
    robot = builtin_piper()
    arms = ArmSet({arm: robot for arm in BASE_Y}, {arm: _T_world_base(arm) for arm in BASE_Y})
    scripted = {arm: _arm_trajectory(arm, span) for arm in BASE_Y}

    T_world_high = look_at(CAMERA_EYE, CAMERA_TARGET)
    cam_infos = [CameraInfo(CAMERA, width, height, _intrinsics(0.8 * width, width, height), mount="world",
                            T_mount_cam=T_world_high)]  # 64 deg horizontal field of view
    if wrist_cameras:
        K_wrist = _intrinsics(height / 2 / np.tan(np.radians(WRIST_FOV_DEG) / 2), width, height)
        cam_infos += [CameraInfo(WRIST_CAMERAS[arm], width, height, K_wrist, mount=f"{arm}/link6",
                                 T_mount_cam=T_LINK6_WRIST_CAM) for arm in BASE_Y]
    labels = {0: "background", **{i + 1: f"robot/{name}" for i, name in enumerate(arms.link_names)}}
    box_label = {arm: len(labels) + k for k, arm in enumerate(BASE_Y)}
    labels.update({value: f"object/box_{arm}" for arm, value in box_label.items()})
    table_label = len(labels)
    labels[table_label] = "table"
    ground = GroundPlane((-0.4, 1.2, -0.9, 0.9), 0.05, ((178, 150, 112), (150, 124, 90)), table_label)
    box_mesh = trimesh.creation.box(extents=(BOX_SIZE,) * 3)

    t_frames = np.arange(frames) / fps
    joints = {arm: np.column_stack(trajectory.at(t_frames)[:2])  # [T, 7] per arm: q1..q6 (rad), gripper (m)
              for arm, (trajectory, _) in scripted.items()}
    q = np.concatenate([joints[arm][:, :6] for arm in BASE_Y], 1)  # [T, 12]
    g = np.stack([joints[arm][:, 6] for arm in BASE_Y], 1)  # [T, 2]
    links = arms.forward_kinematics(torch.tensor(q), torch.tensor(g)).numpy()  # [T, 2 L, 4, 4] world
    T_tcp = arms.tcp_poses(torch.tensor(q)).numpy()  # [T, 2, 4, 4] world
    T_box = {arm: _T_world_base(arm) @ _box_poses(trajectory, robot, t_frames, pick)
             for arm, (trajectory, pick) in scripted.items()}
    T_cam = {CAMERA: np.repeat(T_world_high[None], frames, 0)}  # camera -> T_world_cam [T, 4, 4]
    T_cam.update({cam.name: links[:, arms.link_names.index(cam.mount)] @ cam.T_mount_cam for cam in cam_infos[1:]})

    arm_infos = [ArmInfo(name=arm, description="builtin:agilex_piper", T_world_base=_T_world_base(arm))
                 for arm in BASE_Y]
    out = Path(out)
    with EpisodeWriterV2(out, arm_infos, cam_infos, fps, source="simulation", depth_scale=1e-4, labels=labels,
                         objects=[f"box_{arm}" for arm in BASE_Y], actions=True,
                         extra_meta={"task": TASK, "generator": "manisplat.episode.synthetic_arms"}) as writer:
        t_joint = np.arange(0.0, span + 1e-9, 0.005)
        for arm, (trajectory, _) in scripted.items():
            qj, gj, _ = trajectory.at(t_joint)
            for tj, qi, gi in zip(t_joint, qj, gj):
                writer.add_joint_sample(arm, float(tj), qi, float(gi))
        action = {arm: np.column_stack(trajectory.at(np.minimum(t_frames + 1.0 / fps, span))[:2])
                  for arm, (trajectory, _) in scripted.items()}  # [T, 7] per arm: the next frame's
        for k in range(frames):
            meshes = [_posed(box_mesh, T_box[arm][k], BOX_COLORS[arm], box_label[arm]) for arm in BASE_Y]
            for i, name in enumerate(arms.link_names):
                for visual in arms.visuals.get(name, []):
                    meshes.append(_posed(visual.mesh, links[k, i], LINK_COLORS[name.split("/")[1]], i + 1))
            images = {cam.name: render(Camera(cam.K, width, height, T_cam[cam.name][k]), meshes, ground,
                                       exact_depth=True) for cam in cam_infos}  # camera -> rgb, depth, mask
            writer.add_frame(float(t_frames[k]), {arm: joints[arm][k] for arm in BASE_Y},
                             {c: rgb for c, (rgb, _, _) in images.items()},
                             depth={c: depth for c, (_, depth, _) in images.items()},
                             masks={c: mask for c, (_, _, mask) in images.items()},
                             actions={arm: action[arm][k] for arm in BASE_Y})
    gt = {"t": t_frames, **{f"T_world_tcp_{arm}": T_tcp[:, a] for a, arm in enumerate(BASE_Y)},
          **{f"T_world_box_{arm}": T_box[arm] for arm in BASE_Y}}
    if wrist_cameras:
        gt.update({f"T_world_cam_{name}": T for name, T in T_cam.items()})
    write_gt(out / GT_FILE, gt, compressed=False)
    return out


__all__ = ["write_two_arm_sample_episode"]
