"""From an episode and its plan to a trainable reconstruction: initial nodes, phases, pseudo
ground truth and object trajectories."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from manisplat.align.phases import DEFAULT_TAU, GripperEvents, Segment, gripper_events, segment_phases
from manisplat.align.pseudo_gt import PseudoPoses, hybrid_pseudo_poses, make_tracker, tracked_baseline
from manisplat.reconstruct.data import EpisodeData
from manisplat.reconstruct.init import background_gaussians, link_gaussians, object_gaussians
from manisplat.reconstruct.plan import Plan
from manisplat.reconstruct.poses import ObjectTrajectory
from manisplat.reconstruct.trainer import Reconstruction, TrainConfig
from manisplat.scene import SceneGraph

log = logging.getLogger(__name__)


@dataclass
class ObjectAlignment:
    """What alignment found for one object: phases, pseudo poses, and the phase-free baseline."""

    segments: list[Segment]
    events: list[GripperEvents]
    pseudo: PseudoPoses
    baseline: np.ndarray | None


def build(data: EpisodeData, plan: Plan, config: TrainConfig, *, tau: float = DEFAULT_TAU,
          robot_gaussians: int | None = None) -> tuple[Reconstruction, dict[str, ObjectAlignment]]:
    """Initialise every node and align every object (see the plan for what is skipped).

    ``robot_gaussians`` (default: a quarter of the image's pixels, 2 000 to 20 000) is the
    budget shared by the link meshes: more Gaussians than the robot has pixels add no detail.
    """
    if robot_gaussians is None:
        W, H = data.size
        robot_gaussians = int(min(max(W * H // 4, 2_000), 20_000))
    if data.depth is None or data.masks is None:
        raise NotImplementedError(
            "reconstruction currently needs the episode's depth and masks; "
            "episodes without them are not supported yet"
        )
    background = background_gaussians(data, sh_degree=config.sh_degree)
    links = link_gaussians(data.robot, plan.links, total=robot_gaussians, sh_degree=config.sh_degree)
    objects, trajectories, alignments = {}, {}, {}
    tcp = data.tcp.double().numpy()
    for obj in plan.objects:
        gaussians, T_start = object_gaussians(data, obj.label, 0, sh_degree=config.sh_degree)
        objects[obj.name] = gaussians
        alignment = align_object(data, obj.label, T_start.numpy(), tcp, moves=obj.moves, tau=tau)
        alignments[obj.name] = alignment
        trajectories[obj.name] = ObjectTrajectory(alignment.pseudo.poses, alignment.pseudo.source, static=not obj.moves)
        log.info("object %s: %d pose parameters; phases %s", obj.name, trajectories[obj.name].n_params,
                 ", ".join(f"{s.name} {s.start}-{s.end - 1}" for s in alignment.segments))
    for g in [*links.values(), *objects.values()]:
        g.scene_scale = background.scene_scale
    graph = SceneGraph(background, links, list(data.robot.link_names), objects)
    return Reconstruction(data, plan, graph, trajectories, config), alignments


def align_object(data: EpisodeData, label: int, T_start: np.ndarray, tcp: np.ndarray, *, moves: bool,
                 tau: float = DEFAULT_TAU) -> ObjectAlignment:
    """Phases, hybrid pseudo poses and (for moving objects) the tracking-only baseline."""
    events = gripper_events(data.gripper.numpy())
    segments = segment_phases(tcp[:, :3, 3], data.gripper.numpy(), T_start[:3, 3], tau=tau)
    if not moves:
        poses = np.repeat(T_start[None], data.n_frames, axis=0)
        pseudo = PseudoPoses(poses, ["static"] * data.n_frames, np.zeros(data.n_frames, dtype=bool))
        return ObjectAlignment(segments, events, pseudo, None)
    tracker = make_tracker(
        lambda i: cv2.cvtColor(data.rgb[i].numpy(), cv2.COLOR_RGB2GRAY),
        lambda i: (data.masks[i] == label).numpy(),
        lambda i: data.depth[i].numpy(),
        data.K_opencv.numpy(),
        np.linalg.inv(data.viewmat.double().numpy()),
    )
    pseudo = hybrid_pseudo_poses(segments, T_start, tcp, events, tracker)
    baseline = tracked_baseline(tracker, data.n_frames, T_start)
    return ObjectAlignment(segments, events, pseudo, baseline)


def region_labels(data: EpisodeData) -> dict[str, list[int]]:
    """Mask values of the robot and of the (manipulated) objects, for region metrics."""
    return {"robot": sorted(data.labels.robot), "object": sorted(data.labels.objects)}


__all__ = ["ObjectAlignment", "align_object", "build", "region_labels"]
