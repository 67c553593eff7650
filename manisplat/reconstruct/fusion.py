"""Several demonstrations of one scene reconstructed as one twin.

The episodes (the same table, robot, camera mount and objects; the objects elsewhere) are checked
to show one scene, then joined into one recording whose frames the trainer draws from: one
background, one robot, one canonical model per object, seen from every side any episode showed;
per-episode object trajectories, phases, exposure and held-out frames.

* **Scene**: the same arms, camera (name, size, intrinsics, calibration), mask labels and objects
  in every episode, and the same static surfaces (the first frame's depth where no episode shows
  the robot or an object: :data:`SURFACE_MOVED_M`). A mismatch is refused, naming the episode
  and what differs (:class:`SceneMismatch`).
* **Camera**: the robot's depth checks the extrinsic in every episode
  (:func:`~manisplat.reconstruct.extrinsic.refine_extrinsic`). An episode whose camera sits away
  from where most episodes' is (a bumped mount: :data:`BUMP_DEG`, :data:`BUMP_MM` from the
  fitted camera nearest all others) is refused by name; the twin takes the mean of the trusted
  corrections where more than half the episodes have one, else the calibration. Each episode
  keeps its own camera/joint time offset.
* **Objects**: the first episode's first frame anchors each object's canonical frame; every other
  episode's first frame is registered to it (:func:`~manisplat.reconstruct.register.register_start`)
  and adds the sides it shows. Each episode is then aligned (phases, pseudo poses) on its own.

Memory grows with the frames joined (every image is kept once, as for one episode; each episode's
tensors become views into the joined recording's); an iteration renders one frame, so its time
does not.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from manisplat.align.phases import GripperEvents, Segment
from manisplat.align.pseudo_gt import PseudoPoses
from manisplat.episode.images import describe_chroma
from manisplat.geometry import make_transform, orthonormalize
from manisplat.reconstruct.data import EpisodeData, ReconstructionInputError, retime
from manisplat.reconstruct.extrinsic import ExtrinsicCorrection, pose_difference, refine_extrinsic
from manisplat.reconstruct.plan import Plan
from manisplat.twin.commands import CommandRelation

log = logging.getLogger(__name__)

BUMP_DEG = 0.3  # an episode's camera this far (rotation) from where most episodes' is: a moved camera
BUMP_MM = 3.0  # ... or this far (camera centre)
SURFACE_MOVED_M = 0.02  # static surfaces whose depth differs by this much have moved
SURFACE_MOVED_SHARE = 0.1  # ... over this share of the static pixels both episodes see
NEW_SIDE_M = 0.003  # a registered point this far from the model's adds to it (a side not seen before)


class SceneMismatch(ReconstructionInputError):
    """Episodes that do not show one scene (the episode and what differs are named)."""


@dataclass(frozen=True)
class EpisodeSpan:
    """One episode of a fused recording: its folder, its frames [start, end) and its recorded
    commands (:func:`~manisplat.reconstruct.data.recorded_commands`; None: none recorded)."""

    name: str
    path: Path
    start: int
    end: int
    commands: CommandRelation | None = None

    @property
    def frames(self) -> range:
        return range(self.start, self.end)


def spans_of(datas: list[EpisodeData]) -> list[EpisodeSpan]:
    """The frames each episode takes in the joined recording, in order."""
    spans, start = [], 0
    for d in datas:
        spans.append(EpisodeSpan(Path(d.path).name, Path(d.path), start, start + d.n_frames, d.commands))
        start += d.n_frames
    names = [s.name for s in spans]
    if len(set(names)) != len(names):
        raise ReconstructionInputError(f"episodes with the same folder name: {names}; give each its own name")
    return spans


def check_same_scene(datas: list[EpisodeData]) -> None:
    """Refuse episodes that do not show the first one's scene (:class:`SceneMismatch`)."""
    first = datas[0]
    for d in datas:
        if d.masks is None or d.depth is None:
            raise ReconstructionInputError(f"{d.path}: fusing episodes needs depth and masks in every episode "
                                           f"(this one has {'no depth' if d.depth is None else 'no masks'})")
        if d.riding:
            raise ReconstructionInputError(f"{d.path}: camera {d.camera_name} rides on {d.mount}; fusing "
                                           "episodes needs a fixed reference camera")
    for d in datas[1:]:
        what = _difference(first, d)
        if what:
            raise SceneMismatch(f"{d.path} does not show the scene of {first.path}: {what}")


