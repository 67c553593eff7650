"""Object pose by tracking keypoints: OpenCV pyramidal Lucas-Kanade inside the object mask with a
forward-backward check, lifted to 3D with depth, then RANSAC + Kabsch to canonical points.

Each tracked point carries canonical coordinates (object frame) fixed when it was first seen, so
the pose of every frame is solved against the same model, not chained frame to frame; after each
solve the points are re-anchored at their model projections, so single tracks do not drift. When too
few points survive (occlusion by the fingers, the object turning), new points are seeded in the
mask and given canonical coordinates through the current pose.

With a ``prior`` (what the gripper implies: resting, or moving with the gripper), a frame takes
the tracked pose only once tracking has confidently disagreed with the prior for several frames,
and then for as long as it stays confident; otherwise the prior (corrected where tracking left
off) stands. A grasped object is mostly hidden by the fingers, which is exactly where an
unguided tracker drifts. Confidence in the tracks is not enough: an override must also earn its
place against the prior in the frame's own depth (:class:`DepthEvidence`: the object's visible
surface must sit closer to the object's model at the tracked pose than at the prior's). On the
shared pick-and-place, tracks dragged by the closing fingers confidently turned a still box by
3.2 deg; its depth still fitted the prior to 0.3 mm and the tracked pose to 1.1 mm.

Without depth (or without a mask) in a frame, the object's model seen at the predicted pose
stands in: new points are lifted onto the model's rendered depth, and poses are solved from the
2D tracks by RANSAC PnP; the mask is the model's silhouette, grown by a few pixels. Such poses
never override a prior: PnP on a small, roughly modelled object is ambiguous in depth and
rotation (on the shared pick-and-place without depth, letting it override moved the pseudo
poses 6 cm / 17 deg off; the gripper prior alone is 0.25 cm / 0.8 deg).

Limits: frame-to-frame LK under-reads in-plane rotation (by about 7 % of the turn in the tests,
at 0.7 and 2 deg per frame); the gripper prior carries the pose wherever it holds.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Protocol

import cv2
import numpy as np
import torch

from manisplat.align.surface_fit import SurfaceModel
from manisplat.geometry import GeometryError, kabsch_ransac, rotation_error

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrackerSettings:
    """Tracking parameters.

    Attributes:
        max_points: features kept per frame.
        fb_threshold: forward-backward LK disagreement above which a track is dropped (px).
        ransac_threshold: 3D residual for a RANSAC inlier (m).
        min_inliers: fewer inliers than this and the frame keeps the previous pose (flagged).
        window: LK window (px); levels: pyramid levels.
        grid_step: spacing (px) of the grid of points seeded over the mask besides corner
            features: small objects have too few corners (a 4 cm box at 0.7 m has about 9).
        confident_inliers, confident_rms: a tracked pose is trusted over the prior only with at
            least this many inliers and at most this RMS residual (m)...
        disagree_translation, disagree_rotation_deg: ...and when it differs from the prior by
            more than this (m, deg)...
        persistence: ...in this many consecutive frames (a push or a slip persists; a transient
            misfit as the fingers start to hide the object does not)...
        evidence_ratio, evidence_margin: ...and when the frame's depth fits the tracked pose
            better than the prior's: its :class:`DepthEvidence` misfit below ``evidence_ratio``
            times the prior's and at least ``evidence_margin`` (m) smaller (``depth_evidence``
            False skips this check: confidence alone, the ablation in benchmarks/bench_pseudo_gt.py).
        evidence_model: the depth check's model adds the object's model points (when the tracker
            is given them) to the surface seen in the tracked stretch's first frame.
    """

    max_points: int = 300
    fb_threshold: float = 0.7
    ransac_threshold: float = 0.004
    min_inliers: int = 5
    window: int = 11
    levels: int = 3
    grid_step: int = 2
    confident_inliers: int = 20
    confident_rms: float = 0.002
    persistence: int = 3
    disagree_translation: float = 0.005
    disagree_rotation_deg: float = 3.0
    evidence_ratio: float = 0.7
    evidence_margin: float = 0.0003
    depth_evidence: bool = True
    evidence_model: bool = True


@dataclass
class Track:
    """Poses T_base_obj [n, 4, 4] (float64) of frames ``start .. start + n - 1``; ``solved`` [n]: the
    tracker found a pose; ``from_tracking`` [n]: that pose was used (not the prior or the
    previous pose); ``inliers`` [n]."""

    start: int
    poses: np.ndarray
    solved: np.ndarray
    from_tracking: np.ndarray
    inliers: np.ndarray


def _lift(points: np.ndarray, depth: np.ndarray, K: np.ndarray, T_base_cam: np.ndarray,
          max_step: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Base-frame 3D [M, 3] of pixel points [M, 2] (x, y; OpenCV K) and which were valid.

    Depth is interpolated bilinearly; a point whose four neighbours are not all valid or span
    more than ``max_step`` metres (an occlusion edge) is invalid.
    """
    H, W = depth.shape
    x0 = np.clip(np.floor(points[:, 0]).astype(int), 0, W - 2)
    y0 = np.clip(np.floor(points[:, 1]).astype(int), 0, H - 2)
    fx = np.clip(points[:, 0] - x0, 0, 1)
    fy = np.clip(points[:, 1] - y0, 0, 1)
    quad = np.stack([depth[y0, x0], depth[y0, x0 + 1], depth[y0 + 1, x0], depth[y0 + 1, x0 + 1]], -1).astype(np.float64)
    z = (quad[:, 0] * (1 - fx) * (1 - fy) + quad[:, 1] * fx * (1 - fy) + quad[:, 2] * (1 - fx) * fy
         + quad[:, 3] * fx * fy)
    ok = (quad > 0).all(-1) & (quad.max(-1) - quad.min(-1) < max_step)
    cam = np.stack([(points[:, 0] - K[0, 2]) / K[0, 0] * z, (points[:, 1] - K[1, 2]) / K[1, 1] * z, z], -1)
    return cam @ T_base_cam[:3, :3].T + T_base_cam[:3, 3], ok


