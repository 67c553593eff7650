"""A built-in two-arm sample episode (format version 2): two built-in PiPERs 0.6 m apart, facing
+x, seen by one world-fixed camera from behind and above (and, on request, by a wrist camera on
each arm's link6, as on an AgileX Cobot Magic), with exact ground truth. No files, devices or GPU
needed. Two tasks:

* ``pick_place``: each arm picks its own 4 cm box and places it 12 cm further towards its own
  side; the right arm starts 0.3 s later;
* ``handover``: the left arm picks one box and holds it up between the arms, the right arm closes
  on its lower half, the left lets go, and the right arm places it on its own side.

The two-arm counterpart of :mod:`manisplat.episode.synthetic`, whose script (TCP keyframes, IK,
minimum-jerk moves, a box riding rigidly in the gripper that holds it) each arm runs in its own
base frame (the painter draws; nothing stops two grippers overlapping). Written through
:class:`EpisodeWriterV2`, plus ``gt.npz``.
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
from manisplat.episode.synthetic import (BOX_SIZE, GRASP, LINK_COLORS, OPEN, Keyframe, SampleTrajectory, _box_poses,
                                        _posed, sample_trajectory, solve_keyframes)
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
TASKS = {"pick_place": "each arm picks its own box and places it 12 cm further to its side",
         "handover": "the left arm picks the box and hands it to the right arm, which places it on its side"}
HANDED_BOX_START = (0.30, 0.12)  # the handover's box: where it starts (x, y) (m, world)
HANDOVER_SPOT = (0.30, 0.0, 0.14)  # where the box is handed over (m, world)
HANDED_BOX_PLACE = (0.30, -0.16)  # where the right arm places it (x, y) (m, world)
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
# Each wrist camera's body, which no URDF has: a box of these extents (m, camera frame) behind the
# lens, dark grey, labelled robot/<arm>/wrist_camera (as the shared simulator labels it).
WRIST_CAMERA_BODY_EXTENTS = (0.04, 0.03, 0.025)
WRIST_CAMERA_BODY_COLOR = (45, 45, 50)


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


def _in_base(arm: str, x: float, y: float, z: float) -> tuple[float, float, float]:
    """A world point (m) in the arm's base frame."""
    return x, y - BASE_Y[arm], z


def _handover_script(span: float) -> dict[str, list[Keyframe]]:
    """Keyframes of both arms over ``span`` s: the left picks the box 1 cm above its centre and
    holds it at :data:`HANDOVER_SPOT`; the right closes 1 cm below its centre; the left opens and
    leaves; the right pulls it away and places it at :data:`HANDED_BOX_PLACE`."""
    home = {arm: (0.25, y, 0.24) for arm, y in BASE_Y.items()}  # each arm's rest, 25 cm before its base
    bx, by = HANDED_BOX_START
    hx, hy, hz = HANDOVER_SPOT
    px, py = HANDED_BOX_PLACE
    left = [(0.00, home["left"], OPEN, "approach"), (0.10, (bx, by, 0.14), OPEN, "approach"),
            (0.17, (bx, by, BOX_SIZE / 2 + 0.01), OPEN, "descend"), (0.21, (bx, by, BOX_SIZE / 2 + 0.01), GRASP, "grasp"),
            (0.28, (bx, by, 0.14), GRASP, "lift"), (0.40, (hx, hy, hz + 0.01), GRASP, "to_handover"),
            (0.56, (hx, hy, hz + 0.01), GRASP, "hold"), (0.60, (hx, hy, hz + 0.01), OPEN, "release"),
            (0.68, (hx, hy, hz + 0.09), OPEN, "retreat"), (0.80, home["left"], OPEN, "return"),
            (1.00, home["left"], OPEN, "rest")]
    right = [(0.00, home["right"], OPEN, "rest"), (0.30, home["right"], OPEN, "wait"), (0.42, (hx, hy, hz + 0.06), OPEN, "approach"),
             (0.50, (hx, hy, hz - 0.01), OPEN, "descend"), (0.54, (hx, hy, hz - 0.01), GRASP, "grasp"),
             (0.62, (hx, hy, hz - 0.01), GRASP, "wait_release"), (0.70, (hx, hy - 0.06, hz + 0.02), GRASP, "pull"),
             (0.82, (px, py, 0.12), GRASP, "transfer"), (0.88, (px, py, BOX_SIZE / 2 - 0.01), GRASP, "lower"),
             (0.93, (px, py, BOX_SIZE / 2 - 0.01), OPEN, "release"), (1.00, (px, py, 0.18), OPEN, "retreat")]
    return {arm: [Keyframe(f * span, _in_base(arm, *position), width, phase) for f, position, width, phase in keys]
            for arm, keys in (("left", left), ("right", right))}


