"""From an episode and its plan to a trainable reconstruction: initial nodes, phases, pseudo
ground truth and object trajectories."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from manisplat.align.phases import DEFAULT_TAU, GripperEvents, Segment, segment_phases
from manisplat.align.pseudo_gt import (ATTACHED, STATIC, PseudoPoses, hybrid_pseudo_poses, make_tracker,
                                      tracked_baseline)
from manisplat.align.surface_fit import ModelViews
from manisplat.align.support import support_height
from manisplat.align.tracking import ObjectView, TrackerSettings, visible_surface
from manisplat.reconstruct.camera_bodies import add_camera_bodies, find_camera_bodies
from manisplat.reconstruct.data import EpisodeData, ReconstructionInputError
from manisplat.reconstruct.fusion import (CameraConsensus, EpisodeSpan, JoinedAlignment, camera_consensus,
                                          check_same_scene, join_alignments, joined, joined_plan, merged_model,
                                          spans_of)
from manisplat.reconstruct.init import (background_gaussians, canonical_object_points, link_gaussians,
                                        object_close_up_points, object_model, object_points)
from manisplat.reconstruct.masks import (Carrier, draw_view_object_masks, draw_view_robot_masks, object_carrier,
                                         redraw_robot_masks)
from manisplat.reconstruct.plan import Plan
from manisplat.reconstruct.poses import ObjectTrajectory
from manisplat.reconstruct.register import register_starts
from manisplat.reconstruct.rig_check import check_rig
from manisplat.reconstruct.trainer import Reconstruction, TrainConfig
from manisplat.scene import GaussianSet, SceneGraph
from manisplat.scene.transforms import transform_gaussians
from manisplat.splat import rasterization

log = logging.getLogger(__name__)
#: training frames of each riding camera (wrist cameras) whose close-ups seed the background
CLOSE_UP_FRAMES = 8


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
            pseudo pose (:mod:`~manisplat.reconstruct.masks`); those with depth seed the
            background and each object with their close-ups
            (:func:`~manisplat.reconstruct.init.close_up_points`,
            :func:`~manisplat.reconstruct.init.object_close_up_points`).
        robot_gaussians: the budget shared by the link meshes (default: a quarter of the image's
            pixels, 2 000 to 20 000): more Gaussians than the robot has pixels add no detail.
        table_z: the table's height in the base frame (m), for a start without depth.
        masks_from_model: the objects' masks exist in frame 0 only (no depth to follow them): the
            other frames' come from each object's model at its pseudo pose.
        check_extrinsic: align the robot's depth in the training frames with its model
            (:mod:`manisplat.reconstruct.extrinsic`) and use the corrected ``T_base_cam`` and
            camera/joint time offset for everything after (``data.viewmat`` is replaced, the
            joints re-paired by :func:`~manisplat.reconstruct.data.retime`); the correction is
            kept in ``Reconstruction.extrinsic``. With several arms, each arm's base is checked
            against the first's and with riding cameras, each one's ``T_mount_cam`` against the
            robot and the static scene (:mod:`manisplat.reconstruct.rig_check`); what they say
            is kept in ``Reconstruction.rig``.
    """
    if robot_gaussians is None:
        robot_gaussians = default_robot_gaussians(data)
    if data.masks is None:
        raise ReconstructionInputError(f"{data.path}: no masks; draw them first (manisplat.reconstruct.masks)")
    if data.riding:
        raise ReconstructionInputError(f"camera {data.camera_name} rides on {data.mount}: the reference camera must be "
                                       "fixed (it seeds the scene); reconstruct with a fixed one among the cameras")
    train = plan.train_frames
    if plan.objects and train[0] != 0:
        raise ReconstructionInputError("the first frame must be a training frame: it seeds the objects")
    views = views or {}
    rig = check_rig(data, views, train) if check_extrinsic else None
    bodies = find_camera_bodies(data, train)  # the riding cameras' bodies, which the robot's geometry lacks
    if bodies:
        for robot in {id(r): r for r in (data.robot, *(v.robot for v in views.values()))}.values():
            add_camera_bodies(robot, bodies)
        if data.mask_source.startswith("drawn robot"):
            redraw_robot_masks(data, progress=False)
    links = link_gaussians(data.robot, plan.links, total=robot_gaussians, sh_degree=config.sh_degree)
    objects, trajectories, alignments = {}, {}, {}
    seen = {}  # each object's first-frame points, colours and spacing (its frame)
    for obj in plan.objects:
        *seen[obj.name], T_start = canonical_object_points(data, obj.label, 0, table_z=table_z)
        gaussians = objects[obj.name] = object_model(*seen[obj.name], sh_degree=config.sh_degree)
        model = object_view(gaussians, data) if data.depth is None or masks_from_model else None
        carrier = object_carrier(data, T_start[:3, 3].double().numpy())
        if len(data.arm_names) > 1:
            log.info("object %s: handled by arm %s", obj.name,
                     ", then ".join(f"{h.arm} (from frame {h.start})" if h.start else h.arm for h in carrier.holds))
        alignment = align_object(data, obj.label, T_start.numpy(), carrier, moves=obj.moves, tau=tau, model=model,
                                 masks_from_model=masks_from_model,
                                 model_points=gaussians.params["means"].detach().double().cpu().numpy(),
                                 observe=frozenset(plan.test_frames))
        alignments[obj.name] = alignment
        if masks_from_model:
            _draw_object_masks(data, obj.label, alignment.pseudo.poses, model)
        trajectories[obj.name] = ObjectTrajectory(alignment.pseudo.poses, alignment.pseudo.source, static=not obj.moves)
        log.info("object %s: %d pose parameters; phases %s", obj.name, trajectories[obj.name].n_params,
                 ", ".join(f"{s.name} {s.start}-{s.end - 1}" for s in alignment.segments))
    drawn = [data.labels.robot[v] for v in sorted(data.labels.robot) if data.robot.visuals.get(data.labels.robot[v])]
    unmasked = [name for name, view in views.items() if view.masks is None]
    for name in unmasked:
        draw_view_robot_masks(views[name], drawn, data.label_names, list(data.labels.objects.values()),
                              progress=progress)
    # the riding cameras' close-ups of each object, where its pseudo pose is its start's or its grip's
    close_ups = [view for view in views.values() if view.riding and view.depth is not None]
    if close_ups:
        for obj in plan.objects:
            objects[obj.name] = _with_close_ups(obj.name, seen[obj.name], close_ups, alignments[obj.name].pseudo,
                                                train, sh_degree=config.sh_degree)
    for name in unmasked:
        draw_view_object_masks(views[name], {obj: (label, objects[obj], alignments[obj].pseudo.poses)
                                             for label, obj in data.labels.objects.items() if obj in objects})
        log.info("camera %s: masks drawn (robot at each frame's FK, objects at their pseudo poses)", name)
    # no pixel of a held-out frame reaches the Gaussians: the first, middle and last training frames
    # seed them, and the riding cameras with depth add their close-ups from up to CLOSE_UP_FRAMES
    background = background_gaussians(data, frames=sorted({train[0], train[len(train) // 2], train[-1]}),
                                      sh_degree=config.sh_degree, table_z=table_z, riding=close_ups,
                                      riding_frames=train[::max(1, -(-len(train) // CLOSE_UP_FRAMES))])
    _ready_moving_parts([*links.values(), *objects.values()], background.scene_scale, config)
    graph = SceneGraph(background, links, list(data.robot.link_names), objects)
    rec = Reconstruction(data, plan, graph, trajectories, config, views=views)
    rec.extrinsic = None if rig is None else rig.camera
    rec.rig = rig if rig is not None and (rig.bases or rig.riding) else None
    return rec, alignments


def _ready_moving_parts(parts: list[GaussianSet], scene_scale: float, config: TrainConfig) -> None:
    """The links' and objects' Gaussians at the background's ``scene_scale``, learning their response
    to the light where ``config`` asks for it."""
    for g in parts:
        g.scene_scale = scene_scale
        if config.light_response:
            g.learn_light_response()


def _with_close_ups(name: str, seen: tuple[torch.Tensor, torch.Tensor, torch.Tensor], views: list[EpisodeData],
                    pseudo: PseudoPoses, frames: list[int], *, sh_degree: int) -> GaussianSet:
    """One object's Gaussians from what the reference camera's first frame shows (``seen``: its
    points [N, 3] in the object's frame, colours, spacing) and what the riding ``views`` add
    (:func:`~manisplat.reconstruct.init.object_close_up_points`) in the training ``frames`` where
    its pseudo pose is the start's or follows the gripper that holds it (not where it is tracked)."""
    points, colours, spacing = seen[0].float(), seen[1], seen[2]
    placed = [f for f in frames if pseudo.source[f] in (STATIC, ATTACHED)]
    for view in views:
        p, c, g = object_close_up_points(view, placed, pseudo.poses, points, spacing)
        log.info("object %s: %d more Gaussians from camera %s's close-ups", name, len(p), view.camera_name)
        points, colours, spacing = torch.cat([points, p]), torch.cat([colours, c]), torch.cat([spacing, g])
    return object_model(points, colours, spacing, sh_degree=sh_degree)


@dataclass
class FusedBuild:
    """What :func:`build_fused` made: the trainable reconstruction of the joined recording, each
    object's joined alignment, the episodes' frames and the camera they agreed on."""

    reconstruction: Reconstruction
    alignments: dict[str, JoinedAlignment]
    spans: list[EpisodeSpan]
    camera: CameraConsensus


def build_fused(datas: list[EpisodeData], plans: list[Plan], config: TrainConfig, *, tau: float = DEFAULT_TAU,
                robot_gaussians: int | None = None, check_extrinsic: bool = True) -> FusedBuild:
    """One reconstruction of several episodes of one scene (:mod:`manisplat.reconstruct.fusion`):
    the scene checked, the camera agreed on, each object's canonical model anchored in the first
    episode and completed by the others' first frames, each episode aligned on its own, then the
    episodes joined into one recording.

    Raises:
        SceneMismatch: an episode shows another scene or was seen by a moved camera (named).
        ReconstructionInputError: an episode lacks depth or masks, or its first frame is held out.
    """
    check_same_scene(datas)
    spans = spans_of(datas)
    if any(p.objects and p.train_frames[0] != 0 for p in plans):
        raise ReconstructionInputError("the first frame of every episode must be a training frame: it seeds the objects")
    camera = camera_consensus(datas, plans, check=check_extrinsic)
    viewmat = torch.linalg.inv(torch.as_tensor(camera.T_base_cam)).float()
    for d in datas:
        d.viewmat = viewmat.clone()
    first, plan = datas[0], joined_plan(plans, spans)
    if robot_gaussians is None:
        robot_gaussians = default_robot_gaussians(first)
    objects, trajectories, alignments = {}, {}, {}
    for obj in plan.objects:
        starts, model = _object_starts(datas, spans, obj.label, sh_degree=config.sh_degree)
        objects[obj.name] = model
        model_points = model.params["means"].detach().double().numpy()
        views = ModelViews.of(camera.T_base_cam[:3, 3], starts)  # the model: every episode's first frame
        parts = []
        for d, p, span, T_start in zip(datas, plans, spans, starts):
            log.info("%s: aligning %s", span.name, obj.name)
            parts.append(align_object(d, obj.label, T_start, object_carrier(d, T_start[:3, 3]), moves=obj.moves,
                                      tau=tau, model_points=model_points, views=views,
                                      observe=frozenset(p.test_frames)))
        alignments[obj.name] = join_alignments(parts, spans)
        trajectories[obj.name] = ObjectTrajectory(alignments[obj.name].pseudo.poses, alignments[obj.name].pseudo.source,
                                                  static=not obj.moves, episode_starts=tuple(s.start for s in spans))
    data = joined(datas)
    # the first episode's first, middle and last training frames, then each other episode's first
    # (the table its objects hid in the first); no held-out pixel seeds the background
    train = plans[0].train_frames
    seeds = sorted({train[0], train[len(train) // 2], train[-1], *(s.start for s in spans[1:])})
    background = background_gaussians(data, frames=seeds, sh_degree=config.sh_degree)
    links = link_gaussians(first.robot, plan.links, total=robot_gaussians, sh_degree=config.sh_degree)
    _ready_moving_parts([*links.values(), *objects.values()], background.scene_scale, config)
    graph = SceneGraph(background, links, list(first.robot.link_names), objects)
    rec = Reconstruction(data, plan, graph, trajectories, config)
    log.info("fused %d episodes: %d frames (%d training, %d held out)", len(datas), data.n_frames,
             len(plan.train_frames), len(plan.test_frames))
    return FusedBuild(rec, alignments, spans, camera)


def _object_starts(datas: list[EpisodeData], spans: list[EpisodeSpan], label: int, *,
                   sh_degree: int = 0) -> tuple[list[np.ndarray], GaussianSet]:
    """Each episode's ``T_base_obj`` [4, 4] at its first frame, in the canonical frame the first
    episode's first frame anchors (:func:`~manisplat.reconstruct.init.object_gaussians`'s), and
    the canonical Gaussians completed by the sides the others show
    (:func:`~manisplat.reconstruct.fusion.merged_model`)."""
    seen = []
    for d, span in zip(datas, spans):
        try:
            seen.append(object_points(d, label, 0))
        except ValueError as exc:
            raise ReconstructionInputError(f"{span.name}: the first frame must show every object ({exc})") from exc
    centre = seen[0][0].mean(0).numpy()
    T0 = np.eye(4)
    T0[:3, 3] = centre
    starts = [T0]
    points = [seen[0][0].numpy() - centre]
    colours, spacings = [seen[0][1].numpy()], [seen[0][2].numpy()]
    found = register_starts(points[0], colours[0], [(p.numpy(), c.numpy()) for p, c, _ in seen[1:]])
    for (p, c, s), span, reg in zip(seen[1:], spans[1:], found):
        log.info("%s: object label %d starts at (%.3f, %.3f, %.3f) m, turned %.1f deg from the first episode's "
                 "(residual %.1f mm, next best turn %.1f mm)", span.name, label, *reg.T_base_obj[:3, 3],
                 np.degrees(np.arctan2(reg.T_base_obj[1, 0], reg.T_base_obj[0, 0])), 1e3 * reg.residual_m,
                 1e3 * reg.runner_up_m)
        starts.append(reg.T_base_obj)
        R, t = reg.T_base_obj[:3, :3], reg.T_base_obj[:3, 3]
        points.append((p.numpy() - t) @ R)
        colours.append(c.numpy())
        spacings.append(s.numpy())
    P, C, S = merged_model(points, colours, spacings)
    model = GaussianSet.from_points(torch.as_tensor(P).float(), torch.as_tensor(C).float(),
                                    torch.as_tensor(S).float(), opacity=0.8, sh_degree=sh_degree)
    return starts, model


def default_robot_gaussians(data: EpisodeData) -> int:
    """The links' Gaussian budget when none is given: a quarter of the image's pixels, 2 000 to
    20 000 (more Gaussians than the robot has pixels add no detail)."""
    W, H = data.size
    return int(min(max(W * H // 4, 2_000), 20_000))


def align_object(data: EpisodeData, label: int, T_start: np.ndarray, carrier: Carrier, *, moves: bool,
                 tau: float = DEFAULT_TAU, model: ObjectView | None = None,
                 masks_from_model: bool = False, model_points: np.ndarray | None = None,
                 settings: TrackerSettings = TrackerSettings(),
                 observe: frozenset[int] = frozenset(), rest_from_depth: bool = True,
                 slip_from_depth: bool = True, support_from_depth: bool = True,
                 views: ModelViews | None = None) -> ObjectAlignment:
    """Phases, hybrid pseudo poses and (for moving objects) the tracking-only baseline, with the
    tool track that handles the object (:func:`~manisplat.reconstruct.masks.object_carrier`: one
    arm's TCP and gripper, or the holders' through handovers; its grasps and releases from the
    gripper's opening and, where recorded, its effort: :func:`~manisplat.align.phases.gripper_events`).

    ``model`` stands in for the depth (monocular) and, with ``masks_from_model``, for the masks
    of frames after the first. ``model_points`` [M, 3] (object frame) enable the grasp's
    centring and the release's settling priors (:func:`manisplat.align.pseudo_gt.kinematic_prior`)
    and complete the tracker's depth check (:class:`~manisplat.align.tracking.DepthEvidence`).
    ``settings``: the tracker's; ``observe``: the held-out frames, whose images the tracker does
    not read (:func:`~manisplat.align.tracking.track_object`). ``rest_from_depth``: with
    ``model_points`` and depth, a released object is placed where the depth says it rests
    (:func:`~manisplat.align.pseudo_gt.settle_at_rest`) and, with masks and ``support_from_depth``,
    stands on the support the depth shows under it (:func:`~manisplat.align.pseudo_gt.rest_on_support`);
    with it and ``slip_from_depth``, a held one
    follows its slip in the hand (:func:`~manisplat.align.pseudo_gt.follow_slip`), from the frames
    that see it from near where ``model_points`` were seen (``views``; default: this episode's
    first frame, ``T_start``).
    """
    tcp, width = carrier.track, carrier.width
    events = carrier.events()
    segments = segment_phases(tcp[:, :3, 3], events, T_start[:3, 3], tau=tau)
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

    moving = np.array(data.labels.moving)

    def support(hull_xy: np.ndarray, z_low: float, frames: list[int]) -> float | None:
        views = ((data.depth[f].numpy(), ~np.isin(data.masks[f].numpy(), moving)) for f in frames)
        return support_height(hull_xy, z_low, views, K, T_base_cam)

    supported = (rest_from_depth and support_from_depth and data.depth is not None and data.masks is not None
                 and not masks_from_model)
    if views is None:
        views = ModelViews.of(T_base_cam[:3, 3], [T_start])
    pseudo = hybrid_pseudo_poses(segments, T_start, tcp, events, tracker, model_points, observe,
                                 width=width, surface=surface, slip_from_depth=slip_from_depth, views=views,
                                 support=support if supported else None)
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


__all__ = ["FusedBuild", "ObjectAlignment", "align_object", "build", "build_fused", "object_view"]