def _detect(gray: np.ndarray, mask: np.ndarray, existing: np.ndarray, settings: TrackerSettings) -> np.ndarray:
    """New points [M, 2] inside the (eroded) ``mask``, away from ``existing`` ones: corner features
    plus a grid every ``grid_step`` pixels."""
    m = cv2.erode(mask.astype(np.uint8) * 255, np.ones((3, 3), np.uint8))
    for x, y in existing.astype(int):
        cv2.circle(m, (int(x), int(y)), 1, 0, -1)
    found = cv2.goodFeaturesToTrack(gray, settings.max_points, 0.005, 2, mask=m, blockSize=3)
    corners = np.zeros((0, 2), np.float32) if found is None else found.reshape(-1, 2)
    ys, xs = np.nonzero(m[:: settings.grid_step, :: settings.grid_step])
    grid = np.stack([xs, ys], -1).astype(np.float32) * settings.grid_step
    points = np.concatenate([corners, grid])
    return points[: settings.max_points]


class DepthEvidence:
    """How well a frame's depth fits the object's model at a pose: the misfit is the mean distance
    (m, each point's capped at ``cap``) from the object's visible surface points (mask pixels with
    valid depth, lifted to the base frame) to the nearest model point, with the model placed at
    the pose. The model is the surface seen in the first frame (object frame, from its pose), so
    occluded parts (fingers) simply contribute no points, and the object's model points where
    given. A surface the model lacks costs every pose and pulls the misfit's minimum towards
    poses that cover it with what the model has: a can carried with the fingers over it, its
    model the surface seen then, fitted a pose 7 mm high and 5 deg tilted better than its true
    one once the opened fingers showed the rest (5.1 vs 5.5 mm; with its frame-0 model points
    added, 3.3 vs 1.6 mm).

    Args:
        mask, depth: the first frame's object mask [H, W] bool and z-depth [H, W] (m, 0 invalid).
        T_base_obj: the object's pose in that frame [4, 4].
        model_points: more of the object's surface [M, 3] (object frame), e.g. from another view.
        max_points: points kept (evenly strided) per frame and in the model.
    """

    def __init__(self, mask: np.ndarray, depth: np.ndarray, K: np.ndarray, T_base_cam: np.ndarray,
                 T_base_obj: np.ndarray, *, model_points: np.ndarray | None = None, cap: float = 0.01,
                 max_points: int = 1500) -> None:
        self._K, self._T_base_cam, self._max = K, T_base_cam, max_points
        model = _to_object(self.surface(mask, depth), T_base_obj)
        if model_points is not None:
            model = np.concatenate([model, np.asarray(model_points, dtype=np.float64).reshape(-1, 3)])
        self._model = SurfaceModel(model, cap) if len(model) >= 10 else None

    def surface(self, mask: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Base-frame points [M, 3] of the mask's pixels with valid depth (M <= max_points)."""
        return visible_surface(mask, depth, self._K, self._T_base_cam, self._max)

    def misfit(self, surface: np.ndarray, T_base_obj: np.ndarray) -> float:
        """Mean capped distance (m) of ``surface`` [M, 3] to the model at ``T_base_obj``; inf
        without enough points to judge."""
        if self._model is None or len(surface) < 10:
            return float("inf")
        return self._model.misfit([surface], [T_base_obj])


def visible_surface(mask: np.ndarray, depth: np.ndarray, K: np.ndarray, T_base_cam: np.ndarray,
                    max_points: int = 1500) -> np.ndarray:
    """Base-frame points [M, 3] (M <= ``max_points``, evenly strided) of the ``mask`` [H, W] pixels
    with valid ``depth`` [H, W] (m, 0 invalid; not across an occlusion edge: :func:`_lift`)."""
    ys, xs = np.nonzero(mask)
    step = max(1, len(xs) // max_points)
    pixels = np.stack([xs[::step], ys[::step]], -1).astype(np.float64)
    X, ok = _lift(pixels, depth, K, T_base_cam)
    return X[ok]


def _to_object(points: np.ndarray, T_base_obj: np.ndarray) -> np.ndarray:
    """Base-frame points [M, 3] in the object frame."""
    inv = np.linalg.inv(T_base_obj)
    return points @ inv[:3, :3].T + inv[:3, 3]


def track_object(
    gray: Callable[[int], np.ndarray],
    mask: Callable[[int], np.ndarray],
    depth: Callable[[int], np.ndarray],
    K: np.ndarray,
    T_base_cam: np.ndarray,
    frames: range,
    T_start: np.ndarray,
    settings: TrackerSettings = TrackerSettings(),
    prior: np.ndarray | None = None,
    model: ObjectView | None = None,
    observe: frozenset[int] = frozenset(),
    model_points: np.ndarray | None = None,
) -> Track:
    """Poses of an object over ``frames``, starting from its pose ``T_start`` in the first one.

    Args:
        gray, mask, depth: frame index -> uint8 image [H, W], bool object mask [H, W] (the visible
            object), z-depth [H, W] in metres (0 invalid). ``mask`` and ``depth`` may return None
            for a frame without them: then ``model`` stands in (see :class:`ObjectView`).
        K: OpenCV intrinsics [3, 3]; T_base_cam: camera-to-base [4, 4].
        prior: [n, 4, 4] poses the frames take unless tracking confidently disagrees (module doc).
        model: the object's model seen at a pose, for frames without mask or depth.
        observe: frames held out from training (and scored): their images, masks and depth are
            not read; each takes the pose the frames before it imply (the prior with the
            correction tracking had made by then, or the last pose without a prior), and the
            tracks continue from the frame before, as if they were not there.
        model_points: the object's surface points [M, 3] (object frame) for the depth check's
            model (:class:`DepthEvidence`; ``settings.evidence_model``).
    """
    first = frames[0]
    poses = [np.asarray(T_start, dtype=np.float64)]
    solved, used, inliers = [True], [False], [0]
    correction = np.eye(4)  # object-frame correction applied to the prior after a tracking override
    streak = 0  # consecutive frames where tracking confidently disagreed with the prior
    following = False  # tracking has overridden the prior and is still confident
    view = _Inputs(mask, depth, model)
    pts = _detect(gray(first), view.mask(first, poses[0]), np.zeros((0, 2)), settings)
    X, ok = _lift(pts, view.depth(first, poses[0]), K, T_base_cam)
    pts, canon = pts[ok], _to_object(X[ok], poses[0])
    most_points = len(pts)  # the most trackable points the object showed in any frame
    evidence = None
    if prior is not None and depth(first) is not None:
        evidence = DepthEvidence(view.mask(first, poses[0]), depth(first), K, T_base_cam, poses[0],
                                 model_points=model_points if settings.evidence_model else None)
    prev = gray(first)
    lk = dict(winSize=(settings.window, settings.window), maxLevel=settings.levels,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    last_pose = poses[0]  # the pose of the last frame not held out
    for f in frames[1:]:
        k = len(poses)
        if f in observe:  # held out: an evaluation must not see what it scores
            poses.append(prior[k] @ correction if prior is not None else last_pose)
            solved.append(False)
            used.append(False)
            inliers.append(0)
            continue
        predicted = prior[k] @ correction if prior is not None else last_pose
        cur, m = gray(f), view.mask(f, predicted)
        measured = depth(f)
        pose = last_pose
        if len(pts):
            fwd, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, pts.reshape(-1, 1, 2).astype(np.float32), None, **lk)
            back, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, fwd, None, **lk)
            fwd, back = fwd.reshape(-1, 2), back.reshape(-1, 2)
            good = (st1[:, 0] == 1) & (st2[:, 0] == 1) & (np.linalg.norm(back - pts, axis=1) < settings.fb_threshold)
            H, W = m.shape
            xi = np.clip(np.round(fwd[:, 0]).astype(int), 0, W - 1)
            yi = np.clip(np.round(fwd[:, 1]).astype(int), 0, H - 1)
            good &= m[yi, xi]
            X = None
            if measured is not None:
                X, ok = _lift(fwd, measured, K, T_base_cam)
                good &= ok
                X = X[good]
            pts, canon = fwd[good], canon[good]
        n_in, tracked, rms, keep = 0, None, np.inf, None
        if len(pts) >= settings.min_inliers:
            if measured is not None:
                try:
                    fit = kabsch_ransac(torch.from_numpy(canon), torch.from_numpy(X), settings.ransac_threshold,
                                        min_inliers=settings.min_inliers)
                    tracked, n_in, rms, keep = fit.T.numpy(), int(fit.inliers.sum()), float(fit.rms), fit.inliers.numpy()
                except GeometryError:
                    pass
            else:
                tracked, n_in, rms, keep = _solve_pnp(canon, pts, predicted, K, T_base_cam, settings)
            if tracked is not None:
                pts, canon = pts[keep], canon[keep]
                # re-anchor each point on the rigid model: single tracks cannot drift away from it
                pts = _project(canon, tracked, K, T_base_cam).astype(np.float32)
        use_track = tracked is not None
        if prior is not None:
            pose = prior[k] @ correction
            # only measured depth can prove the prior wrong: PnP on the object's model is ambiguous
            # in depth and rotation for a small object, and agrees with its own wrong guesses
            confident = (use_track and measured is not None and n_in >= settings.confident_inliers
                         and rms <= settings.confident_rms)
            earned = False
            if confident and (following or _disagree(tracked, pose, settings)):
                earned = _earns_override(evidence, evidence.surface(m, measured) if evidence else None,
                                         tracked, pose, settings, following)
            streak = streak + 1 if earned and not following else 0
            # once the prior is proven wrong (a push, a slip), follow tracking while it stays
            # confident and the depth does not favour the prior
            following = earned and (following or streak >= settings.persistence)
            use_track = following
            if use_track:  # where tracking stops, the prior continues from here
                correction = np.linalg.inv(prior[k]) @ tracked
        if use_track:
            pose = tracked
        poses.append(pose)
        solved.append(tracked is not None)
        used.append(use_track)
        inliers.append(n_in)
        last_pose = pose
        if len(pts) < settings.max_points // 2 and m.any():
            new = _detect(cur, m, pts, settings)
            Xn, okn = _lift(new, measured if measured is not None else view.depth(f, pose), K, T_base_cam)
            pts = np.concatenate([pts, new[okn]])
            canon = np.concatenate([canon, _to_object(Xn[okn], pose)])
            most_points = max(most_points, len(pts))
        prev = cur
    track = Track(first, np.stack(poses), np.array(solved), np.array(used), np.array(inliers))
    if most_points < settings.min_inliers:  # nothing to track: say so, not "solved 0"
        log.info("tracking frames %d-%d: not tracked: the object shows at most %d trackable points (%d needed; "
                 "small in the image or plain); %s", first, frames[-1], most_points, settings.min_inliers,
                 "the prior stands" if prior is not None else "its first pose is held")
    else:
        log.info("tracking frames %d-%d: solved %d of %d, %d took the tracked pose", first, frames[-1],
                 int(track.solved[1:].sum()), len(frames) - 1, int(track.from_tracking.sum()))
    return track


class ObjectView(Protocol):
    """The object's model seen at a pose: ``view(T_base_obj [4, 4])`` -> (z-depth [H, W] in metres,
    0 off the object; visible mask [H, W] bool). Stands in for a frame's depth (points are lifted
    onto the model, and poses solved by PnP) or its mask (the model's silhouette, grown)."""

    def __call__(self, T_base_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


class _Inputs:
    """A frame's object mask and depth, or the model's where the frame has none."""

    def __init__(self, mask, depth, model: ObjectView | None, grow: int = 5) -> None:
        self._mask, self._depth, self._model = mask, depth, model
        self._kernel = np.ones((2 * grow + 1, 2 * grow + 1), np.uint8)

    def _need_model(self, what: str, f: int) -> ObjectView:
        if self._model is None:
            raise ValueError(f"tracking: frame {f} has no {what} and no object model stands in")
        return self._model

    def mask(self, f: int, pose: np.ndarray) -> np.ndarray:
        m = self._mask(f)
        if m is None:
            m = cv2.dilate(self._need_model("mask", f)(pose)[1].astype(np.uint8), self._kernel).astype(bool)
        return m

    def depth(self, f: int, pose: np.ndarray) -> np.ndarray:
        d = self._depth(f)
        return self._need_model("depth", f)(pose)[0] if d is None else d


def _solve_pnp(canon: np.ndarray, pts: np.ndarray, guess: np.ndarray, K: np.ndarray, T_base_cam: np.ndarray,
               settings: TrackerSettings, reprojection_px: float = 2.0):
    """Pose from 2D tracks of canonical points (no depth): RANSAC PnP (OpenCV) from ``guess``.

    Returns (T_base_obj or None, inlier count, RMS residual converted to metres at the object's
    distance, inliers [M] bool or None)."""
    T_cam_obj = np.linalg.inv(T_base_cam) @ guess
    rvec, _ = cv2.Rodrigues(T_cam_obj[:3, :3])
    tvec = T_cam_obj[:3, 3].copy()
    ok, rvec, tvec, idx = cv2.solvePnPRansac(
        canon.astype(np.float64), pts.astype(np.float64), K, None, rvec, tvec.reshape(3, 1), useExtrinsicGuess=True,
        reprojectionError=reprojection_px, iterationsCount=100, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or idx is None or len(idx) < settings.min_inliers:
        return None, 0, np.inf, None
    keep = np.zeros(len(pts), dtype=bool)
    keep[idx[:, 0]] = True
    R, _ = cv2.Rodrigues(rvec)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, tvec[:, 0]
    tracked = T_base_cam @ T
    residual = np.linalg.norm(_project(canon[keep], tracked, K, T_base_cam) - pts[keep], axis=1)
    rms_m = float(np.sqrt(np.mean(residual ** 2)) * tvec[2, 0] / K[0, 0])
    return tracked, int(keep.sum()), rms_m, keep


def _project(canon: np.ndarray, T_base_obj: np.ndarray, K: np.ndarray, T_base_cam: np.ndarray) -> np.ndarray:
    """Pixels [M, 2] (OpenCV K) of canonical points [M, 3] seen with the object at ``T_base_obj``."""
    T = np.linalg.inv(T_base_cam) @ T_base_obj
    cam = canon @ T[:3, :3].T + T[:3, 3]
    return (cam @ K.T)[:, :2] / cam[:, 2:3]


def _earns_override(evidence: DepthEvidence | None, surface: np.ndarray | None, tracked: np.ndarray,
                    prior: np.ndarray, settings: TrackerSettings, following: bool) -> bool:
    """Whether the frame's depth backs the tracked pose over the prior's: clearly better to start
    an override (ratio and margin), not worse by more than the margin to continue one; always
    without ``settings.depth_evidence``."""
    if not settings.depth_evidence:
        return True
    if evidence is None or surface is None:
        return False
    at_tracked, at_prior = evidence.misfit(surface, tracked), evidence.misfit(surface, prior)
    if not np.isfinite(at_tracked):
        return False
    if following:
        return at_tracked <= at_prior + settings.evidence_margin
    return at_tracked <= settings.evidence_ratio * at_prior and at_prior - at_tracked >= settings.evidence_margin


def _disagree(a: np.ndarray, b: np.ndarray, settings: TrackerSettings) -> bool:
    """Whether two poses differ by more than the thresholds."""
    dt = np.linalg.norm(a[:3, 3] - b[:3, 3])
    angle = float(rotation_error(torch.as_tensor(a[:3, :3]), torch.as_tensor(b[:3, :3])))
    return dt > settings.disagree_translation or np.degrees(angle) > settings.disagree_rotation_deg