def _difference(a: EpisodeData, b: EpisodeData) -> str | None:
    """What makes ``b`` another scene than ``a`` (None: the same scene)."""
    if [(x.name, x.model, x.description) for x in a.arms] != [(x.name, x.model, x.description) for x in b.arms]:
        return f"other arms ({[x.name for x in b.arms]}, {[x.model for x in b.arms]} against " \
               f"{[x.name for x in a.arms]}, {[x.model for x in a.arms]})"
    if sorted(a.objects) != sorted(b.objects):
        return f"another object set ({sorted(b.objects)} against {sorted(a.objects)})"
    if a.label_names != b.label_names:
        return "other mask labels (episode.json labels differ)"
    if a.camera_name != b.camera_name or a.size != b.size:
        return f"another camera ({b.camera_name} {b.size[0]}x{b.size[1]} against {a.camera_name} {a.size[0]}x{a.size[1]})"
    if not torch.allclose(a.K_opencv.double(), b.K_opencv.double(), rtol=1e-4, atol=1e-3):
        return "other camera intrinsics"
    if a.chroma_subsampling != b.chroma_subsampling:
        return (f"images stored otherwise (colour {describe_chroma(b.chroma_subsampling)} against "
                f"{describe_chroma(a.chroma_subsampling)}; where that is not so, say how with `manisplat-episode "
                "set-chroma`)")
    rotation, translation = pose_difference(np.linalg.inv(a.viewmat.double().numpy()),
                                            np.linalg.inv(b.viewmat.double().numpy()))
    if rotation > BUMP_DEG or translation > BUMP_MM:
        return f"the camera is calibrated elsewhere ({rotation:.2f} deg, {translation:.1f} mm from the first episode's)"
    moved, share = _surface_change(a, b)
    if share > SURFACE_MOVED_SHARE:
        return (f"the static surfaces moved: {100 * share:.0f} % of the static pixels both first frames see differ in "
                f"depth by more than {100 * SURFACE_MOVED_M:.0f} cm (median {100 * moved:.1f} cm there; the table "
                "or the camera moved?)")
    return None


def _surface_change(a: EpisodeData, b: EpisodeData) -> tuple[float, float]:
    """(median depth change m over the changed pixels, their share) of the static pixels both
    episodes' first frames see with depth."""
    both = a.region(0, a.labels.static) & b.region(0, b.labels.static) & (a.depth[0] > 0) & (b.depth[0] > 0)
    if int(both.sum()) < 100:
        return 0.0, 0.0
    change = (a.depth[0][both] - b.depth[0][both]).abs().double()
    changed = change > SURFACE_MOVED_M
    return (float(change[changed].median()) if bool(changed.any()) else 0.0), float(changed.double().mean())


@dataclass
class CameraConsensus:
    """The camera every episode is trained with: ``T_base_cam`` [4, 4] float64, each episode's
    check (None where it could not say) and its distance from the consensus (deg, mm)."""

    T_base_cam: np.ndarray
    checks: list[ExtrinsicCorrection | None]
    offsets: list[tuple[float, float] | None]

    def to_dict(self, spans: list[EpisodeSpan]) -> dict:
        return {"episodes": {s.name: {"check": None if c is None else
                                      {k: v for k, v in c.to_dict().items() if k != "T_correction"},
                                      "from_consensus_deg_mm": None if o is None else [round(o[0], 4), round(o[1], 3)]}
                             for s, c, o in zip(spans, self.checks, self.offsets)}}


def camera_consensus(datas: list[EpisodeData], plans: list[Plan], *, check: bool = True) -> CameraConsensus:
    """Check the extrinsic in every episode and agree on one camera (module docstring); re-time
    each episode by its own time offset. Raises :class:`SceneMismatch` naming a moved camera."""
    T_recorded = np.linalg.inv(datas[0].viewmat.double().numpy())
    if not check:
        return CameraConsensus(T_recorded, [None] * len(datas), [None] * len(datas))
    checks = []
    for d, plan in zip(datas, plans):
        log.info("%s: checking the camera against the robot's depth", Path(d.path).name)
        c = refine_extrinsic(d, plan.train_frames)
        checks.append(c)
        if c is not None and c.time_applied:
            retime(d, d.time_offset_s + c.time_offset_s)
    fitted = [None if c is None else (c.T_fitted if c.T_fitted is not None else c.T_after) for c in checks]
    # where most episodes' cameras are: the fitted camera nearest all others (one bumped camera cannot move it)
    found = [T for T in fitted if T is not None]
    medoid = min(found, key=lambda A: sum(_distance(A, B) for B in found)) if found else T_recorded
    moved = [(Path(d.path).name, pose_difference(medoid, T)) for d, T in zip(datas, fitted) if T is not None]
    moved = [(name, o) for name, o in moved if o[0] > BUMP_DEG or o[1] > BUMP_MM]
    if moved:
        listed = "; ".join(f"{name}: {o[0]:.2f} deg, {o[1]:.1f} mm" for name, o in moved)
        raise SceneMismatch(f"the camera moved between episodes: the robot's depth puts it away from where most "
                            f"episodes' is in {listed} (more than {BUMP_DEG} deg or {BUMP_MM} mm): leave "
                            f"{'that episode' if len(moved) == 1 else 'those episodes'} out, or calibrate and "
                            "reconstruct apart")
    trusted = [c.T_after for c in checks if c is not None and c.applied]
    T = _mean_pose(trusted) if len(trusted) * 2 > len(datas) else T_recorded
    offsets = [None if F is None else pose_difference(T, F) for F in fitted]
    log.info("camera: %d of %d episodes' checks trusted; the twin's camera %s", len(trusted), len(datas),
             "their mean" if T is not T_recorded else "as calibrated")
    return CameraConsensus(T, checks, offsets)


