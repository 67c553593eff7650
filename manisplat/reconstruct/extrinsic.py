"""The camera extrinsic and the camera/joint time offset checked and corrected against the robot
itself: the depth of the pixels the robot covers must lie on the robot's link surfaces, placed by
forward kinematics at the frame's time.

A hand calibration is typically off by a few tenths of a degree and a few millimetres
(../shared/reference: hand-eye accuracy), and a camera's timestamps by milliseconds; both move
every object pose the reconstruction finds in the base frame. The robot is a calibration target
whose pose is known in every frame: its measured surface in the camera frame, aligned to its
model surface over many frames and arm configurations, fixes ``T_base_cam`` and, where the arm
moves, the time offset (point-to-plane ICP, Gauss-Newton on se(3) and the offset, Huber
weights). Each depth point is matched along its pixel's ray: the ray is cast into its link's
meshes, placed by forward kinematics, and the point is compared with the plane of the face the ray
hits first. Stereo noise moves a point along its ray, so this match does not depend on the noise;
matching a noisy point to the nearest model point instead (the first version) takes points pushed
behind a thin part or an edge to another face and biases the fit: at the oak preset's noise from
1.1 m away that bias was 0.34 deg / 5.8 mm, larger than the calibration error it corrected. For
the same reason the rotation's lever arm in the Jacobian is the model point the ray hits, not the
noisy measured one (whose noise, multiplied by the residual's own, biased the fit by the noise's
variance: up to 0.4 mm of camera centre from 1.26 m). Each
depth point is trusted by its expected stereo error, which grows with the square of its depth
(weight ``(z_ref / z)^4``). The static background cannot help: it is seen
by one still camera, so any camera pose explains it.

The uncertainty adds in quadrature a bootstrap over frames (frames resampled with replacement,
the converged normal equations re-solved: the noise) and a jackknife over links (each link's
points left out in turn: a link's mesh or depth off in the same way in every frame): the 1-sigma
spread of the correction's rotation (deg), camera centre (mm) and time offset (ms).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

from manisplat.geometry import pose_error, se3_exp
from manisplat.reconstruct.data import EpisodeData, joints_at
from manisplat.reconstruct.static_surface import world_region
from manisplat.robot import link_meshes

log = logging.getLogger(__name__)

#: fewer measured robot points than this over all frames: the correction is not estimated
MIN_POINTS = 2_000
#: a correction this uncertain (1-sigma, deg and mm) is not applied: its 2-sigma reaches the size of a
#: hand calibration's error, so the robot's depth cannot tell which camera pose is better
MAX_SIGMA_ROTATION_DEG, MAX_SIGMA_TRANSLATION_MM = 0.1, 1.5
#: a correction larger than this is not applied (the calibration is wrong, or the robot model is)
MAX_ROTATION_DEG, MAX_TRANSLATION_MM, MAX_TIME_OFFSET_S = 3.0, 30.0, 0.2
#: a time offset is applied when it is this large and three times its spread (s)
MIN_TIME_OFFSET_S = 0.002
#: the time offset is estimated only where the arm moves enough to tell it from the camera pose
#: (condition number of the unit-diagonal normal equations with the offset)
MAX_TIME_CONDITION = 1e8
#: normal equations worse conditioned than this (unit diagonal) leave a direction of the pose free
MAX_CONDITION = 1e10
#: the residuals before and after are compared within this distance of the model (m): the first
#: iteration's gate (later ones shrink with the residuals, and would flatter the refined pose)
COMPARE_GATE = 0.02
#: a fit that leaves more than this residual RMS (mm) does not describe the depth (stereo noise of
#: an OAK is a few mm at 1.5 m): the model or the depth is wrong, and the correction means nothing
MAX_RESIDUAL_MM = 5.0
#: prefix of the static surface's parts among the links a riding camera is matched to
SCENE = "scene/"
_VELOCITY_STEP_S = 0.01  # central difference of the link poses for the surface velocity
REPLACE_AFTER_S = 0.5e-3  # the meshes are placed anew when the offset moved this far (s)


@dataclass
class ExtrinsicCorrection:
    """What the robot's depth says about ``T_base_cam`` and the time offset.

    Attributes:
        T_before, T_after: [4, 4] float64 camera-to-base, as recorded and as refined.
        rotation_deg, translation_mm: the correction: rotation angle of ``T_before^-1 T_after`` and
            the camera centre's displacement in the base frame.
        sigma_rotation_deg, sigma_translation_mm: 1-sigma bootstrap spread of those (over frames).
        time_offset_s, sigma_time_offset_s: frame f shows the robot at joint time
            ``t[f] + offset`` beyond the offset already used (``EpisodeData.time_offset_s``); None
            when the arm did not move enough to tell.
        rms_before_mm, rms_after_mm: robust RMS point-to-plane residual before and after, both
            within :data:`COMPARE_GATE` of the model.
        points, frames: how many robot depth points from how many frames were used.
        applied: False when the extrinsic correction was not trusted (``reason`` says why).
        time_applied: whether the time offset is large and certain enough to re-pair the joints.
        T_fitted: [4, 4] the fit's camera-to-base, applied or not (``T_after`` when applied).
        sigma_parts: the spreads the sigmas combine (in quadrature), each (deg, mm, s): "frames",
            the bootstrap over frames (noise); "links", the jackknife over links (a link's mesh or
            depth off in the same way in every frame).
        spreads: the samples behind ``sigma_parts`` (:class:`Spread`), for what is computed from
            the fitted pose (a base, :mod:`manisplat.reconstruct.rig_check`).
    """

    T_before: np.ndarray
    T_after: np.ndarray
    rotation_deg: float
    translation_mm: float
    sigma_rotation_deg: float
    sigma_translation_mm: float
    time_offset_s: float | None
    sigma_time_offset_s: float | None
    rms_before_mm: float
    rms_after_mm: float
    points: int
    frames: int
    applied: bool = True
    reason: str = ""
    time_applied: bool = False
    T_fitted: np.ndarray | None = None
    sigma_parts: dict[str, tuple[float, float, float]] | None = None
    spreads: dict[str, "Spread"] | None = None

    def to_dict(self) -> dict:
        return {"rotation_deg": self.rotation_deg, "translation_mm": self.translation_mm,
                "sigma_rotation_deg": self.sigma_rotation_deg, "sigma_translation_mm": self.sigma_translation_mm,
                "time_offset_ms": None if self.time_offset_s is None else 1e3 * self.time_offset_s,
                "sigma_time_offset_ms": None if self.sigma_time_offset_s is None else 1e3 * self.sigma_time_offset_s,
                "time_applied": self.time_applied,
                "rms_before_mm": self.rms_before_mm, "rms_after_mm": self.rms_after_mm,
                "points": self.points, "frames": self.frames, "applied": self.applied, "reason": self.reason,
                "T_correction": (np.linalg.inv(self.T_before) @ self.T_after).tolist(),
                "sigma_parts": None if self.sigma_parts is None else {  # null where a part could not be told
                    name: {"rotation_deg": _finite(deg), "translation_mm": _finite(mm), "time_offset_ms": _finite(1e3 * sec)}
                    for name, (deg, mm, sec) in self.sigma_parts.items()},
                "method": "robot depth on the URDF link meshes along each pixel's ray (point-to-plane ICP); "
                          "sigma: bootstrap over frames and jackknife over links, in quadrature"}


def _finite(x: float) -> float | None:
    return None if math.isnan(x) else x


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(rotation angle of ``T_a^-1 T_b`` in degrees, distance between their origins in mm)."""
    distance, angle = pose_error(torch.as_tensor(T_a), torch.as_tensor(T_b))
    return math.degrees(float(angle)), 1000 * float(distance)


