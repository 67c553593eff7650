"""Hybrid pseudo-ground-truth object poses: what each phase says about where the object is.

* Motions before any grasp and after the last release: the object rests (static pose: the
  initial one, or where the last skill left it).
* Motions while held (M_transfer): attached, ``T_ee(t) @ T_rel`` with ``T_rel`` from the end of
  the pick skill.
* Given the object's model points, two physical facts of a parallel gripper refine the prior:
  closing centres the object between the pads (along the TCP's y axis, the closing direction:
  docs/episode-format.md; the object rests while the pads close, pushed only by the pad that
  reaches it, and is held from the frame they stop, centred at that frame's TCP: the arm yields
  a few millimetres as the pads squeeze), and an object let go on a surface settles on the face it rested on
  before, so a small tilt gained in the hand (a slip) is undone at the release. Both are bounded
  (:data:`MAX_CENTRING`, :data:`MAX_SETTLE_DEG`): a larger correction means the assumption does
  not hold (an object grasped by a handle, a deliberate re-orientation), and the prior keeps the
  rigid grasp. The centring needs both extremes the pads touch in the model: its extent along
  the closing axis must match the opening where the pads stopped (:func:`centring_offset`).
  On the shared pick-and-place they take the pseudo poses' error where the object
  is left from 0.55 cm / 1.28 deg to 0.33 cm / 1.07 deg (start-anchored;
  benchmarks/results_reconstruct/pseudo_gt.json).
* Where an object is let go, the frames' depth says where it came to rest: once the pads have
  opened, the object's visible surface in every later frame (until the next grasp) is aligned
  with its model points by one shift of position (:meth:`SurfaceModel.fit_shift`; the orientation stays the
  prior's). The rigid grasp misses a slip in the hand and the drop onto the support, 2-4 mm
  (MAX_REST_SHIFT bounds it: a larger shift is not a settle).
* Where it is let go, it stands on the support under it as it stood on its own at the start: its
  rest is raised or lowered to the height the depth shows for the support under its footprint in
  the frames before it arrived (:func:`rest_on_support`, :mod:`manisplat.align.support`); the
  carry sets it down as high as it sagged or slipped in the hand.
* While held, the depth shows the object slipping in the hand (:func:`follow_slip`): each held
  frame's visible surface is aligned with the model by a shift of position, the shifts (in the
  TCP's frame) are smoothed by a running median across the pads' closing axis and taken as one
  offset along it (the pads clamp the object there: what the depth shows along it is the
  centring's error, held from the close to the release), and the carry takes them only when the
  depth fits the shifted poses clearly better than the rigid grasp (misfit below
  :data:`SLIP_EVIDENCE_RATIO` of the rigid grasp's and :data:`SLIP_EVIDENCE_M` less), both
  misfits counted above the depth's own noise floor (:func:`noise_floor`).
* Skills: tracked keypoints (:func:`manisplat.align.tracking.track_object`), starting from the
  pose the previous phase ended with, guided by the gripper prior (rest until the grasp, move
  with the gripper until the release): tracking overrides it only when confident and different.
The baseline without this phase prior tracks through the whole episode.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.spatial import QhullError

from manisplat.align.phases import GripperEvents, Segment
from manisplat.align.support import footprint
from manisplat.align.surface_fit import MAX_VIEW_CHANGE_DEG, ModelViews, SurfaceModel
from manisplat.align.tracking import ObjectView, TrackerSettings, track_object

log = logging.getLogger(__name__)

STATIC, ATTACHED, TRACKED = "static", "attached", "tracked"


@dataclass
class PseudoPoses:
    """Per-frame pseudo-ground-truth ``poses`` [T, 4, 4] (T_base_obj, float64), the ``source`` of
    each ("static", "attached", "tracked": the phase's policy) and ``from_tracking`` [T], True where
    a skill frame took the tracked pose over the gripper prior."""

    poses: np.ndarray
    source: list[str]
    from_tracking: np.ndarray
    rest_shifts: list[np.ndarray] = field(default_factory=list)  # [3] (m, base frame) per settled release
    slips: list[np.ndarray] = field(default_factory=list)  # [3] (m, TCP frame): each followed slip where it ended
    rest_heights: list[float] = field(default_factory=list)  # m: each release's rest raised (+) or lowered onto its support


MAX_CENTRING = 0.015  # m: a larger offset between the pads' centre and the object's is not a squeeze
CENTRING_WIDTH_TOLERANCE = 0.004  # m: the model's extent along the closing axis against the pads' opening
MAX_SETTLE_DEG = 10.0  # a larger tilt at the release is a deliberate re-orientation, not a slip
MAX_REST_SHIFT = 0.01  # m: a larger shift of where an object was let go is not a slip or a drop
#: deg: an object let go turned further than this from how it stood at its start (its up axis) does not
#: sit on its lowest model points as it sat there (another face down; the model may lack either)
MAX_REST_TILT_DEG = 10.0
MIN_REST_POINTS = 100  # fewer surface points after a release than this, and the prior stands
MIN_SLIP_POINTS = 30  # a held frame with fewer visible surface points says nothing about a slip
SLIP_WINDOW = 3  # frames each side of the running median over the per-frame slips
SLIP_EVIDENCE_RATIO = 0.8  # the slipped carry's depth misfit must be below this share of the rigid one's...
SLIP_EVIDENCE_M = 2.5e-4  # ...and this much (m) less (both above the noise floor), else the rigid grasp stands
SUPPORT_FRAMES = 40  # frames (evenly spread) a support's height is read in (at most)


def kinematic_prior(T_start: np.ndarray, tcp: np.ndarray, events: list[GripperEvents], *,
                    model_points: np.ndarray | None = None, up: np.ndarray | None = None,
                    width: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """What the gripper implies: the object rests until a grasp has closed, then moves rigidly
    with the TCP until the release, where it stays. Returns (poses [T, 4, 4], held [T] bool).

    Args:
        model_points: the object's surface points [M, 3] (object frame): with them and ``width``
            a grasp centres the object between the pads (module doc, :func:`centring_offset`).
        up: the object-frame direction [3] that points up while it rests (default: the one
            that points up at ``T_start``); with ``model_points`` a release settles it back.
        width: the gripper opening [T] (m). With it a grasp closes over the frames until the
            opening stops shrinking (:func:`close_end`): the object rests meanwhile, pushed along
            the closing axis only by the pad that reaches it (:func:`pad_push`), and is held
            from the frame the pads stopped, centred at the TCP of that frame when the model
            shows both sides the pads touch. Without it the object is held from the grasp frame,
            as seen (no opening: nothing to check a centring against).
    """
    T = len(tcp)
    closes = {e.grasp: close_end(width, e.grasp, e.release) if width is not None else e.grasp for e in events}
    releases = {e.release for e in events if e.release is not None}
    poses, held = np.zeros((T, 4, 4)), np.zeros(T, dtype=bool)
    current, T_rel, holding = np.asarray(T_start, dtype=np.float64), None, False
    rest, offset, axis, closed_at = current, 0.0, None, None  # the close in progress
    if up is None:
        up = current[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    for f in range(T):
        if f in closes:
            rest, closed_at = current, closes[f]
            offset, axis = 0.0, tcp[closed_at][:3, 1]
            if model_points is not None and width is not None and f > 0:  # at 0 it was held already
                offset = centring_offset(current, tcp[closed_at], model_points, float(width[closed_at]))
        if closed_at is not None:
            closing = f < closed_at  # the pads have not stopped (only with ``width``)
            current = rest.copy()
            current[:3, 3] -= (pad_push(offset, width[f] - width[closed_at]) if closing else offset) * axis
            if not closing:
                T_rel, holding, closed_at = np.linalg.inv(tcp[f]) @ current, True, None
        if f in releases:
            holding, closed_at = False, None
            if model_points is not None:
                current = settled(current, up, model_points)
        if holding:
            current = tcp[f] @ T_rel
        poses[f], held[f] = current, holding
    return poses, held


def close_end(width: np.ndarray, grasp: int, release: int | None = None, *, tolerance: float = 2e-4) -> int:
    """The frame at which a close that began at ``grasp`` has stopped: the first from which the
    opening ``width`` [T] (m) shrinks by less than ``tolerance`` to the next frame (the pads
    met the object, or the gripper is shut); before ``release`` and within the track."""
    return _until_still(-np.asarray(width), grasp, (len(width) if release is None else release) - 1, tolerance)


def _until_still(growing: np.ndarray, start: int, last: int, tolerance: float) -> int:
    """The first frame from ``start`` (at most ``last``) from which ``growing`` [T] rises by less
    than ``tolerance`` to the next frame."""
    f = start
    while f < last and growing[f + 1] > growing[f] + tolerance:
        f += 1
    return f


def pad_push(offset: float, extra_opening: float) -> float:
    """How far (m) the closing pads have pushed an object whose centre is ``offset`` (m, along the
    closing axis) from their midplane, when they are still ``extra_opening`` (m) wider than where
    they stop: nothing until the nearer pad reaches it, then what keeps it between them; all of
    ``offset`` once they stop (the stop is where both touch: the object's width)."""
    remaining = max(extra_opening, 0.0) / 2
    return float(np.sign(offset) * max(abs(offset) - remaining, 0.0))


def centring_offset(T_obj: np.ndarray, T_tcp: np.ndarray, model_points: np.ndarray, opening: float) -> float:
    """How far (m) the object's centre lies from the pads' midplane along the TCP's closing axis
    (y): the middle of the model points' extent along that axis (1st-99th percentiles, robust to
    stray points), where the pads stopped ``opening`` (m) apart. 0 (the grasp kept as seen) when
    the offset exceeds :data:`MAX_CENTRING` (the pads hold a part away from the centre: a
    handle, a long object's end) or when the extent differs from the opening by more than
    :data:`CENTRING_WIDTH_TOLERANCE`: the pads touch the object's two extremes along the axis,
    so a model that spans less than the opening shows one side only (a can seen from the side,
    its near half; from 1 m its far rim lost at the silhouette), and its middle is off by half
    of what is hidden (5-10 mm on the viewpoint set of benchmarks/_viewpoints.py, against a true
    offset of 0.1-2.4 mm); one that spans more is noise or not what the pads hold.

    Measured along the closing axis itself: the pads touch the object's extremes along it, and
    a box seen from one side spans its full width there; the middle of a bounding box in the
    object frame's axes, off the closing axis for a turned box, was 0.6-3 mm off on the test set.
    """
    axis = T_tcp[:3, 1]
    along = (model_points @ T_obj[:3, :3].T + T_obj[:3, 3] - T_tcp[:3, 3]) @ axis
    low, high = np.percentile(along, [1, 99])
    if abs((high - low) - opening) > CENTRING_WIDTH_TOLERANCE:
        return 0.0
    offset = float((low + high) / 2)
    return offset if abs(offset) <= MAX_CENTRING else 0.0


def settled(T_obj: np.ndarray, up: np.ndarray, model_points: np.ndarray) -> np.ndarray:
    """The pose [4, 4] with the object's resting ``up`` direction (object frame) turned back to
    vertical, about the centre of its model points; unchanged beyond :data:`MAX_SETTLE_DEG`."""
    current_up = T_obj[:3, :3] @ (up / np.linalg.norm(up))
    vertical = np.array([0.0, 0.0, 1.0])
    axis = np.cross(current_up, vertical)
    s, c = np.linalg.norm(axis), float(current_up @ vertical)
    angle = np.arctan2(s, c)
    if angle < 1e-9 or np.degrees(angle) > MAX_SETTLE_DEG:
        return T_obj
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    R = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    centre = T_obj[:3, :3] @ model_points.mean(0) + T_obj[:3, 3]
    out = T_obj.copy()
    out[:3, :3] = R @ T_obj[:3, :3]
    out[:3, 3] = centre + R @ (T_obj[:3, 3] - centre)
    return out


def open_end(width: np.ndarray, release: int, end: int, *, tolerance: float = 2e-4) -> int:
    """The frame at which the pads, opening from ``release``, have stopped (before ``end``):
    the first from which ``width`` [T] (m) grows by less than ``tolerance`` to the next frame."""
    return _until_still(width, release, end - 1, tolerance)


def _rest_end(events: list[GripperEvents], release: int, T: int) -> int:
    """The frame (exclusive) a rest from ``release`` lasts to: the next grasp, else the track's end ``T``."""
    return min((e.grasp for e in events if e.grasp > release), default=T)


def noise_floor(model: SurfaceModel, poses: np.ndarray, events: list[GripperEvents],
                surface: Callable[[int], np.ndarray | None], observe: frozenset[int] = frozenset()) -> float:
    """The misfit (m) the depth's noise alone leaves: the model (made from frame 0's depth)
    against the object's visible surface in the frames after 0 and before the first grasp, where
    it rests at ``poses`` [T, 4, 4] as frame 0 saw it (held-out frames left out). 0 where no such
    frame shows it (no frame to tell; exact depth gives 0 too). The median over those frames: the
    last ones, where the fingers may already nudge the object, do not raise it.

    Stereo depth of an object 0.6-1.3 m away scatters by millimetres: on the oak copies of the
    viewpoint set this floor is 1.2-3.1 mm, while a carried box that slipped 2.4 mm in the hand
    fits its rigid grasp at 1.82 mm and the slip at 1.60 mm: above the floor (1.27 mm), 1.30
    against 0.96 mm (the same carry in exact depth: 1.61 against 1.06 mm, floor 0)."""
    first_grasp = min((e.grasp for e in events), default=0)
    seen = ((f, surface(f)) for f in range(1, first_grasp) if f not in observe)
    misfits = [model.misfit([X], [poses[f]]) for f, X in seen if X is not None and len(X) >= MIN_SLIP_POINTS]
    return float(np.median(misfits)) if misfits else 0.0


def _above(misfit: float, floor: float) -> float:
    """The part of a misfit (m) above the noise ``floor`` (m), as independent errors add: in quadrature."""
    return math.sqrt(max(misfit ** 2 - floor ** 2, 0.0))


def follow_slip(poses: np.ndarray, events: list[GripperEvents], surface: Callable[[int], np.ndarray | None],
                model_points: np.ndarray, tcp: np.ndarray, width: np.ndarray | None = None,
                observe: frozenset[int] = frozenset(), keep: np.ndarray | None = None,
                views: ModelViews | None = None) -> list[np.ndarray]:
    """Shift ``poses`` [T, 4, 4] (in place) over each held stretch, from the frame the pads stopped
    closing to the release, by the object's slip in the hand that the frames' depth shows.

    Each held frame's visible surface (``surface(f)`` [M, 3], base frame, or None) is aligned with
    ``model_points`` [M, 3] (object frame) by one shift of position (:meth:`SurfaceModel.fit_shift`); the shifts,
    in the TCP's frame (``tcp`` [T, 4, 4]), are smoothed by a running median over
    2 :data:`SLIP_WINDOW` + 1 fitted frames and interpolated between them, except along the pads'
    closing axis (the TCP's y), where the object is clamped: there the median over the whole
    stretch, one offset from the close to the release (held-out frames,
    ``observe``, and frames that ``keep`` [T] bool marks, e.g. tracked poses, are not fitted; the
    held-out ones are shifted; nor are frames that see the object from elsewhere than its model
    was seen from, ``views``). A stretch takes its slip only when the depth misfit of its fitted
    frames drops clearly (:data:`SLIP_EVIDENCE_RATIO`, :data:`SLIP_EVIDENCE_M`; both misfits above
    the depth's :func:`noise_floor`); the object then rests, until the next grasp, shifted as it was
    let go. Returns each taken slip where its stretch ended [3] (m, TCP frame)."""
    T, slips, model = len(poses), [], SurfaceModel(model_points)
    floor = noise_floor(model, poses, events, surface, observe)
    for e in events:
        first = close_end(width, e.grasp, e.release) if width is not None else e.grasp
        end = e.release if e.release is not None else T
        fitted, shifts, surfaces, sparse, unseen = [], [], [], 0, 0
        for f in range(first, end):
            if f in observe or (keep is not None and keep[f]):
                continue
            if views is not None and not views.sees(poses[f]):
                unseen += 1
                continue
            if (X := surface(f)) is None or len(X) < MIN_SLIP_POINTS:
                sparse += 1
                continue
            shift, before, after = model.fit_shift([X], [poses[f]])
            if np.linalg.norm(shift) <= MAX_REST_SHIFT and after < before:
                fitted.append(f)
                shifts.append(tcp[f, :3, :3].T @ shift)
                surfaces.append(X)
        if len(fitted) < 2 * SLIP_WINDOW + 1:
            if unseen > (end - first) // 2:
                log.info("grasp at frame %d: slip in the hand not checked: %d of %d held frames see the object from "
                         "more than %.0f deg away from where its model was seen (surface the model lacks); the rigid "
                         "grasp stands", e.grasp, unseen, end - first, MAX_VIEW_CHANGE_DEG)
            elif sparse > (end - first) // 2:
                log.info("grasp at frame %d: slip in the hand not checked: the object shows fewer than %d depth "
                         "points in %d of %d held frames (small in the image, or hidden by the gripper); the rigid "
                         "grasp stands", e.grasp, MIN_SLIP_POINTS, sparse, end - first)
            else:
                log.info("grasp at frame %d: the depth fits %d of %d held frames, too few to follow a slip in the "
                         "hand; the rigid grasp stands", e.grasp, len(fitted), end - first)
            continue
        shifts = np.array(shifts)
        smooth = np.array([np.median(shifts[max(0, i - SLIP_WINDOW): i + SLIP_WINDOW + 1], axis=0)
                           for i in range(len(fitted))])
        smooth[:, 1] = np.median(shifts[:, 1])  # along the closing axis the pads hold it where they closed
        frames = np.arange(first, end)
        in_hand = np.stack([np.interp(frames, fitted, smooth[:, k]) for k in range(3)], -1)  # [n, 3] TCP frame
        if keep is not None:
            in_hand[keep[first:end]] = 0.0  # a tracked pose is the tracker's own
        slipped = poses[first:end].copy()
        slipped[:, :3, 3] += np.einsum("nij,nj->ni", tcp[first:end, :3, :3], in_hand)
        rigid = _above(model.misfit(surfaces, [poses[f] for f in fitted]), floor)
        taken = _above(model.misfit(surfaces, [slipped[f - first] for f in fitted]), floor)
        if not (taken < SLIP_EVIDENCE_RATIO * rigid and rigid - taken > SLIP_EVIDENCE_M):
            log.info("grasp at frame %d: the depth shows no clear slip in the hand (misfit above the depth's noise "
                     "floor of %.2f mm: %.2f -> %.2f mm); the rigid grasp stands", e.grasp, 1000 * floor,
                     1000 * rigid, 1000 * taken)
            continue
        let_go = slipped[-1, :3, 3] - poses[end - 1, :3, 3]
        poses[first:end] = slipped
        if e.release is not None:
            poses[e.release:_rest_end(events, e.release, T), :3, 3] += let_go
        slips.append(in_hand[-1])
        log.info("grasp at frame %d: the object slipped %.1f mm in the hand by the release (largest %.1f mm; "
                 "depth misfit above its noise floor of %.2f mm %.2f -> %.2f mm)", e.grasp,
                 1000 * np.linalg.norm(in_hand[-1]), 1000 * np.linalg.norm(in_hand, axis=1).max(), 1000 * floor,
                 1000 * rigid, 1000 * taken)
    return slips


def settle_at_rest(poses: np.ndarray, events: list[GripperEvents], surface: Callable[[int], np.ndarray | None],
                   model_points: np.ndarray, width: np.ndarray | None = None,
                   observe: frozenset[int] = frozenset(), views: ModelViews | None = None) -> list[np.ndarray]:
    """Shift ``poses`` [T, 4, 4] (in place) from each release to the next grasp by where the
    frames' depth says the object rests (:meth:`SurfaceModel.fit_shift` over the frames after the pads opened;
    ``surface(f)``: the object's visible surface [M, 3] in frame f, or None without depth).
    Held-out frames (``observe``) are shifted but not fitted, nor are frames that see the object
    from elsewhere than its model was seen from (``views``). Returns the shifts applied."""
    T, shifts, model = len(poses), [], SurfaceModel(model_points)
    for e in events:
        if e.release is None:
            continue
        end = _rest_end(events, e.release, T)
        first = open_end(width, e.release, end) if width is not None else e.release
        seen = [f for f in range(first, end) if f not in observe and (views is None or views.sees(poses[f]))]
        if first < end and not seen:
            log.info("release at frame %d: where it rests not fitted: the camera sees it there from more than %.0f deg "
                     "away from where its model was seen (surface the model lacks); the prior stands", e.release,
                     MAX_VIEW_CHANGE_DEG)
            continue
        fitted = [(f, X) for f in seen if (X := surface(f)) is not None]
        if sum(len(X) for _, X in fitted) < MIN_REST_POINTS:
            continue
        shift, before, after = model.fit_shift([X for _, X in fitted], [poses[f] for f, _ in fitted])
        if np.linalg.norm(shift) > MAX_REST_SHIFT or not after < before:
            log.info("release at frame %d: the depth's rest shift %.1f mm is not a settle; the prior stands",
                     e.release, 1000 * np.linalg.norm(shift))
            continue
        poses[e.release:end, :3, 3] += shift
        shifts.append(shift)
        log.info("release at frame %d: came to rest %.1f mm from the rigid grasp's pose (depth misfit %.2f -> %.2f mm)",
                 e.release, 1000 * np.linalg.norm(shift), 1000 * before, 1000 * after)
    return shifts


def rest_on_support(poses: np.ndarray, events: list[GripperEvents],
                    support: Callable[[np.ndarray, float, list[int]], float | None], model_points: np.ndarray,
                    observe: frozenset[int] = frozenset()) -> list[float]:
    """Raise or lower ``poses`` [T, 4, 4] (in place) from each release to the next grasp so that the
    object's lowest points stand on the support under it as they stood on theirs at frame 0.
    ``support(hull_xy, z_low, frames)``: the support's height (m) under a footprint
    (:func:`manisplat.align.support.footprint`) in those frames, or None. The start's support is
    read once the object has left it (from the first release), each rest's before the object was
    picked up; held-out frames (``observe``) are moved but not read. A change beyond
    :data:`MAX_REST_SHIFT` is not a rest on that support: the pose stands. Returns the changes (m)."""
    T, heights = len(poses), []
    releases = sorted(e.release for e in events if e.release is not None)
    if not releases:
        return heights

    def frames(first: int, end: int) -> list[int]:
        usable = [f for f in range(first, end) if f not in observe]
        return usable[:: max(1, len(usable) // SUPPORT_FRAMES)]

    try:
        hull, low = footprint(model_points, poses[0])
    except QhullError:
        log.info("the object's model points span no area seen from above: its rests keep their height")
        return heights
    start_support = support(hull, low, frames(releases[0], T))
    if start_support is None:
        log.info("the support under the object's start is not seen once it has left: its rests keep their height")
        return heights
    gap = low - start_support  # how its lowest points sit on a support (as modelled and measured)
    for e in events:
        if e.release is None:
            continue
        end = _rest_end(events, e.release, T)
        tilt = np.degrees(np.arccos(np.clip(poses[0][:3, 2] @ poses[e.release][:3, 2], -1.0, 1.0)))
        if tilt > MAX_REST_TILT_DEG:
            log.info("release at frame %d: it rests turned %.0f deg from how it stood at its start, another face "
                     "down: its height stands", e.release, tilt)
            continue
        hull, low = footprint(model_points, poses[e.release])
        under = support(hull, low, frames(0, e.grasp))
        if under is None:
            log.info("release at frame %d: the support under where it rests is not seen before; its height stands",
                     e.release)
            continue
        change = under + gap - low
        if abs(change) > MAX_REST_SHIFT:
            log.info("release at frame %d: standing on the support would move it %.1f mm: not a rest on it; "
                     "its height stands", e.release, 1000 * change)
            continue
        poses[e.release:end, 2, 3] += change
        heights.append(change)
        log.info("release at frame %d: set on its support (%.1f mm %s the carry's height)", e.release,
                 1000 * abs(change), "above" if change > 0 else "below")
    return heights


def hybrid_pseudo_poses(
    segments: list[Segment],
    T_start: np.ndarray,
    tcp: np.ndarray,
    events: list[GripperEvents],
    tracker: Callable[..., tuple[np.ndarray, np.ndarray]],
    model_points: np.ndarray | None = None,
    observe: frozenset[int] = frozenset(),
    width: np.ndarray | None = None,
    surface: Callable[[int], np.ndarray | None] | None = None,
    slip_from_depth: bool = True,
    views: ModelViews | None = None,
    support: Callable[[np.ndarray, float, list[int]], float | None] | None = None,
) -> PseudoPoses:
    """Pseudo poses for every frame from the phases.

    Args:
        T_start: the object's pose at frame 0 [4, 4].
        tcp: T_base_tcp [T, 4, 4] of every frame.
        events: the gripper's grasps and releases.
        tracker: ``(frames, T_first, prior) -> (poses [n, 4, 4], from_tracking [n])`` (see
            :func:`make_tracker`).
        model_points: the object's surface points [M, 3] (object frame) for the centring and
            settling priors (:func:`kinematic_prior`); without them the grasp is rigid as seen.
        observe: held-out frames: no segment starts from one (the tracker, made with the same
            set, gives them the pose the frames before imply, without reading their images).
        width: the gripper opening [T] (m): grasps close over time (:func:`kinematic_prior`).
        surface: frame -> the object's visible surface [M, 3] (base frame; None without depth):
            with ``model_points``, where a released object rests (:func:`settle_at_rest`) and,
            with ``slip_from_depth``, how it slipped in the hand while held (:func:`follow_slip`).
        views: where ``model_points`` were seen from: frames that see the object from elsewhere
            are not fitted (:class:`~manisplat.align.surface_fit.ModelViews`).
        support: ``(hull_xy, z_low, frames) -> height`` of the support under a footprint (None
            where not seen): with ``model_points``, each rest stands on it (:func:`rest_on_support`).
    """
    T = len(tcp)
    poses = np.zeros((T, 4, 4))
    source = [""] * T
    from_tracking = np.zeros(T, dtype=bool)
    up = np.asarray(T_start, dtype=np.float64)[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # up while it rests
    for seg in segments:
        # each segment continues from the pose of the frame before it (or the one before that
        # when it is only observed: held out from training, nothing may learn from it)
        first = max(seg.start - 1, 0)
        if first in observe and first > 0:
            first -= 1
        current = poses[first] if seg.start > 0 else np.asarray(T_start, dtype=np.float64)
        prior, held = kinematic_prior(current, tcp[first:], _shift(events, first), model_points=model_points, up=up,
                                      width=None if width is None else width[first:])
        offset = seg.start - first
        if seg.kind == "skill":
            frames = range(first, seg.end)
            tracked, used = tracker(frames, current, prior[: len(frames)])
            poses[seg.start:seg.end] = tracked[offset:]
            from_tracking[seg.start:seg.end] = used[offset:]
            source[seg.start:seg.end] = [TRACKED] * (seg.end - seg.start)
        else:
            n = seg.end - seg.start
            poses[seg.start:seg.end] = prior[offset:offset + n]
            source[seg.start:seg.end] = [ATTACHED if h else STATIC for h in held[offset:offset + n]]
    shifts, slips = [], []
    if surface is not None and model_points is not None:
        if slip_from_depth:
            slips = follow_slip(poses, events, surface, model_points, tcp, width, observe, keep=from_tracking,
                                views=views)
        shifts = settle_at_rest(poses, events, surface, model_points, width, observe, views=views)
    heights = []
    if support is not None and model_points is not None:
        heights = rest_on_support(poses, events, support, model_points, observe)
    return PseudoPoses(poses, source, from_tracking, shifts, slips, heights)


def _shift(events: list[GripperEvents], start: int) -> list[GripperEvents]:
    """Events re-indexed to frames counted from ``start`` (events before it dropped)."""
    out = []
    for e in events:
        release = None if e.release is None else e.release - start
        if e.grasp >= start:
            out.append(GripperEvents(e.grasp - start, release))
        elif release is None or release >= 0:
            out.append(GripperEvents(0, release))  # held at the segment's start (maybe never let go)
    return out


def make_tracker(gray, mask, depth, K: np.ndarray, T_base_cam: np.ndarray,
                 settings: TrackerSettings = TrackerSettings(), model: ObjectView | None = None,
                 observe: frozenset[int] = frozenset(), model_points: np.ndarray | None = None):
    """A ``tracker(frames, T_first)`` closure over an episode's images, masks and depth (``model``
    stands in where they are missing; ``observe``: held-out frames, whose images are not read;
    ``model_points`` [M, 3]: the object's surface, for the depth check:
    :func:`manisplat.align.tracking.track_object`)."""

    def tracker(frames: range, T_first: np.ndarray, prior: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        if len(frames) == 1:
            return np.asarray(T_first)[None], np.array([False])
        track = track_object(gray, mask, depth, K, T_base_cam, frames, T_first, settings, prior, model, observe,
                             model_points)
        return track.poses, track.from_tracking

    return tracker


def tracked_baseline(tracker, n_frames: int, T_start: np.ndarray) -> np.ndarray:
    """Per-frame poses [T, 4, 4] from tracking alone through the whole episode (no phase prior)."""
    poses, _ = tracker(range(0, n_frames), T_start, None)
    return poses