def _handed_box(trajectories: dict[str, SampleTrajectory], robot, t: np.ndarray) -> np.ndarray:
    """T_world_box [N, 4, 4] of the handover at times ``t`` (s): it rests until the left's grasp
    keyframe, rides in the left gripper until the right's grasp keyframe has closed, in the right
    one until its "lower" keyframe, then rests there."""

    def tcp(arm: str, times) -> np.ndarray:
        q = trajectories[arm].at(np.atleast_1d(np.asarray(times, np.float64)))[0]
        return _T_world_base(arm) @ robot.tcp_pose(torch.tensor(q)).numpy()

    def keyframe(arm: str, phase: str) -> float:
        return float(trajectories[arm].times[trajectories[arm].phases.index(phase)])

    picked, taken, placed = keyframe("left", "grasp"), keyframe("right", "grasp"), keyframe("right", "lower")
    rest = np.eye(4)
    rest[:3, 3] = (*HANDED_BOX_START, BOX_SIZE / 2)
    in_left = np.linalg.inv(tcp("left", picked)[0]) @ rest
    in_right = np.linalg.inv(tcp("right", taken)[0]) @ tcp("left", taken)[0] @ in_left
    out = np.repeat(rest[None], len(t), axis=0)
    for (begin, end), arm, held in (((picked, taken), "left", in_left), ((taken, placed), "right", in_right)):
        inside = (t > begin) & (t <= end)
        if inside.any():
            out[inside] = tcp(arm, t[inside]) @ held
    out[t > placed] = tcp("right", placed)[0] @ in_right
    return out


