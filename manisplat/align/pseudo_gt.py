"""Hybrid pseudo-ground-truth object poses: what each phase says about where the object is.

* Motions before any grasp and after the last release: the object rests (static pose: the
  initial one, or where the last skill left it).
* Motions while held (M_transfer): attached, ``T_ee(t) @ T_rel`` with ``T_rel`` from the end of
  the pick skill.
* Skills: tracked keypoints (:func:`manisplat.align.tracking.track_object`), starting from the
  pose the previous phase ended with, guided by the gripper prior (rest until the grasp, move
  with the gripper until the release): tracking overrides it only when confident and different.
The baseline without this phase prior tracks through the whole episode.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from manisplat.align.phases import GripperEvents, Segment
from manisplat.align.tracking import ObjectView, TrackerSettings, track_object

STATIC, ATTACHED, TRACKED = "static", "attached", "tracked"


@dataclass
class PseudoPoses:
    """Per-frame pseudo-ground-truth ``poses`` [T, 4, 4] (T_base_obj, float64), the ``source`` of
    each ("static", "attached", "tracked": the phase's policy) and ``from_tracking`` [T], True where
    a skill frame took the tracked pose over the gripper prior."""

    poses: np.ndarray
    source: list[str]
    from_tracking: np.ndarray


def kinematic_prior(T_start: np.ndarray, tcp: np.ndarray, events: list[GripperEvents]) -> tuple[np.ndarray, np.ndarray]:
    """What the gripper implies: the object rests until a grasp, then moves rigidly with the TCP
    until the release, where it stays. Returns (poses [T, 4, 4], held [T] bool)."""
    T = len(tcp)
    grasps = {e.grasp for e in events}
    releases = {e.release for e in events if e.release is not None}
    poses, held = np.zeros((T, 4, 4)), np.zeros(T, dtype=bool)
    current, T_rel, holding = np.asarray(T_start, dtype=np.float64), None, False
    for f in range(T):
        if f in grasps:
            T_rel, holding = np.linalg.inv(tcp[f]) @ current, True
        if f in releases:
            holding = False
        if holding:
            current = tcp[f] @ T_rel
        poses[f], held[f] = current, holding
    return poses, held


def hybrid_pseudo_poses(
    segments: list[Segment],
    T_start: np.ndarray,
    tcp: np.ndarray,
    events: list[GripperEvents],
    tracker: Callable[..., tuple[np.ndarray, np.ndarray]],
) -> PseudoPoses:
    """Pseudo poses for every frame from the phases.

    Args:
        T_start: the object's pose at frame 0 [4, 4].
        tcp: T_base_tcp [T, 4, 4] of every frame.
        events: the gripper's grasps and releases.
        tracker: ``(frames, T_first, prior) -> (poses [n, 4, 4], from_tracking [n])`` (see
            :func:`make_tracker`).
    """
    T = len(tcp)
    poses = np.zeros((T, 4, 4))
    source = [""] * T
    from_tracking = np.zeros(T, dtype=bool)
    current = np.asarray(T_start, dtype=np.float64)
    for seg in segments:
        # the prior for this segment continues from where the previous one left the object
        prior, held = kinematic_prior(current, tcp[max(seg.start - 1, 0):], _shift(events, max(seg.start - 1, 0)))
        offset = 1 if seg.start > 0 else 0
        if seg.kind == "skill":
            frames = range(seg.start - offset, seg.end)
            tracked, used = tracker(frames, current, prior[: len(frames)])
            poses[seg.start:seg.end] = tracked[offset:]
            from_tracking[seg.start:seg.end] = used[offset:]
            source[seg.start:seg.end] = [TRACKED] * (seg.end - seg.start)
        else:
            n = seg.end - seg.start
            poses[seg.start:seg.end] = prior[offset:offset + n]
            source[seg.start:seg.end] = [ATTACHED if h else STATIC for h in held[offset:offset + n]]
        current = poses[seg.end - 1]
    return PseudoPoses(poses, source, from_tracking)


def _shift(events: list[GripperEvents], start: int) -> list[GripperEvents]:
    """Events re-indexed to frames counted from ``start`` (events before it dropped)."""
    out = []
    for e in events:
        release = None if e.release is None else e.release - start
        if e.grasp >= start:
            out.append(GripperEvents(e.grasp - start, release))
        elif release is not None and release >= 0:
            out.append(GripperEvents(0, release))  # held at the segment's start
    return out


def make_tracker(gray, mask, depth, K: np.ndarray, T_base_cam: np.ndarray,
                 settings: TrackerSettings = TrackerSettings(), model: ObjectView | None = None):
    """A ``tracker(frames, T_first)`` closure over an episode's images, masks and depth (``model``
    stands in where they are missing: :func:`manisplat.align.tracking.track_object`)."""

    def tracker(frames: range, T_first: np.ndarray, prior: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        if len(frames) == 1:
            return np.asarray(T_first)[None], np.array([False])
        track = track_object(gray, mask, depth, K, T_base_cam, frames, T_first, settings, prior, model)
        return track.poses, track.from_tracking

    return tracker


def tracked_baseline(tracker, n_frames: int, T_start: np.ndarray) -> np.ndarray:
    """Per-frame poses [T, 4, 4] from tracking alone through the whole episode (no phase prior)."""
    poses, _ = tracker(range(0, n_frames), T_start, None)
    return poses
