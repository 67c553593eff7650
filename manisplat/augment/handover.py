"""An object handed from one gripper to the other (a Cobot Magic handover), as augmentation moves it.

The handover is one skill that both arms share, ``S_handover``: the source frames from the first
of the two TCPs coming within ``tau`` of the handover spot (where the object is when the taker's
gripper starts closing) to the last leaving it, around the taker's grasp and the giver's release.
A new demonstration moves that skill rigidly as one: both arms' TCPs by the same transform, the
one that takes the object's handover pose to its new, sampled pose. Otherwise each arm sees its
own half of the object's story and is planned as one arm is (:mod:`manisplat.augment.arm_view`):

* the giver picks the object where it starts and "places" it at the handover pose, where it lets
  go (its object track holds the handover pose from there);
* the taker finds it "resting" at the handover pose (its track holds that pose until there),
  picks it up there and places it.

Then one arm's start is delayed so that both enter the shared skill at the same frame
(:func:`entry_delays`; where one arm must slow the skill down for its limits, the other is planned
again at that pace by :class:`~manisplat.augment.bimanual.BimanualPlanner`), and the object's
track is the giver's until the taker holds it, the taker's after (:func:`handed_track`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from manisplat.align.acting_arm import Hold
from manisplat.align.phases import DEFAULT_TAU, HYSTERESIS, gripper_events, interval_around
from manisplat.augment.draws import Draws
from manisplat.augment.errors import Rejected
from manisplat.augment.source import SourceError, rigid
from manisplat.twin import Phase

HANDOVER_SKILL = "S_handover"
HANDOVER_RANGE = (0.04, 0.04, 0.02)
"""m: default half-ranges of the handover point's new position along the world's x, y and z."""


@dataclass(frozen=True)
class Handover:
    """``object`` passed from ``giver`` to ``taker`` in the source demonstration.

    Attributes:
        grasp: the source frame where the taker's gripper starts closing on it.
        takeover: the frame from which the taker holds it (its pads have closed).
        release: the frame where the giver's gripper starts opening.
        skill: the shared skill's source frames [start, end).
        T_world_obj: the object's pose at ``grasp`` [4, 4] (world, m): what the shared skill is
            relative to.
    """

    object: str
    giver: str
    taker: str
    grasp: int
    takeover: int
    release: int
    skill: Phase
    T_world_obj: np.ndarray


def find_handover(name: str, order: list[Hold], tcp: dict[str, np.ndarray], gripper: dict[str, np.ndarray],
                  poses: np.ndarray, tau: float = DEFAULT_TAU) -> Handover:
    """The :class:`Handover` of object ``name`` from who holds it when (``order``, two holds).

    Args:
        tcp: arm -> TCP positions [T, 3] (world, m); gripper: arm -> opening [T] (m).
        poses: the object's poses [T, 4, 4] (world).

    Raises:
        SourceError: the object changes hands more than once, the giver never lets go, or either
            TCP is farther than ``tau`` from the handover spot when it closes or opens there.
    """
    if len(order) != 2:
        raise SourceError(f"{name} changes hands {len(order) - 1} times: augmentation handles one handover")
    giver, (taker, takeover) = order[0].arm, (order[1].arm, order[1].start)
    taker_grasp = max((e.grasp for e in gripper_events(np.asarray(gripper[taker], np.float64)) if e.grasp <= takeover),
                      default=None)
    release = next((e.release for e in gripper_events(np.asarray(gripper[giver], np.float64))
                    if e.grasp < takeover and (e.release is None or e.release > takeover)), None)
    if taker_grasp is None or release is None:
        raise SourceError(f"{name}: the {giver} arm never lets go of it after the {taker} arm takes it at frame "
                          f"{takeover}")
    spot = np.asarray(poses[taker_grasp], np.float64)[:3, 3]
    windows = []
    for arm, frame, what in ((taker, taker_grasp, "closes on"), (giver, release, "lets go of")):
        distance = np.linalg.norm(np.asarray(tcp[arm], np.float64) - spot, axis=1)
        window = interval_around(distance, frame, tau, tau * HYSTERESIS)
        if window is None:
            raise SourceError(f"{name}: the {arm} arm's TCP is {distance[frame] * 100:.1f} cm from the handover spot "
                              f"when it {what} the object at frame {frame} (more than {tau * HYSTERESIS * 100:g} cm)")
        windows.append(window)
    skill = Phase("skill", HANDOVER_SKILL, min(w[0] for w in windows), max(w[1] for w in windows))
    return Handover(name, giver, taker, taker_grasp, takeover, release, skill, rigid(poses[taker_grasp]))


def giver_part(handover: Handover, poses: np.ndarray, phases: list[Phase]) -> tuple[np.ndarray, list[Phase]]:
    """The giver's view of the handed object: its poses [T, 4, 4] held at the handover pose from
    the taker's grasp on, and its skills: those before the handover, then the shared one."""
    held = np.array(poses, np.float64, copy=True)
    held[handover.grasp:] = handover.T_world_obj
    return held, [*_skills(handover, phases, before=True), handover.skill]


