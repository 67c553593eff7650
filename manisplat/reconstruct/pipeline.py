"""From an episode and its plan to a trainable reconstruction: initial nodes, phases, pseudo
ground truth and object trajectories."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from manisplat.align.phases import DEFAULT_TAU, GripperEvents, Segment, gripper_events, segment_phases
from manisplat.align.pseudo_gt import PseudoPoses, hybrid_pseudo_poses, make_tracker, tracked_baseline
from manisplat.align.tracking import ObjectView, TrackerSettings, visible_surface
from manisplat.reconstruct.data import EpisodeData, ReconstructionInputError, retime
from manisplat.reconstruct.extrinsic import refine_extrinsic
from manisplat.reconstruct.init import background_gaussians, link_gaussians, object_gaussians
from manisplat.reconstruct.masks import draw_view_masks, object_carrier, redraw_robot_masks
from manisplat.reconstruct.plan import Plan
from manisplat.reconstruct.poses import ObjectTrajectory
from manisplat.reconstruct.trainer import Reconstruction, TrainConfig
from manisplat.scene import GaussianSet, SceneGraph
from manisplat.scene.transforms import transform_gaussians
from manisplat.splat import rasterization

log = logging.getLogger(__name__)


@dataclass
class ObjectAlignment:
    """What alignment found for one object: phases, pseudo poses, and the phase-free baseline."""

    segments: list[Segment]
    events: list[GripperEvents]
    pseudo: PseudoPoses
    baseline: np.ndarray | None


def build(data: EpisodeData, plan: Plan, config: TrainConfig, *, tau: float = DEFAULT_TAU,
          robot_gaussians: int | None = None, table_z: float = 0.0, masks_from_model: bool = False,
          check_extrinsic: bool = True, views: dict[str, EpisodeData] | None = None,
          progress: bool = False) -> tuple[Reconstruction, dict[str, ObjectAlignment]]:
    """Check the camera extrinsic against the robot, initialise every node and align every
    object (see the plan for what is skipped).

    Args:
        data: the reference camera's view: a fixed camera; it seeds every node and the alignment.
        views: other cameras' views trained at once (wrist cameras riding on a link); those
            without masks get the robot's drawn at each frame and each object's model at its
            pseudo pose (:func:`~manisplat.reconstruct.masks.draw_view_masks`).
        robot_gaussians: the budget shared by the link meshes (default: a quarter of the image's
            pixels, 2 000 to 20 000): more Gaussians than the robot has pixels add no detail.
        table_z: the table's height in the base frame (m), for a start without depth.
        masks_from_model: the objects' masks exist in frame 0 only (no depth to follow them): the
            other frames' come from each object's model at its pseudo pose.
        check_extrinsic: align the robot's depth in the training frames with its model
            (:mod:`manisplat.reconstruct.extrinsic`) and use the corrected ``T_base_cam`` and
            camera/joint time offset for everything after (``data.viewmat`` is replaced, the
            joints re-paired by :func:`~manisplat.reconstruct.data.retime`); the correction is
            kept in ``Reconstruction.extrinsic``.
    """
    if robot_gaussians is None:
        W, H = data.size
        robot_gaussians = int(min(max(W * H // 4, 2_000), 20_000))
    if data.masks is None:
        raise ReconstructionInputError(f"{data.path}: no masks; draw them first (manisplat.reconstruct.masks)")
    if data.riding:
        raise ReconstructionInputError(f"camera {data.camera_name} rides on {data.mount}: the reference camera must be "
                                       "fixed (it seeds the scene); reconstruct with a fixed one among the cameras")
    train = plan.train_frames
    if plan.objects and train[0] != 0:
        raise ReconstructionInputError("the first frame must be a training frame: it seeds the objects")
    correction = refine_extrinsic(data, train) if check_extrinsic else None
    if correction is not None and correction.applied:
        data.viewmat = torch.linalg.inv(torch.as_tensor(correction.T_after)).float()
    if correction is not None and correction.time_applied:
        retime(data, data.time_offset_s + correction.time_offset_s)
    if correction is not None and (correction.applied or correction.time_applied) and \
            data.mask_source.startswith("drawn robot"):
        redraw_robot_masks(data, progress=False)  # drawn with the camera and timing just corrected
    # no pixel of a held-out frame reaches the Gaussians: the first, middle and last training frames seed them
    background = background_gaussians(data, frames=sorted({train[0], train[len(train) // 2], train[-1]}),
                                      sh_degree=config.sh_degree, table_z=table_z)
    links = link_gaussians(data.robot, plan.links, total=robot_gaussians, sh_degree=config.sh_degree)
    objects, trajectories, alignments = {}, {}, {}
    for obj in plan.objects:
        gaussians, T_start = object_gaussians(data, obj.label, 0, sh_degree=config.sh_degree, table_z=table_z)
        objects[obj.name] = gaussians
        model = object_view(gaussians, data) if data.depth is None or masks_from_model else None
        track, width, held_by = object_carrier(data, T_start[:3, 3].double().numpy())
        if len(data.arm_names) > 1:
            log.info("object %s: handled by arm %s", obj.name,
                     ", then ".join(f"{h.arm} (from frame {h.start})" if h.start else h.arm for h in held_by))
        alignment = align_object(data, obj.label, T_start.numpy(), track, width, moves=obj.moves, tau=tau, model=model,
                                 masks_from_model=masks_from_model,
                                 model_points=gaussians.params["means"].detach().double().cpu().numpy(),
                                 observe=frozenset(plan.test_frames))
        alignments[obj.name] = alignment
        if masks_from_model:
            _draw_object_masks(data, obj.label, alignment.pseudo.poses, model)
        trajectories[obj.name] = ObjectTrajectory(alignment.pseudo.poses, alignment.pseudo.source, static=not obj.moves)
        log.info("object %s: %d pose parameters; phases %s", obj.name, trajectories[obj.name].n_params,
                 ", ".join(f"{s.name} {s.start}-{s.end - 1}" for s in alignment.segments))
    for g in [*links.values(), *objects.values()]:
        g.scene_scale = background.scene_scale
    graph = SceneGraph(background, links, list(data.robot.link_names), objects)
    for name, view in (views or {}).items():
        if view.masks is None:
            labels = {label: obj for label, obj in data.labels.objects.items()}
            drawn = [data.labels.robot[v] for v in sorted(data.labels.robot) if data.robot.visuals.get(data.labels.robot[v])]
            draw_view_masks(view, drawn,
                            {obj: (label, objects[obj], alignments[obj].pseudo.poses) for label, obj in labels.items()
                             if obj in objects}, data.label_names, progress=progress)
            log.info("camera %s: masks drawn (robot at each frame's FK, objects at their pseudo poses)", name)
    rec = Reconstruction(data, plan, graph, trajectories, config, views=views)
    rec.extrinsic = correction
    return rec, alignments


def align_object(data: EpisodeData, label: int, T_start: np.ndarray, tcp: np.ndarray, width: np.ndarray, *,
                 moves: bool,
                 tau: float = DEFAULT_TAU, model: ObjectView | None = None,
                 masks_from_model: bool = False, model_points: np.ndarray | None = None,
                 settings: TrackerSettings = TrackerSettings(),
                 observe: frozenset[int] = frozenset(), rest_from_depth: bool = True,
                 slip_from_depth: bool = True) -> ObjectAlignment:
    """Phases, hybrid pseudo poses and (for moving objects) the tracking-only baseline, with the
    tool track that handles the object: ``tcp`` [T, 4, 4] T_base_tcp and the gripper ``width`` [T] m
    (one arm's, or :func:`~manisplat.reconstruct.masks.object_carrier`'s through handovers).

    ``model`` stands in for the depth (monocular) and, with ``masks_from_model``, for the masks
    of frames after the first. ``model_points`` [M, 3] (object frame) enable the grasp's
    centring and the release's settling priors (:func:`manisplat.align.pseudo_gt.kinematic_prior`)
    and complete the tracker's depth check (:class:`~manisplat.align.tracking.DepthEvidence`).
    ``settings``: the tracker's; ``observe``: the held-out frames, whose poses are tracked without
    anything learning from them. ``rest_from_depth``: with ``model_points`` and depth, a released
    object is placed where the depth says it rests
    (:func:`~manisplat.align.pseudo_gt.settle_at_rest`); with it and ``slip_from_depth``, a held one
    follows its slip in the hand (:func:`~manisplat.align.pseudo_gt.follow_slip`).
    """
    events = gripper_events(width)
    segments = segment_phases(tcp[:, :3, 3], width, T_start[:3, 3], tau=tau)
    if not moves:
        poses = np.repeat(T_start[None], data.n_frames, axis=0)
        pseudo = PseudoPoses(poses, ["static"] * data.n_frames, np.zeros(data.n_frames, dtype=bool))
        return ObjectAlignment(segments, events, pseudo, None)
    tracker = make_tracker(
        lambda i: cv2.cvtColor(data.rgb[i].numpy(), cv2.COLOR_RGB2GRAY),
        lambda i: None if masks_from_model and i > 0 else (data.masks[i] == label).numpy(),
        lambda i: None if data.depth is None else data.depth[i].numpy(),
        data.K_opencv.numpy(),
        np.linalg.inv(data.viewmat.double().numpy()),
        settings,
        model=model,
        observe=observe,
        model_points=model_points,
    )
    K, T_base_cam = data.K_opencv.numpy(), np.linalg.inv(data.viewmat.double().numpy())

    def surface(f: int) -> np.ndarray | None:
        if not rest_from_depth or data.depth is None or (masks_from_model and f > 0):
            return None
        return visible_surface((data.masks[f] == label).numpy(), data.depth[f].numpy(), K, T_base_cam)

    pseudo = hybrid_pseudo_poses(segments, T_start, tcp, events, tracker, model_points, observe,
                                 width=width, surface=surface,
                                 slip_from_depth=slip_from_depth)
    baseline = tracked_baseline(tracker, data.n_frames, T_start)
    return ObjectAlignment(segments, events, pseudo, baseline)


def object_view(gaussians: GaussianSet, data: EpisodeData, alpha_threshold: float = 0.5) -> ObjectView:
    """The object's initial Gaussians rendered at a pose: (z-depth [H, W], mask [H, W]) as numpy,
    depth 0 and mask False where the rendered alpha is below ``alpha_threshold``."""
    means, quats, scales, opacities, _ = (x.detach() for x in gaussians.activated())
    W, H = data.size

    def view(T_base_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        m, q = transform_gaussians(torch.as_tensor(T_base_obj, dtype=torch.float64), means, quats)
        with torch.no_grad():
            depth, alpha, _ = rasterization(m, q, scales, opacities, torch.zeros_like(means), data.viewmat[None],
                                            data.K[None], W, H, render_mode="ED")
        visible = (alpha[0, ..., 0] > alpha_threshold).numpy()
        return np.where(visible, depth[0, ..., 0].numpy(), 0.0).astype(np.float32), visible

    return view


def _draw_object_masks(data: EpisodeData, label: int, poses: np.ndarray, model: ObjectView) -> None:
    """Masks of frames after the first: the object's model at its pose, where no robot was drawn."""
    for f in range(1, data.n_frames):
        _, visible = model(poses[f])
        data.masks[f][torch.from_numpy(visible) & (data.masks[f] == 0)] = label


__all__ = ["ObjectAlignment", "align_object", "build", "object_view"]
