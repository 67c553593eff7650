"""Motion / Skill phases from the end-effector-object distance, with the gripper as a cue.

A Skill is where the TCP is within ``tau`` of the object, ``d(t) = |p_tcp(t) - c_obj(t)| < tau``
(entered below ``tau``, left above ``tau * hysteresis``); Motions fill the rest. A pick-and-place
gives M_approach -> S_pick -> M_transfer -> S_place -> M_return: the pick skill is the stretch
around the gripper closing, measured to where the object rested; the place skill the stretch
around it opening, measured to where the object is released (the TCP's position then, plus the
grasp offset). Without a grasp (a reach) the skill is wherever the TCP comes within ``tau``.

``tau`` is in metres. The paper's 0.2 is in its scenes' units; on a PiPER table the pick and
place spots are often closer than 0.2 m apart, which would merge the two skills, so the default
here is 0.08 m. Segments shorter than ``min_duration`` are absorbed by their neighbours.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

DEFAULT_TAU = 0.08  # m
HYSTERESIS = 1.25  # a skill is left where the distance exceeds tau times this


@dataclass(frozen=True)
class Segment:
    """Frames [start, end) of one phase: ``kind`` "motion" or "skill"; ``name`` e.g. "S_pick"."""

    kind: str
    name: str
    start: int
    end: int


@dataclass(frozen=True)
class GripperEvents:
    """Frame indices where the gripper closed (grasp) and opened again (release, or None)."""

    grasp: int
    release: int | None


SQUEEZE_END = 0.25
"""A grip has ended where the gripper's effort falls below this share of its hold (the median
effort between the grasp and the opening's release)."""
MAX_SQUEEZE_LEAD = 5
"""frames: a squeeze that ended further ahead of the opening's release is not the release (a grip
that relaxed while it still held the object): the opening dates it."""


def gripper_events(width: np.ndarray, *, min_change: float = 0.005,
                   effort: np.ndarray | None = None) -> list[GripperEvents]:
    """Grasps and releases in a gripper-width track [T] (m).

    A grasp is the first frame after the gripper starts closing by more than ``min_change`` from
    its recent maximum; the release is the first frame after it opens by that much again. With
    the gripper's ``effort`` [T] (as recorded: its sign and units do not matter, only its size
    against the hold's) the release is the first frame the pads no longer squeeze
    (:func:`squeeze_end`): the object is let go as the motor stops pressing, a frame or two
    before the pads have opened by ``min_change``.
    """
    events, i, n = [], 0, len(width)
    while i < n:
        peak = width[i]
        j = i
        while j < n and width[j] > peak - min_change:
            peak = max(peak, width[j])
            j += 1
        if j >= n:
            break
        low = width[j]
        k = j
        while k < n and width[k] < low + min_change:
            low = min(low, width[k])
            k += 1
        release = k if k < n else None
        if effort is not None and release is not None:
            release = squeeze_end(effort, j, release)
        events.append(GripperEvents(grasp=j, release=release))
        i = k
    return events


def squeeze_end(effort: np.ndarray, grasp: int, release: int) -> int:
    """The frame the pads stopped squeezing an object held from ``grasp`` and let go, by the
    opening, at ``release``: the frame after the last one whose effort [T] (absolute) was at
    least :data:`SQUEEZE_END` of the hold's (its median over the grasp). ``release`` where the
    effort does not show the squeeze (not finite there, or no hold above zero) or ended more than
    :data:`MAX_SQUEEZE_LEAD` frames before it."""
    held = np.abs(np.asarray(effort[grasp:release], np.float64))
    if not len(held) or not np.isfinite(held).all() or (hold := float(np.median(held))) <= 0.0:
        log.info("grasp at frame %d: the gripper's effort shows no squeeze; released where the pads opened (frame %d)",
                 grasp, release)
        return release
    pressing = np.flatnonzero(held >= SQUEEZE_END * hold)
    end = grasp + int(pressing[-1]) + 1
    if release - end > MAX_SQUEEZE_LEAD:
        log.info("grasp at frame %d: the gripper's effort eased at frame %d, %d frames before the pads opened: a "
                 "grip that relaxed while holding, not the release; released where the pads opened (frame %d)",
                 grasp, end, release - end, release)
        return release
    if end < release:
        log.info("grasp at frame %d: the pads stopped squeezing at frame %d (effort under %.0f %% of the hold's "
                 "%.3g), %d frame(s) before the opening showed the release", grasp, end, 100 * SQUEEZE_END,
                 hold, release - end)
    return end