def taker_part(handover: Handover, poses: np.ndarray, phases: list[Phase]) -> tuple[np.ndarray, list[Phase]]:
    """The taker's view: the poses held at the handover pose until the taker's grasp, and its
    skills: the shared one, then those after the handover."""
    held = np.array(poses, np.float64, copy=True)
    held[:handover.grasp] = handover.T_world_obj
    return held, [handover.skill, *_skills(handover, phases, before=False)]


def _skills(handover: Handover, phases: list[Phase], before: bool) -> list[Phase]:
    """The object's own skills before (or after) the shared one; one that overlaps it is refused."""
    start, end = handover.skill.start, handover.skill.end
    for p in phases:
        if p.kind == "skill" and p.start < end and p.end > start:
            raise SourceError(f"{handover.object}: its skill {p.name} (frames {p.start}-{p.end - 1}) overlaps the "
                              f"handover (frames {start}-{end - 1}): the object is picked or placed too close to it")
    return [p for p in phases if p.kind == "skill" and ((p.end <= start) if before else (p.start >= end))]


def moved_handover(T_world_obj: np.ndarray, rng: Draws,
                   handover_range: tuple[float, float, float] = HANDOVER_RANGE) -> np.ndarray:
    """The handover pose [4, 4] moved by an offset drawn uniformly within +- ``handover_range``
    (m, the world's x, y, z); its orientation kept."""
    ranges = tuple(float(r) for r in handover_range)
    if len(ranges) != 3 or min(ranges) < 0 or not all(map(math.isfinite, ranges)):
        raise ValueError(f"handover_range must be three finite half-ranges >= 0 (m), got {handover_range}")
    out = np.array(T_world_obj, np.float64, copy=True)
    out[:3, 3] += [rng.uniform(-r, r) if r > 0 else 0.0 for r in ranges]
    return out


def skill_segment(segments: list[dict], handover: Handover) -> dict:
    """The shared skill's segment among one arm's new ``segments``."""
    return next(s for s in segments if s["kind"] == "skill" and s["name"] == HANDOVER_SKILL
                and s["object"] == handover.object)


def entry_delays(segments: dict[str, list[dict]], handover: Handover) -> dict[str, int]:
    """Frames each arm must wait at its start so that both enter the shared skill together (one of
    them 0), from the arms' new segments.

    Raises:
        Rejected: ("handover_timing", ...) where the arms play the shared skill at different paces
            (one slowed to stay within its limits more than the other): their frames would not meet.
    """
    shared = {arm: skill_segment(segments[arm], handover) for arm in (handover.giver, handover.taker)}
    paces = {arm: float(segment.get("slowed", 1.0)) for arm, segment in shared.items()}
    if abs(paces[handover.giver] - paces[handover.taker]) > 1e-9:
        raise Rejected("handover_timing", "the handover of {} is slowed x{:.2f} by the {} arm and x{:.2f} by the {} arm "
                                          "to stay within their limits: the arms would not meet".format(
                                              handover.object, paces[handover.giver], handover.giver,
                                              paces[handover.taker], handover.taker))
    entry = {arm: segment["frames"][0] for arm, segment in shared.items()}
    latest = max(entry.values())
    return {arm: latest - frame for arm, frame in entry.items()}


def output_frame(segment: dict, source_frame: float) -> int:
    """The first frame of a skill ``segment`` (its ``frames`` and ``source_frames``, both inclusive,
    slowed or not) at or after ``source_frame``."""
    (first, last), (begin, end) = segment["frames"], segment["source_frames"]
    return first + int(math.ceil((source_frame - begin) * (last - first) / (end - begin) - 1e-9))


def handed_track(giver_track: np.ndarray, taker_track: np.ndarray, taker_segments: list[dict],
                 handover: Handover) -> np.ndarray:
    """The handed object's poses [T, 4, 4] on the common timeline: the giver's track until the
    frame the taker holds it (its takeover, in the taker's shared skill), the taker's from there."""
    takeover = output_frame(skill_segment(taker_segments, handover), handover.takeover)
    return np.concatenate([giver_track[:takeover], taker_track[takeover:]])


__all__ = ["HANDOVER_RANGE", "HANDOVER_SKILL", "Handover", "entry_delays", "find_handover", "giver_part",
           "handed_track", "moved_handover", "output_frame", "skill_segment", "taker_part"]
