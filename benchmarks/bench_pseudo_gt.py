"""The pseudo ground truth alone (no training), and what each of its parts contributes, on
shared/data sim_pick_place_small and the generated test set (benchmarks/_testset.py).

Variants, each adding one part:
* ``prior only``: the gripper's kinematics (rest, rigid grasp, rest), tracking never overrides;
* ``+ tracking (confidence)``: tracked poses override the prior when confident, persistent and
  different (the behaviour before the depth check);
* ``+ depth evidence``: ...and only when the frame's depth fits the tracked pose better;
* ``+ centring, settling``: the grasp centres the object between the pads, the release settles
  a small tilt;
* ``+ model in the depth check``: the depth check's model adds the object's model points
  (frame 0) to the surface seen where tracking starts;
* ``+ rest from depth``: a released object is shifted to where the depth after the release says
  it rests;
* ``+ slip in the hand from depth``: a held object follows the slip in the hand the depth shows
  while it is carried;
* ``+ standing on its support`` (the default): a released object stands on the support the depth
  shows under it, as it stood on its own at the start.
Errors against gt.npz by both definitions (manisplat.reconstruct.metrics): fitted offset over all
frames, and start-anchored (mean over the frames after the object first moves; final frame; worst).
Seconds of CPU, tens of seconds with the test set's generation (once).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from benchmarks._harness import BenchContext, MissingBenchmarkData
from benchmarks._testset import test_set
from manisplat.align.tracking import TrackerSettings
from manisplat.reconstruct.data import load_episode_data, load_ground_truth
from manisplat.reconstruct.init import object_gaussians
from manisplat.reconstruct.masks import object_carrier
from manisplat.reconstruct.metrics import pose_errors, start_anchored_errors
from manisplat.reconstruct.pipeline import align_object
from manisplat.reconstruct.plan import make_plan

THREADED = False
NEVER = TrackerSettings(confident_inliers=10**9)
NO_EVIDENCE = TrackerSettings(depth_evidence=False)
@dataclass(frozen=True)
class Variant:
    """Which parts of the pseudo ground truth one variant uses."""

    tracker: TrackerSettings
    model_points: bool = False  # the object's model: the grasp's centring, the release's settling
    rest: bool = False  # where it rests after a release, from depth
    slip: bool = False  # its slip in the hand, from depth
    support: bool = False  # it stands on the support the depth shows under it


VARIANTS = {
    "prior only": Variant(NEVER),
    "+ tracking (confidence)": Variant(NO_EVIDENCE),
    "+ depth evidence": Variant(TrackerSettings(evidence_model=False)),
    "+ centring, settling": Variant(TrackerSettings(evidence_model=False), model_points=True),
    "+ model in the depth check": Variant(TrackerSettings(), model_points=True),
    "+ rest from depth": Variant(TrackerSettings(), model_points=True, rest=True),
    "+ slip in the hand from depth": Variant(TrackerSettings(), model_points=True, rest=True, slip=True),
    "+ standing on its support (default)": Variant(TrackerSettings(), model_points=True, rest=True, slip=True,
                                                   support=True),
}


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    episodes = [ctx.require_shared("data", "sim_pick_place_small")]
    try:
        episodes += test_set(ctx)[: 1 if ctx.quick else None]
    except MissingBenchmarkData as exc:
        ctx.notes.append(f"test set skipped: {exc}")
    rows = []
    for episode in episodes:
        data = load_episode_data(episode, load_meshes=False)
        obj = next(o for o in make_plan(data).objects if o.moves)
        gaussians, T_start = object_gaussians(data, obj.label, 0)
        points = gaussians.params["means"].detach().double().numpy()
        gt = load_ground_truth(episode)[f"T_base_{obj.name}"]
        for variant, parts in VARIANTS.items():
            alignment = align_object(data, obj.label, T_start.numpy(), object_carrier(data, T_start[:3, 3].numpy()),
                                     moves=True, model_points=points if parts.model_points else None,
                                     settings=parts.tracker, rest_from_depth=parts.rest, slip_from_depth=parts.slip,
                                     support_from_depth=parts.support)
            poses = alignment.pseudo.poses
            fitted = pose_errors(poses, gt)
            anchored = start_anchored_errors(poses, gt)
            rows.append({"episode": episode.name, "object": obj.name, "variant": variant,
                         "overrides": int(alignment.pseudo.from_tracking.sum()),
                         "slips_mm": [round(1000 * float(np.linalg.norm(s)), 2) for s in alignment.pseudo.slips],
                         "rest_heights_mm": [round(1000 * h, 2) for h in alignment.pseudo.rest_heights],
                         "fitted_et_cm": fitted["et_cm"], "fitted_er_deg": fitted["er_deg"],
                         "anchored_et_cm": anchored["et_cm"], "anchored_er_deg": anchored["er_deg"],
                         "anchored_max_et_cm": anchored["et_cm_max"], "anchored_max_er_deg": anchored["er_deg_max"],
                         "final_et_cm": anchored["final"]["et_cm"], "final_er_deg": anchored["final"]["er_deg"]})
    for variant in VARIANTS:
        mine = [r for r in rows if r["variant"] == variant]
        rows.append({"episode": "mean", "object": "", "variant": variant, "overrides": float(np.mean([r["overrides"] for r in mine])),
                     **{k: float(np.mean([r[k] for r in mine])) for k in mine[0] if k.endswith(("_cm", "_deg"))}})
    ctx.notes.append("start-anchored: offset fixed by the frames before the object first moves (5 mm / 2 deg from its "
                     "start); errors over the frames after; final = the last frame (where the demonstration leaves it)")
    return rows