def interval_around(d: np.ndarray, frame: int, tau: float, leave: float) -> tuple[int, int] | None:
    """The stretch around ``frame`` where the distance stays below ``leave``, entered below ``tau``."""
    if d[frame] >= leave:
        return None
    start = frame
    while start > 0 and d[start - 1] < leave:
        start -= 1
    while start < frame and d[start] >= tau:  # the entry is where it first came within tau
        start += 1
    end = frame + 1
    while end < len(d) and d[end] < leave:
        end += 1
    return start, end


def segment_phases(
    tcp: np.ndarray,
    events: list[GripperEvents],
    object_start: np.ndarray,
    *,
    tau: float = DEFAULT_TAU,
    hysteresis: float = HYSTERESIS,
    min_duration: int = 3,
) -> list[Segment]:
    """Phases of an episode from TCP positions [T, 3], the gripper's grasps and releases
    (:func:`gripper_events`) and the object's resting position [3] at the start (all in the base
    frame, m)."""
    T = len(tcp)
    leave = tau * hysteresis
    skills: list[tuple[int, int, str]] = []
    if events:
        for event in events:
            # the object is held between grasp and release: it sits at the TCP plus the grasp offset
            offset = object_start - tcp[event.grasp]
            d_pick = np.linalg.norm(tcp - object_start, axis=1)
            pick = interval_around(d_pick, event.grasp, tau, leave)
            if pick is not None:
                skills.append((*pick, "S_pick"))
            if event.release is not None:
                place_spot = tcp[event.release] + offset
                d_place = np.linalg.norm(tcp - place_spot, axis=1)
                place = interval_around(d_place, event.release, tau, leave)
                if place is not None:
                    skills.append((*place, "S_place"))
                object_start = place_spot
    else:
        d = np.linalg.norm(tcp - object_start, axis=1)
        inside = False
        for i in range(T):
            if not inside and d[i] < tau:
                inside, start = True, i
            elif inside and d[i] > leave:
                skills.append((start, i, "S_reach"))
                inside = False
        if inside:
            skills.append((start, T, "S_reach"))
    skills = _merge_overlaps(sorted(skills))
    return _fill_motions(skills, T, min_duration, grasped=bool(events))


def _merge_overlaps(skills: list[tuple[int, int, str]]) -> list[tuple[int, int, str]]:
    out: list[tuple[int, int, str]] = []
    for start, end, name in skills:
        if out and start <= out[-1][1]:
            log.warning("skills %s and %s overlap (frames %d-%d and %d-%d); merged: consider a smaller tau",
                        out[-1][2], name, out[-1][0], out[-1][1], start, end)
            prev = out.pop()
            out.append((prev[0], max(prev[1], end), f"{prev[2]}+{name}"))
        else:
            out.append((start, end, name))
    return out


def _fill_motions(skills: list[tuple[int, int, str]], T: int, min_duration: int, grasped: bool) -> list[Segment]:
    segments: list[Segment] = []
    cursor = 0
    for i, (start, end, name) in enumerate(skills):
        if start - cursor > 0:
            segments.append(Segment("motion", "", cursor, start))
        segments.append(Segment("skill", name, start, end))
        cursor = end
    if cursor < T:
        segments.append(Segment("motion", "", cursor, T))
    segments = _absorb_short(segments, min_duration)
    named = []
    motions = [s for s in segments if s.kind == "motion"]
    for s in segments:
        if s.kind == "motion":
            if s is motions[0] and s.start == 0:
                name = "M_approach"
            elif s is motions[-1] and s.end == T:
                name = "M_return"
            else:
                name = "M_transfer" if grasped else "M_motion"
            s = Segment("motion", name, s.start, s.end)
        named.append(s)
    return named


def _absorb_short(segments: list[Segment], min_duration: int) -> list[Segment]:
    """Merge segments shorter than ``min_duration`` frames into the previous one (or the next)."""
    out: list[Segment] = []
    for s in segments:
        if out and (s.end - s.start) < min_duration:
            prev = out.pop()
            out.append(Segment(prev.kind, prev.name, prev.start, s.end))
        else:
            out.append(s)
    if len(out) > 1 and out[0].end - out[0].start < min_duration:
        first, second = out[0], out[1]
        out[:2] = [Segment(second.kind, second.name, first.start, second.end)]
    return out


def phase_of_frames(segments: list[Segment], n: int) -> list[str]:
    """The phase name of each of ``n`` frames."""
    names = [""] * n
    for s in segments:
        for i in range(s.start, s.end):
            names[i] = s.name
    return names