def _distance(A: np.ndarray, B: np.ndarray) -> float:
    """Two camera poses' difference in units of the bump thresholds (rotation / BUMP_DEG + centre / BUMP_MM)."""
    rotation, translation = pose_difference(A, B)
    return rotation / BUMP_DEG + translation / BUMP_MM


def _mean_pose(poses: list[np.ndarray]) -> np.ndarray:
    """The chordal mean of [4, 4] poses (rotation projected to SO(3), translation averaged)."""
    R = orthonormalize(torch.as_tensor(np.mean([p[:3, :3] for p in poses], axis=0)))
    return make_transform(R, torch.as_tensor(np.mean([p[:3, 3] for p in poses], axis=0))).numpy()


def merged_model(points: list[np.ndarray], colours: list[np.ndarray],
                 spacings: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One object's canonical points [N, 3], colours [N, 3], spacings [N] from each episode's
    (already in the object frame): the first episode's all, each later one's only where it shows a
    side not yet covered (:data:`NEW_SIDE_M`)."""
    P, C, S = [points[0]], [colours[0]], [spacings[0]]
    for p, c, s in zip(points[1:], colours[1:], spacings[1:]):
        dist, _ = cKDTree(np.concatenate(P)).query(p)
        new = dist > NEW_SIDE_M
        P.append(p[new])
        C.append(c[new])
        S.append(s[new])
    return np.concatenate(P), np.concatenate(C), np.concatenate(S)


def joined(datas: list[EpisodeData]) -> EpisodeData:
    """One recording of the episodes' frames in order: every per-frame tensor concatenated, the
    rest (robot, camera, labels, commands, raw joints, path) the first episode's. Each episode's
    tensors become views into the joined ones, field by field, so that no second copy of the
    images outlives its field's concatenation (the peak: the recording plus its largest field)."""
    per_frame = ("rgb", "depth", "masks", "t", "q", "gripper", "link_poses", "link_quats", "tcp", "eval_masks")
    first = datas[0]
    out = {}
    for name in per_frame:
        if getattr(first, name) is None:
            continue
        out[name] = torch.cat([getattr(d, name) for d in datas])
        start = 0
        for d in datas:
            n = d.n_frames
            setattr(d, name, out[name][start:start + n])
            start += n
    return replace(first, **out)


def joined_plan(plans: list[Plan], spans: list[EpisodeSpan]) -> Plan:
    """The episodes' plans as one: frame lists shifted to the joined recording; an object moves
    if it moves in any episode."""
    first = plans[0]

    def shifted(key: str) -> list[int]:
        return [f + s.start for p, s in zip(plans, spans) for f in getattr(p, key)]

    objects = []
    for k, obj in enumerate(first.objects):
        moving = [p.objects[k] for p in plans if p.objects[k].moves]
        objects.append(replace(obj, moves=bool(moving),
                               reason=f"moves in {len(moving)} of {len(plans)} episodes" if moving else obj.reason))
    links = list(dict.fromkeys(l for p in plans for l in p.links))
    return replace(first, frames=spans[-1].end, train_frames=shifted("train_frames"), test_frames=shifted("test_frames"),
                   distinct_train_states=shifted("distinct_train_states"), links=links,
                   skipped_links=[l for l in first.skipped_links if l not in links], objects=objects)


@dataclass
class JoinedAlignment:
    """One object's alignment over the joined recording (phases and events shifted; pseudo poses
    and the baseline concatenated), with each episode's own in ``parts``."""

    segments: list[Segment]
    events: list[GripperEvents]
    pseudo: PseudoPoses
    baseline: np.ndarray | None
    parts: list


def join_alignments(parts: list, spans: list[EpisodeSpan]) -> JoinedAlignment:
    """The per-episode :class:`~manisplat.reconstruct.pipeline.ObjectAlignment` of one object, joined."""
    segments = [replace(s, start=s.start + span.start, end=s.end + span.start) for a, span in zip(parts, spans)
                for s in a.segments]
    events = [GripperEvents(e.grasp + span.start, None if e.release is None else e.release + span.start)
              for a, span in zip(parts, spans) for e in a.events]
    pseudo = PseudoPoses(np.concatenate([a.pseudo.poses for a in parts]), [x for a in parts for x in a.pseudo.source],
                         np.concatenate([a.pseudo.from_tracking for a in parts]))
    baseline = None if any(a.baseline is None for a in parts) else np.concatenate([a.baseline for a in parts])
    return JoinedAlignment(segments, events, pseudo, baseline, list(parts))


__all__ = ["BUMP_DEG", "BUMP_MM", "CameraConsensus", "EpisodeSpan", "JoinedAlignment", "SceneMismatch",
           "camera_consensus", "check_same_scene", "join_alignments", "joined", "joined_plan", "merged_model",
           "spans_of"]
