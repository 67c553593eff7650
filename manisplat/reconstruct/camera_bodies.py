"""The bodies of cameras riding on the robot, found in the reference camera's depth.

A wrist camera (Cobot Magic's, a RealSense or an Orbbec on a PiPER's gripper) and its bracket are
part of the moving robot, yet no URDF has them: the robot's drawn masks leave them out, no link's
Gaussians cover them, and the static background cannot follow them. In the head camera of the
shared Cobot Magic sample the two camera bodies are 0.3 % of the pixels and 55 % of the held-out
squared error (rendered at 7-8 dB).

Each camera that rides on a link (the episode's metadata says which link and where on it) has its
body looked for around its optical centre: in the training frames, the reference camera's depth
pixels that may be a body (:func:`body_labels`: unclaimed where the robot's masks were drawn, a
robot label naming no link where they are the episode's) and that lie within
:data:`SEARCH_RADIUS_M` of the centre are taken into the mount link's frame. What moves with the link lands in the same voxels pose after
pose; the table, objects and the other arm do not. Voxels hit from at least :data:`MIN_POSES`
distinct link poses and :data:`MIN_POSE_SHARE` of them, the largest connected part, make the body:
their convex hull is added to the link's visuals, so that the link's Gaussians, the drawn robot
masks and everything else that reads the robot's geometry include it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from scipy import ndimage

from manisplat.geometry import pose_error
from manisplat.reconstruct.data import EpisodeData
from manisplat.reconstruct.masks import backproject_pixels
from manisplat.robot.arms import ArmSet
from manisplat.robot.model import RobotModel, Visual

log = logging.getLogger(__name__)

SEARCH_RADIUS_M = 0.06  # body points within this distance of the camera's optical centre
VOXEL_M = 0.004  # voxels of the link frame in which points of different poses meet, at least this wide ...
PIXELS_PER_VOXEL = 1.5  # ... and as wide as this many pixels of the reference camera at the body
MIN_POSES = 3  # a voxel of the body is seen from at least this many distinct link poses ...
MIN_POSE_SHARE = 0.25  # ... and from this share of the poses in which the centre was in view
DISTINCT_POSE_M = 0.02  # link poses this far apart (or DISTINCT_POSE_DEG) count as distinct
DISTINCT_POSE_DEG = 5.0
MIN_VOXELS = 8  # fewer voxels than this: no body found


@dataclass(frozen=True)
class CameraBody:
    """A riding camera's body: its camera, the link it is on, the hull in that link's frame (m)
    and what it was found from (voxels of ``voxel_m`` seen from ``poses`` distinct link poses)."""

    camera: str
    link: str
    mesh: trimesh.Trimesh
    voxels: int
    poses: int
    voxel_m: float

    @property
    def size_cm(self) -> tuple[float, float, float]:
        """The hull's bounding box in the link frame (cm)."""
        extent = self.mesh.bounds[1] - self.mesh.bounds[0]
        return tuple(round(float(100 * e), 1) for e in extent)


def body_labels(data: EpisodeData) -> set[int]:
    """The mask values a camera body may carry: where the masks were drawn from the robot's
    geometry, the unclaimed pixels (0); where they are the episode's, its robot labels that name
    no link of the robot (``robot/left/wrist_camera``): a part of the robot that no URDF has."""
    if data.mask_source.startswith("drawn robot"):
        return {0}
    return {value for value, name in data.labels.robot.items() if name not in data.robot.link_names}


def find_camera_bodies(data: EpisodeData, frames: list[int]) -> list[CameraBody]:
    """The bodies of ``data.riding_cameras`` seen by its (fixed) camera in ``frames``.

    Needs depth and masks; only pixels of :func:`body_labels` are looked at. A camera whose body
    is not found (out of view, hidden, no depth there) is logged and left out.
    """
    values = body_labels(data) if data.masks is not None else set()
    if data.depth is None or not values or data.riding:
        return []
    bodies = []
    for camera, (link, T_link_cam) in data.riding_cameras.items():
        body = _body_of(data, frames, camera, link, T_link_cam.double().numpy(), values)
        if body is None:
            log.info("camera %s rides on %s: no body of it found in %s's depth; not modelled", camera, link,
                     data.camera_name)
            continue
        log.info("camera %s rides on %s: its body, %s cm in the link's frame (%d voxels of %.0f mm seen from %d "
                 "poses), is modelled on that link", camera, link, " x ".join(map(str, body.size_cm)), body.voxels,
                 1e3 * body.voxel_m, body.poses)
        bodies.append(body)
    return bodies


def add_camera_bodies(robot: RobotModel | ArmSet, bodies: list[CameraBody]) -> None:
    """Give each body's link the body as one more visual: ``robot.visuals`` gets a new list for it
    (lists an arm set shares with its arms' models, or two arms with one model, are left alone)."""
    for body in bodies:
        robot.visuals[body.link] = [*robot.visuals.get(body.link, []),
                                    Visual(body.mesh, f"body of camera {body.camera}, from depth")]


