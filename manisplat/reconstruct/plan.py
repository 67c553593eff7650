"""The reconstruction plan: inspect the episode first and skip what the scene does not need.

* An object that never moves gets one static pose: no tracking, no per-frame poses.
* Frames that repeat the previous frame's state (arm, gripper, objects still) add no dynamic
  work: training draws each distinct state once, not each frame.
* Links never visible get no Gaussians.
* No depth means a monocular start (a table plane and a distant backdrop); no masks means the
  robot's are drawn from its meshes and the object's segmented from a prompt
  (:mod:`manisplat.reconstruct.masks`).
* Every 8th frame is held out for evaluation.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from manisplat.reconstruct.data import EpisodeData
from manisplat.reconstruct.init import backproject

log = logging.getLogger(__name__)

HOLDOUT_EVERY = 8
HOLDOUT_OFFSET = 4  # held out: frames 4, 12, 20, ...; frame 0, which seeds the objects, trains
STILL_JOINTS = 1e-4  # rad: below this change between frames the arm is still
STILL_GRIPPER = 1e-4  # m
MOVING_OBJECT = 0.01  # m: an object whose centre moves more than this is tracked


@dataclass
class ObjectPlan:
    """What to do with one manipulated object."""

    name: str
    label: int | None
    moves: bool
    displacement_m: float
    reason: str


@dataclass
class Plan:
    """Decisions taken before optimising (printed by ``--plan``, stored in metrics.json)."""

    frames: int
    train_frames: list[int]
    test_frames: list[int]
    distinct_train_states: list[int]
    depth: bool
    masks: str
    links: list[str]
    skipped_links: list[str]
    objects: list[ObjectPlan] = field(default_factory=list)
    init: str = "depth"

    def summary(self) -> str:
        lines = [
            f"frames        {self.frames}: {len(self.train_frames)} train, {len(self.test_frames)} held out (every {HOLDOUT_EVERY}th)",
            f"distinct      {len(self.distinct_train_states)} distinct train states "
            f"({len(self.train_frames) - len(self.distinct_train_states)} frames repeat the previous state and add no dynamic work)",
            f"depth         {'yes' if self.depth else 'no'}; initialisation: {self.init}",
            f"masks         {self.masks}",
            f"robot links   {', '.join(self.links)}" + (f" (never visible, no Gaussians: {', '.join(self.skipped_links)})" if self.skipped_links else ""),
        ]
        for o in self.objects:
            what = "tracked, per-frame poses" if o.moves else "one static pose (no tracking)"
            lines.append(f"object        {o.name}: {what} ({o.reason})")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["train_frames"] = len(self.train_frames)
        d["test_frames"] = self.test_frames
        d["distinct_train_states"] = len(self.distinct_train_states)
        return json.loads(json.dumps(d))


def make_plan(data: EpisodeData) -> Plan:
    """Inspect ``data`` and decide (see the module docstring)."""
    n = data.n_frames
    test = list(range(HOLDOUT_OFFSET, n, HOLDOUT_EVERY))
    train = [i for i in range(n) if i % HOLDOUT_EVERY != HOLDOUT_OFFSET]
    links, skipped = _visible_links(data, train)
    objects = [_object_plan(data, name, train) for name in data.objects]
    moving = [o for o in objects if o.moves]
    distinct = _distinct_states(data, train, objects_move=bool(moving))
    plan = Plan(
        frames=n, train_frames=train, test_frames=test, distinct_train_states=distinct,
        depth=data.depth is not None, masks=data.mask_source if data.masks is not None else "none", links=links, skipped_links=skipped,
        objects=objects, init="depth" if data.depth is not None else "monocular (table plane and backdrop)",
    )
    return plan


def _visible_links(data: EpisodeData, train: list[int]) -> tuple[list[str], list[str]]:
    """Links seen in at least one training frame's mask (all links without masks), and the rest."""
    names = [name for name in data.robot.link_names if data.robot.visuals.get(name)]
    if data.masks is None:
        return names, []
    present = set(torch.unique(data.masks[train]).tolist())
    seen = {link for value, link in data.labels.robot.items() if value in present}
    return [l for l in names if l in seen], [l for l in names if l not in seen]


def _object_plan(data: EpisodeData, name: str, train: list[int]) -> ObjectPlan:
    label = next((v for v, o in data.labels.objects.items() if o == name), None)
    if data.masks is None or data.depth is None or label is None:
        return ObjectPlan(name, label, True, float("nan"), "no masks or depth to prove it still: tracked")
    centres, first_area = [], None
    T_base_cam = torch.linalg.inv(data.viewmat.double())
    for i in train:
        keep = data.masks[i] == label
        area = int(keep.sum())
        if first_area is None:
            first_area = area
        if area < 0.5 * max(first_area, 1):  # occluded: its centroid would be biased
            continue
        pts, _, _ = backproject(data.depth[i], data.K_opencv, T_base_cam, keep)
        if len(pts):
            centres.append(pts.double().mean(0).numpy())
    if len(centres) < 2:
        return ObjectPlan(name, label, True, float("nan"), "rarely visible: tracked")
    c = np.stack(centres)
    displacement = float(np.linalg.norm(c - c[0], axis=1).max())
    moves = displacement > MOVING_OBJECT
    reason = f"its centre moves up to {displacement * 100:.1f} cm in well-visible frames"
    return ObjectPlan(name, label, moves, displacement, reason)


def _distinct_states(data: EpisodeData, train: list[int], objects_move: bool) -> list[int]:
    """Train frames whose arm/gripper state differs from the previous train frame's."""
    out: list[int] = []
    for i in train:
        if out:
            j = out[-1]
            still = (float((data.q[i] - data.q[j]).abs().max()) < STILL_JOINTS
                     and float((data.gripper[i] - data.gripper[j]).abs().max()) < STILL_GRIPPER)
            if still and not (objects_move and _images_differ(data, i, j)):
                continue
        out.append(i)
    return out


def _images_differ(data: EpisodeData, i: int, j: int, level: float = 12.0, fraction: float = 0.002) -> bool:
    """Whether frames differ: more than ``fraction`` of the pixels changed by over ``level`` grey
    levels in some channel (a small moving part changes few pixels, sensor noise few levels)."""
    changed = (data.rgb[i].float() - data.rgb[j].float()).abs().amax(-1) > level
    return float(changed.float().mean()) > fraction