def _intrinsics(f: float, width: int, height: int) -> np.ndarray:
    """K (3, 3): focal length ``f`` (px), principal point at the image centre."""
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def write_two_arm_sample_episode(out: Path, *, duration: float = 4.0, fps: float = 10.0, width: int = 160,
                                 height: int = 120, wrist_cameras: bool = False, task: str = "pick_place") -> Path:
    """Write the two-arm sample episode to ``out`` (a new folder) and return its path.

    Args:
        duration: episode length (s): ``round(duration * fps)`` frames; the motion ends at the last.
        fps: frame rate (Hz); joint streams ``joints_<arm>.csv`` at 200 Hz.
        width, height: image size (px) of ``cam_high`` (rgb, z-depth at 0.1 mm, masks labelled
            ``robot/<arm>/<link>``, ``object/<box>``, ``table``), and of the wrist cameras.
        wrist_cameras: also ``cam_left_wrist`` and ``cam_right_wrist`` (mounts ``<arm>/link6``,
            ``T_mount_cam`` :data:`T_LINK6_WRIST_CAM`, 70 deg vertical field of view), rendered
            like ``cam_high``, and their bodies (:func:`wrist_camera_body`) in every image.
        task: "pick_place" (boxes ``box_left`` and ``box_right``) or "handover" (one ``box``).

    ``gt.npz`` holds per frame ``t`` (T,) s, ``T_world_tcp_<arm>`` for arms ``left`` and ``right``
    and ``T_world_<box>`` (T, 4, 4) float64 for every box; with ``wrist_cameras`` also
    ``T_world_cam_<camera>`` (T, 4, 4) float64 for every camera (``cam_high``'s constant). At the
    default 4 s the pick-and-place's joints accelerate up to about 3.7 times the PiPER's limit
    (5 rad/s^2): a sample to look at and reconstruct, not to replay on real arms at speed 1 (that
    takes about 8 s); the handover needs 10 s to stay within the limits.
    """
    if task not in TASKS:
        raise ValueError(f"task must be one of {sorted(TASKS)}, got {task!r}")
    frames = round(duration * fps)
    if frames < 8:
        raise ValueError(f"the sample needs at least 8 frames, got {frames} ({duration} s at {fps} fps)")
    span = (frames - 1) / fps
    robot = builtin_piper()
    arms = ArmSet({arm: robot for arm in BASE_Y}, {arm: _T_world_base(arm) for arm in BASE_Y})
    t_frames = np.arange(frames) / fps
    if task == "handover":
        scripted = {arm: solve_keyframes(keys) for arm, keys in _handover_script(span).items()}
        T_box = {"box": _handed_box(scripted, robot, t_frames)}  # box name -> T_world_box [T, 4, 4]
        box_colors = {"box": BOX_COLORS["left"]}
    else:
        picks = {arm: _arm_trajectory(arm, span) for arm in BASE_Y}
        scripted = {arm: trajectory for arm, (trajectory, _) in picks.items()}
        T_box = {f"box_{arm}": _T_world_base(arm) @ _box_poses(trajectory, robot, t_frames, pick)
                 for arm, (trajectory, pick) in picks.items()}
        box_colors = {f"box_{arm}": BOX_COLORS[arm] for arm in BASE_Y}

    T_world_high = look_at(CAMERA_EYE, CAMERA_TARGET)
    cam_infos = [CameraInfo(CAMERA, width, height, _intrinsics(0.8 * width, width, height), mount="world",
                            T_mount_cam=T_world_high)]  # 64 deg horizontal field of view
    if wrist_cameras:
        K_wrist = _intrinsics(height / 2 / np.tan(np.radians(WRIST_FOV_DEG) / 2), width, height)
        cam_infos += [CameraInfo(WRIST_CAMERAS[arm], width, height, K_wrist, mount=f"{arm}/link6",
                                 T_mount_cam=T_LINK6_WRIST_CAM) for arm in BASE_Y]
    labels = {0: "background", **{i + 1: f"robot/{name}" for i, name in enumerate(arms.link_names)}}
    box_label = {name: len(labels) + k for k, name in enumerate(T_box)}
    labels.update({value: f"object/{name}" for name, value in box_label.items()})
    table_label = len(labels)
    labels[table_label] = "table"
    body_label = {}  # wrist camera -> the label of its body: robot/<arm>/wrist_camera, a part no URDF has
    for cam in cam_infos[1:]:
        body_label[cam.name] = len(labels)
        labels[len(labels)] = f"robot/{cam.mount.split('/')[0]}/wrist_camera"
    ground = GroundPlane((-0.4, 1.2, -0.9, 0.9), 0.05, ((178, 150, 112), (150, 124, 90)), table_label)
    box_mesh = trimesh.creation.box(extents=(BOX_SIZE,) * 3)
    camera_body = wrist_camera_body()

    joints = {arm: np.column_stack(trajectory.at(t_frames)[:2])  # [T, 7] per arm: q1..q6 (rad), gripper (m)
              for arm, trajectory in scripted.items()}
    q = np.concatenate([joints[arm][:, :6] for arm in BASE_Y], 1)  # [T, 12]
    g = np.stack([joints[arm][:, 6] for arm in BASE_Y], 1)  # [T, 2]
    links = arms.forward_kinematics(torch.tensor(q), torch.tensor(g)).numpy()  # [T, 2 L, 4, 4] world
    T_tcp = arms.tcp_poses(torch.tensor(q)).numpy()  # [T, 2, 4, 4] world
    T_cam = {CAMERA: np.repeat(T_world_high[None], frames, 0)}  # camera -> T_world_cam [T, 4, 4]
    T_cam.update({cam.name: links[:, arms.link_names.index(cam.mount)] @ cam.T_mount_cam for cam in cam_infos[1:]})

    arm_infos = [ArmInfo(name=arm, description="builtin:agilex_piper", T_world_base=_T_world_base(arm))
                 for arm in BASE_Y]
    out = Path(out)
    with EpisodeWriterV2(out, arm_infos, cam_infos, fps, source="simulation", depth_scale=1e-4, labels=labels,
                         objects=list(T_box), actions=True,
                         extra_meta={"task": TASKS[task], "generator": "manisplat.episode.synthetic_arms"}) as writer:
        t_joint = np.arange(0.0, span + 1e-9, 0.005)
        for arm, trajectory in scripted.items():
            qj, gj, _ = trajectory.at(t_joint)
            for tj, qi, gi in zip(t_joint, qj, gj):
                writer.add_joint_sample(arm, float(tj), qi, float(gi))
        action = {arm: np.column_stack(trajectory.at(np.minimum(t_frames + 1.0 / fps, span))[:2])
                  for arm, trajectory in scripted.items()}  # [T, 7] per arm: the next frame's
        for k in range(frames):
            meshes = [_posed(box_mesh, T_box[name][k], box_colors[name], box_label[name]) for name in T_box]
            for i, name in enumerate(arms.link_names):
                for visual in arms.visuals.get(name, []):
                    meshes.append(_posed(visual.mesh, links[k, i], LINK_COLORS[name.split("/")[1]], i + 1))
            for cam in cam_infos[1:]:
                meshes.append(_posed(camera_body, T_cam[cam.name][k], WRIST_CAMERA_BODY_COLOR,
                                     body_label[cam.name]))
            images = {cam.name: render(Camera(cam.K, width, height, T_cam[cam.name][k]), meshes, ground,
                                       exact_depth=True) for cam in cam_infos}  # camera -> rgb, depth, mask
            writer.add_frame(float(t_frames[k]), {arm: joints[arm][k] for arm in BASE_Y},
                             {c: rgb for c, (rgb, _, _) in images.items()},
                             depth={c: depth for c, (_, depth, _) in images.items()},
                             masks={c: mask for c, (_, _, mask) in images.items()},
                             actions={arm: action[arm][k] for arm in BASE_Y})
    gt = {"t": t_frames, **{f"T_world_tcp_{arm}": T_tcp[:, a] for a, arm in enumerate(BASE_Y)},
          **{f"T_world_{name}": poses for name, poses in T_box.items()}}
    if wrist_cameras:
        gt.update({f"T_world_cam_{name}": T for name, T in T_cam.items()})
    write_gt(out / GT_FILE, gt, compressed=False)
    return out


def wrist_camera_body() -> trimesh.Trimesh:
    """A wrist camera's body in its camera's frame (m): :data:`WRIST_CAMERA_BODY_EXTENTS`, its
    front face 1 mm behind the lens."""
    body = trimesh.creation.box(extents=WRIST_CAMERA_BODY_EXTENTS)
    body.apply_translation((0.0, 0.0, -WRIST_CAMERA_BODY_EXTENTS[2] / 2 - 0.001))
    return body


__all__ = ["write_two_arm_sample_episode", "wrist_camera_body"]