class _Group:
    """Measured robot points of one frame (camera frame) and the link meshes they belong to,
    placed at the frame's time (``now``) and ``_VELOCITY_STEP_S`` before and after it.
    ``carrier`` [4, 4]: the pose the fitted transform is relative to (the identity for a fixed
    camera, the mount link's pose at the frame for a camera riding on it)."""

    def __init__(self, frame: int, link: str | None, points_cam: np.ndarray, w_depth: np.ndarray,
                 meshes: list[trimesh.Trimesh], now: np.ndarray, before: np.ndarray, after: np.ndarray,
                 carrier: np.ndarray) -> None:
        self.frame, self.link, self.p, self.w_depth = frame, link, points_cam, w_depth
        self.meshes, self.now, self.before, self.after, self.carrier = meshes, now, before, after, carrier
        self.rays = self.p / np.linalg.norm(self.p, axis=1, keepdims=True)

    def _first_hits(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Where each point's pixel ray from the camera at ``T`` first meets the meshes: whether it
        does [N], the hit [N, 3] and the face normal [N, 3] (base frame), the hit's velocity [N, 3]
        (m/s) as its link moves."""
        R, centre = T[:3, :3], T[:3, 3]
        directions = self.rays @ R.T
        n = len(self.p)
        nearest = np.full(n, np.inf)
        hit, normal, velocity = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
        for mesh, P, P_before, P_after in zip(self.meshes, self.now, self.before, self.after):
            R_link, t_link = P[:3, :3], P[:3, 3]
            origins = np.broadcast_to((centre - t_link) @ R_link, (n, 3))
            local, ray, face = mesh.ray.intersects_location(origins, directions @ R_link, multiple_hits=False)
            placed = local @ R_link.T + t_link
            distance = np.linalg.norm(placed - centre, axis=1)
            closer = distance < nearest[ray]
            ray, local, face, placed = ray[closer], local[closer], face[closer], placed[closer]
            nearest[ray], hit[ray] = distance[closer], placed
            normal[ray] = mesh.face_normals[face] @ R_link.T
            velocity[ray] = (local @ (P_after[:3, :3] - P_before[:3, :3]).T + P_after[:3, 3] - P_before[:3, 3]) / (
                2 * _VELOCITY_STEP_S)
        return np.isfinite(nearest), hit, normal, velocity

    def residuals(self, T: np.ndarray, gate: float, shift: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Point-to-plane residuals [N] (m) at camera pose ``carrier T`` with the meshes moved
        ``shift`` s along their velocity, whether each ray hit its link within ``gate`` of the plane
        [N], and their Jacobian [N, 7] for ``T Exp(e)`` and a further time shift ``s``:
        (e, s) = (v, omega, s), e in the camera frame, s in seconds."""
        T = self.carrier @ T
        hits, hit, n, velocity = self._first_hits(T)
        R, t = T[:3, :3], T[:3, 3]
        r = np.einsum("ij,ij->i", n, self.p @ R.T + t - hit - shift * velocity)
        ok = hits & (np.abs(r) <= gate)
        # d pb / d e = R [I | -[p]x]; n^T R [I | -[p]x] = [(R^T n)^T | (p x R^T n)^T]; d r / d s = -n.v.
        # The lever p is taken at the model point the ray hits (camera frame), not at the measured
        # point: the measured one carries the depth noise that r carries, and their product would bias
        # the fit by the noise's variance (errors in variables); where r is 0 the two are the same.
        nc = n @ R
        lever = np.where(hits[:, None], (hit + shift * velocity - t) @ R, self.p)
        J = np.concatenate([nc, np.cross(lever, nc), -np.einsum("ij,ij->i", n, velocity)[:, None]], 1)
        return np.where(ok, r, 0.0), ok, J


def _normal_equations(groups: list[_Group], T: np.ndarray, gate: float, huber: float,
                      shift: float = 0.0) -> dict[tuple[int, str | None], tuple]:
    """(frame, link) -> (H [7, 7], g [7], inlier residuals [M] in m) of the Huber- and
    depth-weighted point-to-plane cost at ``T`` (models moved ``shift`` s) over that group."""
    out = {}
    for grp in groups:
        r, ok, J = grp.residuals(T, gate, shift)
        a = np.abs(r)
        w = np.where(a <= huber, 1.0, huber / np.maximum(a, 1e-12)) * grp.w_depth * ok
        Jw = J * w[:, None]
        out[grp.frame, grp.link] = (Jw.T @ J, Jw.T @ r, r[ok])
    return out


def _summed(systems: dict, by: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The systems' (H, g) summed over every key sharing element ``by`` of the (frame, link) key."""
    out: dict = {}
    for key, (H, g, _) in systems.items():
        H0, g0 = out.get(key[by], (0.0, 0.0))
        out[key[by]] = (H0 + H, g0 + g)
    return list(out.values())


def _link_meshes(data: EpisodeData) -> dict[str, trimesh.Trimesh]:
    """link -> its visual meshes as one mesh (link frame), ray-cast with Embree."""
    out = link_meshes(data.robot.visuals)
    for mesh in out.values():
        mesh.ray = RayMeshIntersector(mesh)  # Embree (embreex), not trimesh's slow pure-Python fallback
    return out


def _robot_points(data: EpisodeData, frame: int, region: np.ndarray, erode_px: int, max_points: int,
                  rng: np.random.Generator) -> np.ndarray:
    """[N, 3] camera-frame points of the frame's pixels in ``region`` [H, W] bool with valid depth,
    ``erode_px`` away from the region's edge (stereo depth is unreliable there), at most ``max_points``."""
    region = region.astype(np.uint8)
    if erode_px:
        region = cv2.erode(region, np.ones((2 * erode_px + 1, 2 * erode_px + 1), np.uint8))
    z = data.depth[frame].numpy().astype(np.float64)
    rows, cols = np.nonzero((region > 0) & (z > 0))
    if len(rows) > max_points:
        keep = rng.choice(len(rows), max_points, replace=False)
        rows, cols = rows[keep], cols[keep]
    K = data.K_opencv.numpy()
    zz = z[rows, cols]
    return np.stack([(cols - K[0, 2]) / K[0, 0] * zz, (rows - K[1, 2]) / K[1, 1] * zz, zz], axis=1)


@dataclass
class _Measured:
    """One frame's robot depth points matched to one link (``link`` None: to all links)."""

    frame: int
    link: str | None
    points: np.ndarray
    w_depth: np.ndarray


def _mask_regions(data: EpisodeData, meshes: dict, modelled: set[str]) -> dict[str | None, list[int]]:
    """Link (of ``meshes``) -> the robot mask labels showing it. A label naming a link of the
    robot (``modelled``) outside ``meshes`` (another arm's, when one arm is fitted) or a part
    without a mesh (a wrist camera's housing) is left out where other labels name links; only
    where no label names a link (one label for the whole arm) are they matched to every link
    together (key None)."""
    named = {value: link for value, link in data.labels.robot.items() if link in modelled}
    if not named:
        return {None: list(data.labels.robot)}
    by_link: dict[str | None, list[int]] = {}
    for value, link in named.items():
        if link in meshes:
            by_link.setdefault(link, []).append(value)
    return by_link


def _link_poses(data: EpisodeData, frame: int) -> np.ndarray:
    """[L, 4, 4] float64 every link's pose at the frame's joints (order ``robot.link_names``)."""
    return data.robot.forward_kinematics(data.q[frame].double(), data.gripper[frame].double()).numpy()


def _camera_pose(data: EpisodeData, poses: np.ndarray, T: np.ndarray) -> np.ndarray:
    """[4, 4] the camera's pose for ``T`` (its pose relative to the carrier, as fitted) with the
    links at ``poses`` (:func:`_link_poses`): on its mount link for a riding camera."""
    return poses[list(data.robot.link_names).index(data.mount)] @ T if data.riding else T


def _drawn_regions(data: EpisodeData, poses: np.ndarray, meshes: dict[str, trimesh.Trimesh], T: np.ndarray,
                   stride: int = 2) -> dict[str, np.ndarray]:
    """Link -> [H, W] bool: the pixels (every ``stride``-th row and column) whose ray from the
    camera at ``T`` (world frame) meets that link first, the links at ``poses`` (the frame's
    :func:`_link_poses`): the robot's pixels of a camera without masks."""
    names = list(data.robot.link_names)
    W, H = data.size
    rows, cols = np.mgrid[0:H:stride, 0:W:stride]
    K = data.K_opencv.numpy()
    rays = np.stack([(cols.ravel() - K[0, 2]) / K[0, 0], (rows.ravel() - K[1, 2]) / K[1, 1], np.ones(cols.size)], 1)
    directions = rays / np.linalg.norm(rays, axis=1, keepdims=True) @ T[:3, :3].T
    nearest, owner = np.full(len(rays), np.inf), np.full(len(rays), -1)
    links = list(meshes)
    for k, link in enumerate(links):
        P = poses[names.index(link)]
        origins = np.broadcast_to((T[:3, 3] - P[:3, 3]) @ P[:3, :3], directions.shape)
        local, ray, _ = meshes[link].ray.intersects_location(origins, directions @ P[:3, :3], multiple_hits=False)
        distance = np.linalg.norm(local @ P[:3, :3].T + P[:3, 3] - T[:3, 3], axis=1)
        closer = distance < nearest[ray]
        nearest[ray[closer]], owner[ray[closer]] = distance[closer], k
    out = {}
    for k, link in enumerate(links):
        region = np.zeros((H, W), bool)
        region[rows.ravel()[owner == k], cols.ravel()[owner == k]] = True
        if region.any():  # the grid's gaps closed: one region per link, eroded like a mask
            out[link] = cv2.dilate(region.astype(np.uint8), np.ones((stride, stride), np.uint8),
                                   anchor=(0, 0)).astype(bool)
    return out


def _measurements(data: EpisodeData, frames: list[int], meshes: dict, modelled: set[str], T0: np.ndarray,
                  erode_px: int, points_per_frame: int, rng: np.random.Generator,
                  surface: trimesh.Trimesh | None = None) -> list[_Measured]:
    """Each mask label naming a link is matched to that link's meshes (:func:`_mask_regions`);
    without masks, the pixels where the links are drawn at the recorded camera ``T0``
    (:func:`_drawn_regions`) are, each to its link. With a static ``surface`` (a riding camera),
    the pixels no link covers are matched to it, as many points again as the robot's, in the
    quadrant of the world they show at ``T0`` (:data:`SCENE`)."""
    robot_links = {name: mesh for name, mesh in meshes.items() if not name.startswith(SCENE)}
    by_link = _mask_regions(data, robot_links, modelled) if data.masks is not None else None
    # each label value (each drawn link) its share of the frame's points
    share = points_per_frame / max(len(robot_links) if by_link is None else sum(map(len, by_link.values())), 1)
    out = []
    for f in frames:
        if by_link is None or surface is not None:  # the camera where the recorded extrinsic puts it
            poses = _link_poses(data, f)
            T_cam = _camera_pose(data, poses, T0)
        if by_link is None:
            regions = {link: (region, 1) for link, region in _drawn_regions(data, poses, robot_links, T_cam).items()}
        else:
            masks = data.masks[f].numpy()
            regions = {link: (np.isin(masks, values), len(values)) for link, values in by_link.items()}
        for link, (region, labels) in regions.items():
            p = _robot_points(data, f, region, erode_px, max(int(share * labels), 1), rng)
            if len(p) >= 20:
                out.append(_Measured(f, link, p, p[:, 2] ** -4.0))  # 1 / sigma_z^2 up to a constant
        if surface is not None:
            out += _scene_measurements(data, f, surface, T_cam, regions, erode_px, points_per_frame, rng)
    if out:
        z_ref = np.median(np.concatenate([m.points[:, 2] for m in out]))
        for m in out:  # relative to the median depth (dimensionless)
            m.w_depth = m.w_depth * z_ref ** 4
    return out


def _scene_measurements(data: EpisodeData, frame: int, surface: trimesh.Trimesh, T_cam: np.ndarray, robot: dict,
                        erode_px: int, count: int, rng: np.random.Generator) -> list[_Measured]:
    """A riding camera's points of the static ``surface`` in ``frame``: its pixels with depth
    ``erode_px`` away from every robot region (``robot``: link -> (region, labels)), at most
    ``count``, split by the quadrant of the world they show with the camera at ``T_cam`` (world
    frame; one group each)."""
    covered = np.zeros(data.depth.shape[1:], np.uint8)
    for region, _ in robot.values():
        covered |= region.astype(np.uint8)
    if data.masks is not None and data.labels.objects:  # the objects move: not the static surface
        covered |= np.isin(data.masks[frame].numpy(), list(data.labels.objects)).astype(np.uint8)
    if erode_px:
        covered = cv2.dilate(covered, np.ones((2 * erode_px + 1, 2 * erode_px + 1), np.uint8))
    p = _robot_points(data, frame, covered == 0, erode_px, count, rng)
    world = p @ T_cam[:3, :3].T + T_cam[:3, 3]
    part = world_region(world, surface.bounds.mean(0))
    return [_Measured(frame, f"{SCENE}{k}", p[part == k], p[part == k, 2] ** -4.0)
            for k in range(4) if (part == k).sum() >= 20]


def _groups(data: EpisodeData, measured: list[_Measured], meshes: dict[str, trimesh.Trimesh],
            offset: float) -> list[_Group]:
    """The measurements with their links' meshes placed at joint time ``t[f] + offset`` beyond
    the data's own offset (and ``_VELOCITY_STEP_S`` before and after, for their velocity)."""
    names = list(data.robot.link_names)
    frames = sorted({m.frame for m in measured})
    t = data.t.cpu().numpy()[frames] + data.time_offset_s + offset  # joint time of what the frame shows
    h = _VELOCITY_STEP_S
    q, gripper = joints_at(data, np.concatenate([t, t - h, t + h]))
    poses = data.robot.forward_kinematics(torch.as_tensor(q), torch.as_tensor(gripper)).double().numpy()
    now, before, after = np.split(poses, 3)
    row = {f: k for k, f in enumerate(frames)}
    mount = names.index(data.mount) if data.riding else None
    groups = []
    for m in measured:
        links = [m.link] if m.link is not None else [n for n in meshes if not n.startswith(SCENE)]
        k = row[m.frame]
        # a static surface stands in the world: its pose is the identity whenever it is seen
        placed = [np.stack([np.eye(4)] * 3) if n.startswith(SCENE) else
                  np.stack([now[k, names.index(n)], before[k, names.index(n)], after[k, names.index(n)]])
                  for n in links]
        carrier = now[k, mount] if mount is not None else np.eye(4)
        groups.append(_Group(m.frame, m.link, m.points, m.w_depth, [meshes[n] for n in links],
                             *(np.stack([p[j] for p in placed]) for j in range(3)), carrier))
    return groups


def refine_extrinsic(data: EpisodeData, frames: list[int], *, max_frames: int = 40, points_per_frame: int = 1500,
                     iterations: int = 20, bootstrap: int = 200, erode_px: int = 2, time_offset: bool = True,
                     depth_weighting: bool = True, links: list[str] | None = None,
                     surface: trimesh.Trimesh | None = None, seed: int = 0) -> ExtrinsicCorrection | None:
    """Align the robot's measured depth with its model over ``frames`` (training frames).

    A fixed camera's pose in the robot's (world) frame is fitted; a camera riding on a link
    (``data.riding``, a wrist camera) its ``T_mount_cam``, the link placed by forward kinematics
    in every frame: it sees its own gripper's fingers and whatever other links come into view.
    Without masks, a riding camera's robot pixels are where the links are drawn at its recorded
    extrinsic.

    ``time_offset`` also estimates the camera/joint time offset where the arm moves enough to
    tell it (:data:`MAX_TIME_CONDITION`); it is applied (``time_applied``) when at least
    :data:`MIN_TIME_OFFSET_S` and three times its bootstrap spread (not for a riding camera,
    whose own pose moves with the joints: its recorded latency stands). ``depth_weighting``
    False weighs every depth point the same (the ablation in
    ``benchmarks/bench_reconstruct_degraded_ablation.py``). ``links``: fit to these links only
    (one arm of several, :mod:`manisplat.reconstruct.rig_check`); default every link with a mesh.
    ``surface``: for a riding camera, the static scene in the world frame
    (:func:`~manisplat.reconstruct.static_surface.static_surface`, measured by a checked fixed
    camera): what the camera sees besides the robot is matched to it too; its quadrants count as
    links in the jackknife.

    Returns None when the episode cannot say (no depth, no robot masks, fewer than
    :data:`MIN_POINTS` robot points, a degenerate geometry); otherwise the correction, with
    ``applied`` False (and the reason) when the fit leaves a residual above
    :data:`MAX_RESIDUAL_MM` (the depth or the model is wrong: the painter's one depth per triangle
    leaves several millimetres and the fit proposes degrees), is larger than
    :data:`MAX_ROTATION_DEG` / :data:`MAX_TRANSLATION_MM`, or does not lower the residual (the
    recorded camera already fits).
    """
    if data.depth is None or (not data.riding and (data.masks is None or not data.labels.robot)):
        log.info("camera extrinsic: not checked (needs depth and robot masks)")
        return None
    rng = np.random.default_rng(seed)
    chosen = list(frames)[:: max(1, len(frames) // max_frames)][:max_frames]
    modelled = _link_meshes(data)
    unknown = sorted(set(links or ()) - set(modelled))
    if unknown:
        raise ValueError(f"links {unknown}: no such link with a mesh ({', '.join(modelled)})")
    meshes = {name: mesh for name, mesh in modelled.items() if links is None or name in links}
    T0 = data.T_mount_cam.double().numpy() if data.riding else np.linalg.inv(data.viewmat.double().numpy())
    time_offset = time_offset and not data.riding
    if surface is not None:
        if not data.riding:
            raise ValueError("a static surface checks a riding camera; a fixed one sees it from one place only")
        meshes.update({f"{SCENE}{k}": surface for k in range(4)})
    measured = _measurements(data, chosen, meshes, set(modelled), T0, erode_px, points_per_frame, rng, surface)
    if not depth_weighting:
        for m in measured:
            m.w_depth = np.ones_like(m.w_depth)
    total = sum(len(m.points) for m in measured)
    if total < MIN_POINTS:
        log.warning("camera extrinsic: not checked (only %d robot depth points)", total)
        return None
    T, offset = T0.copy(), 0.0
    groups, placed_at = _groups(data, measured, meshes, offset), offset
    gate = COMPARE_GATE
    r = np.concatenate([s[2] for s in _normal_equations(groups, T, gate, gate).values()])
    rms_before = _robust_rms(r)
    solve_time = time_offset
    for _ in range(iterations):
        sigma = max(1.4826 * float(np.median(np.abs(r))), 2e-4)  # robust depth residual scale (m)
        gate, huber = max(5 * sigma, 0.003), 1.5 * sigma
        systems = _normal_equations(groups, T, gate, huber, offset - placed_at)
        H, g = sum(s[0] for s in systems.values()), sum(s[1] for s in systems.values())
        if solve_time and _condition(H) > MAX_TIME_CONDITION:
            solve_time = False  # the arm hardly moves: the offset cannot be told apart from the camera
        k = 7 if solve_time else 6
        if _condition(H[:k, :k]) > MAX_CONDITION:
            log.warning("camera extrinsic: not checked (the robot's points do not constrain the camera; "
                        "condition number %.1e)", _condition(H[:k, :k]))
            return None
        step = -np.linalg.solve(H[:k, :k], g[:k])
        T = T @ se3_exp(torch.as_tensor(step[:6])).numpy()
        if solve_time:
            offset += float(step[6])
            if abs(offset - placed_at) > REPLACE_AFTER_S:  # the meshes at the new time (within it: linear)
                groups, placed_at = _groups(data, measured, meshes, offset), offset
        r = np.concatenate([s[2] for s in _normal_equations(groups, T, gate, huber, offset - placed_at).values()])
        if np.linalg.norm(step[:6]) < 1e-8 and (not solve_time or abs(step[6]) < 1e-6):
            break
    systems = _normal_equations(groups, T, gate, huber, offset - placed_at)
    k = 7 if solve_time else 6
    spreads = {"frames": _bootstrap(_summed(systems, 0), k, bootstrap, rng), "links": _jackknife(_summed(systems, 1), k)}
    by_frames, by_links = _spread(T, spreads["frames"]), _spread(T, spreads["links"])
    # one label for the whole arm leaves no links to leave out: then the frames' spread alone (sigma_parts says so)
    sig_rot, sig_trans, sig_time = (math.hypot(a, 0.0 if math.isnan(b) else b) for a, b in zip(by_frames, by_links))
    rot, trans = pose_difference(T0, T)
    # after compared with before on the same terms: the first iteration's gate
    rms_after = _robust_rms(np.concatenate([s[2] for s in _normal_equations(
        groups, T, COMPARE_GATE, COMPARE_GATE, offset - placed_at).values()]))
    result = ExtrinsicCorrection(T0, T, rot, trans, sig_rot, sig_trans, offset if solve_time else None,
                                 sig_time if solve_time else None, 1000 * rms_before, 1000 * rms_after,
                                 total, len(chosen), T_fitted=T.copy(),
                                 sigma_parts={"frames": by_frames, "links": by_links},
                                 spreads={name: v for name, v in spreads.items() if v is not None})
    if solve_time:
        result.time_applied = (abs(offset) >= max(MIN_TIME_OFFSET_S, 3 * sig_time) and abs(offset) <= MAX_TIME_OFFSET_S)
    refused = refusal(rot, trans, sig_rot, sig_trans, rms_before, rms_after)
    if refused is not None:
        result.reason, keeps_time, warn = refused
        result.applied, result.time_applied = False, result.time_applied and keeps_time
        result.T_after = T0.copy()
        if warn:
            log.warning("camera extrinsic: %s", result.reason)
    if solve_time:
        verdict = ("applied" if result.time_applied else "not applied: " + (
            f"beyond {MAX_TIME_OFFSET_S} s" if abs(offset) > MAX_TIME_OFFSET_S else
            "too small to be sure" if abs(offset) < max(MIN_TIME_OFFSET_S, 3 * sig_time) else "the extrinsic was not"))
        timing = f"; camera/joint time offset {1e3 * offset:+.1f} +- {1e3 * sig_time:.1f} ms ({verdict})"
    else:
        timing = ""
    if result.applied or rms_after < rms_before:  # a correction, applied or refused above with a warning
        log.info("camera extrinsic: correction %.3f +- %.3f deg, %.2f +- %.2f mm from %d robot depth points in %d "
                 "frames (residual RMS %.2f -> %.2f mm)%s%s", rot, sig_rot, trans, sig_trans, total, len(chosen),
                 result.rms_before_mm, result.rms_after_mm, "" if result.applied else f"; NOT applied: {result.reason}",
                 timing)
    else:
        log.info("camera extrinsic: kept: %s; %d robot depth points in %d frames%s", result.reason, total,
                 len(chosen), timing)
    return result


def refusal(rot: float, trans: float, sig_rot: float, sig_trans: float, rms_before: float,
            rms_after: float, subject: str = "the camera") -> tuple[str, bool, bool] | None:
    """Why a fitted correction of ``subject`` (deg, mm, its 1-sigma; residual RMS before and after
    in m) is not applied, whether a certain time offset still is, and whether that deserves a
    warning; None when it is applied."""
    if 1000 * rms_after > MAX_RESIDUAL_MM:
        return (f"the robot's depth does not fit its model (residual RMS {1000 * rms_before:.2f} -> "
                f"{1000 * rms_after:.2f} mm, at most {MAX_RESIDUAL_MM} mm expected): the extrinsic cannot be checked "
                "and the episode's calibration is kept; check the depth scale and the robot description", False, True)
    if rot > MAX_ROTATION_DEG or trans > MAX_TRANSLATION_MM:
        return (f"the correction ({rot:.2f} deg, {trans:.1f} mm) is larger than {MAX_ROTATION_DEG} deg / "
                f"{MAX_TRANSLATION_MM} mm: recalibrate (manisplat-calibrate) or check the robot description", False, True)
    if rms_after >= rms_before:
        return (f"the robot's depth fits {subject} as recorded (residual RMS {1000 * rms_before:.2f} mm; the fit's "
                f"{rot:.3f} deg, {trans:.2f} mm does not lower it)", False, False)
    if sig_rot > MAX_SIGMA_ROTATION_DEG or sig_trans > MAX_SIGMA_TRANSLATION_MM:
        return (f"the robot's depth cannot pin {subject} down: the correction's 1-sigma is {sig_rot:.3f} deg, "
                f"{sig_trans:.2f} mm, more than {MAX_SIGMA_ROTATION_DEG} deg / {MAX_SIGMA_TRANSLATION_MM} mm (as "
                "uncertain as a hand calibration); the episode's calibration is kept: more of the arm in view, nearer "
                "the camera, or a calibration (manisplat-calibrate) decides it", False, True)
    if rot < 2 * sig_rot and trans < 2 * sig_trans:  # a certain time offset still re-pairs the joints
        return (f"the correction ({rot:.3f} deg, {trans:.2f} mm) is within its own 2-sigma ({2 * sig_rot:.3f} deg, "
                f"{2 * sig_trans:.2f} mm): {subject} as recorded agrees with the robot's depth", True, False)
    return None


def _condition(H: np.ndarray) -> float:
    """Condition number of ``H`` scaled to unit diagonal (the parameters' units do not count)."""
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    return float(np.linalg.cond(H / d[:, None] / d[None, :]))


def _robust_rms(r: np.ndarray) -> float:
    """RMS of the residuals within 3 robust sigmas (m)."""
    if not len(r):
        return float("nan")
    sigma = 1.4826 * np.median(np.abs(r))
    inl = r[np.abs(r) <= 3 * sigma] if sigma > 0 else r
    return float(np.sqrt(np.mean(inl ** 2)))


@dataclass
class Spread:
    """Samples of the fit's error: pose steps [n, k] (se(3) twist in the camera frame, then the time
    offset) whose root mean square times ``sqrt(scale)`` is the 1-sigma spread."""

    steps: np.ndarray
    scale: float


def _bootstrap(systems: list[tuple[np.ndarray, np.ndarray]], k: int, n: int, rng: np.random.Generator) -> Spread:
    """The one-step solutions of the first ``k`` parameters with the frames' normal equations
    ``systems`` resampled with replacement (a resample that leaves a direction unconstrained, as
    the fit itself would refuse, is left out)."""
    Hs = np.stack([H[:k, :k] for H, _ in systems])
    gs = np.stack([g[:k] for _, g in systems])
    steps = []
    for _ in range(n):
        pick = rng.integers(0, len(systems), len(systems))
        H = Hs[pick].sum(0)
        if _condition(H) > MAX_CONDITION:
            continue
        steps.append(-np.linalg.solve(H, gs[pick].sum(0)))
    return Spread(np.array(steps).reshape(-1, k), 1.0)


def _jackknife(systems: list[tuple[np.ndarray, np.ndarray]], k: int) -> Spread | None:
    """The one-step solutions with each link's normal equations ``systems`` left out in turn,
    centred: what one link's systematic error (its mesh against the real link, its depth) moves
    the solution by. None with fewer than 3 links."""
    if len(systems) < 3:
        return None
    H, g = sum(h for h, _ in systems), sum(v for _, v in systems)
    steps = []
    for H_link, g_link in systems:
        try:
            steps.append(-np.linalg.solve((H - H_link)[:k, :k], (g - g_link)[:k]))
        except np.linalg.LinAlgError:
            return None
    steps = np.array(steps)
    return Spread(steps - steps.mean(0), len(steps) - 1.0)


def _spread(T: np.ndarray, spread: Spread | None) -> tuple[float, float, float]:
    """The 1-sigma size (deg, mm, s) of ``spread``'s pose steps applied to ``T``: the spread of a
    3-vector's length about 0 (the time's NaN without one, all NaN without steps)."""
    if spread is None or not len(spread.steps):
        return math.nan, math.nan, math.nan
    steps, scale = spread.steps, spread.scale
    angles, shifts = zip(*(pose_difference(T, T @ se3_exp(torch.as_tensor(step[:6])).numpy()) for step in steps))
    times = steps[:, 6] if steps.shape[1] == 7 else [math.nan]
    rms = lambda x: float(np.sqrt(scale * np.mean(np.square(x))))  # noqa: E731
    return rms(angles), rms(shifts), rms(times)


__all__ = ["ExtrinsicCorrection", "MAX_ROTATION_DEG", "MAX_TIME_OFFSET_S", "MAX_TRANSLATION_MM", "SCENE", "Spread",
           "pose_difference", "refine_extrinsic"]