def _body_of(data: EpisodeData, frames: list[int], camera: str, link: str, T_link_cam: np.ndarray,
             values: set[int]) -> CameraBody | None:
    index = list(data.robot.link_names).index(link)
    T_cam_base = data.viewmat.double().cpu().numpy()  # the fixed reference camera: base -> camera
    K = data.K_opencv.double().cpu().numpy()
    poses, seen, distances = [], [], []  # distinct link poses; (pose, points [N, 3] link frame); centre depth (m)
    for f in frames:
        T_base_link = data.link_poses[f, index].double().cpu().numpy()
        centre = T_base_link[:3, :3] @ T_link_cam[:3, 3] + T_base_link[:3, 3]
        depth = data.depth[f].cpu().numpy()
        found = _pixels_near(centre, T_cam_base, K, depth, data.masks[f].cpu().numpy(), values)
        if found is None:
            continue
        pose = _distinct_pose(T_base_link, poses)
        if pose is None:
            continue
        keep, distance = found
        points = backproject_pixels(depth, keep, data)  # [N, 3] base frame
        near = np.linalg.norm(points - centre, axis=1) < SEARCH_RADIUS_M
        T_link_base = np.linalg.inv(T_base_link)
        seen.append((pose, points[near] @ T_link_base[:3, :3].T + T_link_base[:3, 3]))
        distances.append(distance)
    if not poses:
        return None
    # a voxel at least as wide as 1.5 pixels where the body is, so that each pose's pixels reach it
    voxel = max(VOXEL_M, PIXELS_PER_VOXEL * float(np.median(distances) / K[0, 0]))
    voxel_poses: dict[tuple[int, int, int], set[int]] = {}
    for pose, local in seen:
        for key in {tuple(k) for k in np.floor(local / voxel).astype(np.int64)}:
            voxel_poses.setdefault(key, set()).add(pose)
    needed = max(MIN_POSES, MIN_POSE_SHARE * len(poses))
    kept = np.array([k for k, hit in voxel_poses.items() if len(hit) >= needed], dtype=np.int64).reshape(-1, 3)
    kept = _largest_part(kept)
    if len(kept) < MIN_VOXELS:
        return None
    corners = (kept[:, None, :] + _UNIT_CUBE[None]).reshape(-1, 3) * voxel  # each voxel's 8 corners
    hull = trimesh.PointCloud(corners).convex_hull
    return CameraBody(camera, link, hull, len(kept), len(poses), voxel)


_UNIT_CUBE = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.float64)


def _pixels_near(centre: np.ndarray, T_cam_base: np.ndarray, K: np.ndarray, depth: np.ndarray, labels: np.ndarray,
                 values: set[int]) -> tuple[np.ndarray, float] | None:
    """(the pixels [H, W] bool with depth and a label of ``values`` inside the search radius's
    image window around ``centre`` [3] (base frame), the centre's depth (m)); None when the centre
    is out of view or no such pixel has depth."""
    H, W = depth.shape
    c = T_cam_base[:3, :3] @ centre + T_cam_base[:3, 3]
    if c[2] <= SEARCH_RADIUS_M:
        return None
    u, v = K[0, 0] * c[0] / c[2] + K[0, 2], K[1, 1] * c[1] / c[2] + K[1, 2]
    reach = K[0, 0] * SEARCH_RADIUS_M / (c[2] - SEARCH_RADIUS_M)
    x0, x1 = int(max(0, np.floor(u - reach))), int(min(W, np.ceil(u + reach) + 1))
    y0, y1 = int(max(0, np.floor(v - reach))), int(min(H, np.ceil(v + reach) + 1))
    if x0 >= x1 or y0 >= y1:
        return None
    keep = np.zeros((H, W), dtype=bool)
    keep[y0:y1, x0:x1] = (depth[y0:y1, x0:x1] > 0) & np.isin(labels[y0:y1, x0:x1], list(values))
    return (keep, float(c[2])) if keep.any() else None


def _distinct_pose(T: np.ndarray, poses: list[np.ndarray]) -> int | None:
    """The index of ``T`` [4, 4] among ``poses`` (appended when it differs from every one by more
    than the distinct-pose thresholds); None for a pose already counted."""
    if poses:
        moved, angle = pose_error(torch.as_tensor(np.stack(poses)), torch.as_tensor(T))
        if bool(((moved < DISTINCT_POSE_M) & (angle < math.radians(DISTINCT_POSE_DEG))).any()):
            return None
    poses.append(T)
    return len(poses) - 1


def _largest_part(voxels: np.ndarray) -> np.ndarray:
    """The voxels [N, 3] of the largest 26-connected part."""
    if len(voxels) == 0:
        return voxels
    low = voxels.min(0)
    grid = np.zeros(tuple(voxels.max(0) - low + 1), dtype=bool)
    grid[tuple((voxels - low).T)] = True
    parts, count = ndimage.label(grid, structure=np.ones((3, 3, 3)))
    if count <= 1:
        return voxels
    sizes = np.bincount(parts[tuple((voxels - low).T)])
    return voxels[parts[tuple((voxels - low).T)] == int(np.argmax(sizes))]


__all__ = ["CameraBody", "add_camera_bodies", "body_labels", "find_camera_bodies"]
