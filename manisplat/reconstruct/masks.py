"""Masks for episodes recorded without segmentation.

* Robot: the robot node rendered at each frame's forward kinematics (opaque discs sampled on the
  link meshes, one label per link). With depth, a pixel whose measured surface is clearly in
  front of the link (the object, a hand) is not robot.
* Object, with depth: a plane fitted (RANSAC) to the first frame's non-robot points is the table;
  the object is the connected region above it, not robot, that holds the prompt point (or
  overlaps the prompt box most). Each later frame keeps the above-table, non-robot regions that
  overlap where the previous mask moves as the gripper implies: the object is followed.
* Object, without depth: GrabCut (OpenCV) inside the prompt box of the first frame; later frames
  come from the object's model rendered at its tracked pose (:mod:`manisplat.reconstruct.pipeline`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from tqdm import tqdm

from manisplat.align.acting_arm import Hold, carrier_track, holders_values, holds
from manisplat.align.phases import GripperEvents, gripper_events
from manisplat.align.pseudo_gt import kinematic_prior
from manisplat.reconstruct.data import EpisodeData, Labels, ReconstructionInputError
from manisplat.reconstruct.init import link_gaussians
from manisplat.scene import GaussianSet
from manisplat.scene.transforms import transform_gaussians
from manisplat.splat import rasterization

log = logging.getLogger(__name__)

OBJECT_LABEL = 200  # mask value given to the prompted object (robot links take 1, 2, ...)
# mask discs: half the size of training's, with a 0.1 px^2 screen-space dilation (training: 0.3),
# so silhouettes grow by well under a pixel (robot IoU 0.972 against MuJoCo's masks on
# shared/data; drawing the URDF meshes exactly with the painter gives 0.963)
MASK_DISC_SCALE = 0.5
MASK_EPS2D = 0.1
# a wrist camera sees its own fingers from a few centimetres: 60 000 discs over the links leave
# holes there (robot IoU 0.74-0.79 against the simulated masks of the built-in two-arm sample's
# wrist cameras); 400 000 close most of them (0.88-0.95)
RIDING_MASK_SAMPLES = 400_000


@dataclass(frozen=True)
class ObjectPrompt:
    """Where the manipulated object is in the first frame: a pixel ``point`` (u, v) or a ``box``
    (x0, y0, x1, y1), pixels, OpenCV convention (integer pixel centres)."""

    name: str = "object"
    point: tuple[float, float] | None = None
    box: tuple[int, int, int, int] | None = None

    def __post_init__(self) -> None:
        if (self.point is None) == (self.box is None):
            raise ValueError("ObjectPrompt: give exactly one of point or box")
        if self.box is not None and not (self.box[0] < self.box[2] and self.box[1] < self.box[3]):
            raise ValueError(f"ObjectPrompt: box {self.box} must be x0 < x1, y0 < y1")


@dataclass(frozen=True)
class Plane:
    """The plane ``normal . x + offset = 0`` (base frame, metres); ``normal`` is a unit vector
    pointing to the camera's side, so ``height`` is positive above the table."""

    normal: np.ndarray
    offset: float

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed distances [...] of points [..., 3] from the plane (m)."""
        return points @ self.normal + self.offset


def fit_plane_ransac(points: np.ndarray, *, threshold: float = 0.005, iterations: int = 300,
                     seed: int = 0) -> tuple[Plane, np.ndarray]:
    """The plane most points [N, 3] lie on (within ``threshold`` m), refined by least squares on its
    inliers. Returns (plane with an arbitrary normal sign, inliers [N] bool).

    Raises:
        ReconstructionInputError: fewer than 3 points or no plane with 10 % of them.
    """
    P = np.asarray(points, dtype=np.float64)
    if len(P) < 3:
        raise ReconstructionInputError(f"table plane: only {len(P)} points with depth")
    rng = np.random.default_rng(seed)
    best, best_count = None, 0
    for _ in range(iterations):
        a, b, c = P[rng.choice(len(P), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-9:  # collinear sample
            continue
        n /= norm
        inliers = np.abs((P - a) @ n) < threshold
        count = int(inliers.sum())
        if count > best_count:
            best, best_count = inliers, count
    if best is None or best_count < 0.1 * len(P):
        raise ReconstructionInputError(f"table plane: no plane holds 10 % of the {len(P)} points")
    centre = P[best].mean(0)
    normal = np.linalg.svd(P[best] - centre, full_matrices=False)[2][-1]
    inliers = np.abs((P - centre) @ normal) < threshold
    return Plane(normal, float(-normal @ centre)), inliers


def render_robot_labels(data: EpisodeData, links: list[str], *, occlusion_margin: float = 0.05,
                        samples: int = 60_000, progress: bool = True) -> tuple[torch.Tensor, dict[int, str]]:
    """Label masks [T, H, W] uint8 of the robot's links (link ``i`` of ``links`` gets ``i + 1``,
    0 elsewhere) and the label values' link names.

    The robot node is rendered: ``samples`` opaque discs on the link surfaces, placed by each
    frame's FK, rasterized with one alpha map per link; a pixel is robot where the alpha exceeds
    0.5, labelled by the link that covers it most. With depth, a pixel whose measured surface
    lies ``occlusion_margin`` m in front of the rendered (expected) depth is not robot.
    """
    W, H = data.size
    sets = link_gaussians(data.robot, links, total=samples)
    index = {name: i for i, name in enumerate(data.robot.link_names)}
    parts = []
    for label, (name, g) in enumerate(sets.items()):
        means, quats, scales, _, _ = (x.detach() for x in g.activated())
        parts.append((index[name], label, means, quats, scales))
    groups = torch.cat([torch.full((len(p[2]),), p[1], dtype=torch.int64) for p in parts])
    # each disc's colour is its link's one-hot channel: a pixel's colour is then each link's alpha
    # there (what group_ids gives, without a one-hot of every disc made again per frame)
    link_channels = torch.nn.functional.one_hot(groups, len(parts)).float()
    scales = torch.cat([p[4] for p in parts]) * MASK_DISC_SCALE
    opacities = torch.full((len(groups),), 0.99)
    masks = torch.zeros(data.n_frames, H, W, dtype=torch.uint8)
    for f in tqdm(range(data.n_frames), desc="rendering robot masks", unit="frame", leave=False, disable=not progress):
        placed = [transform_gaussians(data.link_poses[f, i], m, q, data.link_quats[f, i]) for i, _, m, q, _ in parts]
        with torch.no_grad():
            image, alpha, _ = rasterization(
                torch.cat([p[0] for p in placed]), torch.cat([p[1] for p in placed]), scales, opacities, link_channels,
                data.view_at(f)[None], data.K[None], W, H, render_mode="RGB+ED", eps2d=MASK_EPS2D)
        link_alphas, depth = image[0, ..., :-1], image[0, ..., -1]
        robot = alpha[0, ..., 0] > 0.5
        if data.depth is not None:  # a measured surface clearly in front of the link occludes it
            measured = data.depth[f]
            robot &= ~((measured > 0) & (measured < depth - occlusion_margin))
        label = link_alphas.argmax(-1).to(torch.uint8) + 1
        masks[f] = torch.where(robot, label, torch.zeros_like(label))
    return masks, {i + 1: name for i, name in enumerate(sets)}


def redraw_robot_masks(data: EpisodeData, *, progress: bool = True) -> None:
    """Draw the robot's masks of ``data`` again with its current camera and joints (after the
    camera check corrected them: masks drawn with a camera 0.3 deg / 3 mm off miss the robot's
    edges by a pixel or more), keeping the objects' pixels and the label values."""
    values = sorted(data.labels.robot)
    links = [data.labels.robot[v] for v in values]
    drawn, labels = render_robot_labels(data, links, progress=progress)
    if [labels[k] for k in sorted(labels)] != links:
        raise ValueError(f"robot labels {data.labels.robot} do not follow the drawn links {labels}")
    masks = data.masks.clone()
    masks[torch.isin(masks, torch.tensor(values, dtype=masks.dtype))] = 0
    free = (masks == 0) & (drawn > 0)
    masks[free] = drawn[free]
    data.masks = masks


def draw_view_robot_masks(view: EpisodeData, links: list[str], label_names: dict[int, str], objects: list[str], *,
                          progress: bool = True) -> None:
    """Give another camera's view (a wrist camera) masks of the robot, labelled as the reference
    camera's: its links drawn at each frame's FK (as :func:`render_robot_labels`); the
    ``objects`` are named in its labels and drawn by :func:`draw_view_object_masks`.

    Args:
        label_names: the reference camera's label values -> names (``robot/<link>`` for the
            links, which take the same values here).
    """
    drawn, drawn_links = render_robot_labels(view, links, samples=RIDING_MASK_SAMPLES, progress=progress)
    value_of = {name: value for value, name in label_names.items()}
    missing = [link for link in drawn_links.values() if f"robot/{link}" not in value_of]
    if missing:
        raise ValueError(f"links {missing} have no label in the reference camera's masks")
    masks = torch.zeros_like(drawn)
    for value, link in drawn_links.items():
        masks[drawn == value] = value_of[f"robot/{link}"]
    view.masks = masks
    view.label_names = dict(label_names)
    view.objects = list(objects)
    view.labels = Labels.from_meta(label_names, view.objects)
    view.mask_source = "drawn robot"


def draw_view_object_masks(view: EpisodeData, objects: dict[str, tuple[int, GaussianSet, np.ndarray]], *,
                           occlusion_margin: float = 0.02) -> None:
    """Add each object to a view's drawn masks (:func:`draw_view_robot_masks`): its model at its
    pose in each frame, where no robot link was drawn and, with depth, where no measured surface
    lies ``occlusion_margin`` m in front of it.

    Args:
        objects: name -> (label value, the object's Gaussians in its frame, poses [T, 4, 4]
            ``T_base_obj``), e.g. the pseudo ground truth of alignment.
    """
    W, H = view.size
    for name, (label, gaussians, poses) in objects.items():
        means, quats, scales, opacities, _ = (x.detach().cpu() for x in gaussians.activated())
        for f in range(view.n_frames):
            m, q = transform_gaussians(torch.as_tensor(poses[f], dtype=torch.float64), means, quats)
            with torch.no_grad():
                depth, alpha, _ = rasterization(m, q, scales, opacities, torch.zeros_like(means), view.view_at(f)[None],
                                                view.K[None], W, H, render_mode="ED")
            seen = (alpha[0, ..., 0] > 0.5) & (view.masks[f] == 0)
            if view.depth is not None:
                measured = view.depth[f]
                seen &= ~((measured > 0) & (measured < depth[0, ..., 0] - occlusion_margin))
            view.masks[f][seen] = label
    view.mask_source = "drawn robot, objects from their models at their poses"


def table_plane(data: EpisodeData, robot_mask: np.ndarray, frame: int = 0) -> Plane:
    """The table: the dominant plane of the non-robot points of ``frame`` (depth needed), its
    normal towards the camera."""
    depth = data.depth[frame].numpy()
    keep = (depth > 0) & (robot_mask == 0)
    points = backproject_pixels(depth, keep, data)[::7]
    plane, _ = fit_plane_ransac(points)
    camera_centre = torch.linalg.inv(data.viewmat.double())[:3, 3].numpy()
    if plane.height(camera_centre) < 0:
        plane = Plane(-plane.normal, -plane.offset)
    return plane


def object_mask_from_depth(data: EpisodeData, robot_mask: np.ndarray, plane: Plane, prompt: ObjectPrompt,
                           frame: int = 0, *, min_height: float = 0.006) -> np.ndarray:
    """The prompted object's mask [H, W] bool in ``frame``: the connected region above the table
    (by more than ``min_height`` m), not robot, holding the prompt point or overlapping its box most.

    Raises:
        ReconstructionInputError: nothing above the table there.
    """
    labels = _above_table_components(data, frame, robot_mask, plane, min_height)
    if prompt.point is not None:
        u, v = (int(round(c)) for c in prompt.point)
        H, W = labels.shape
        if not (0 <= u < W and 0 <= v < H):
            raise ReconstructionInputError(f"object point {prompt.point} is outside the {W}x{H} image")
        # the nearest above-table pixel within a few pixels (a click on the object's edge)
        r = max(3, W // 100)
        window = labels[max(v - r, 0):v + r + 1, max(u - r, 0):u + r + 1]
        ids = window[window > 0]
        if not len(ids):
            raise ReconstructionInputError(
                f"nothing above the table at object point {prompt.point} in frame {frame} (is it on the object?)")
        chosen = int(np.bincount(ids).argmax())
    else:
        x0, y0, x1, y1 = prompt.box
        window = labels[y0:y1 + 1, x0:x1 + 1]
        ids = window[window > 0]
        if not len(ids):
            raise ReconstructionInputError(f"nothing above the table in object box {prompt.box} in frame {frame}")
        chosen = int(np.bincount(ids).argmax())
    mask = labels == chosen
    log.info("object %s: %d pixels above the table in frame %d", prompt.name, int(mask.sum()), frame)
    return mask


def follow_object_masks(data: EpisodeData, robot_masks: torch.Tensor, first: np.ndarray, plane: Plane, *,
                        min_height: float = 0.006, grow: int | None = None, inside: float = 0.5) -> np.ndarray:
    """Object masks [T, H, W] bool, frame by frame.

    The first mask's points (from depth) are moved as the grippers that handle the object imply
    (:func:`object_carrier`: resting, or rigidly with the TCP while held, through handovers:
    :func:`manisplat.align.pseudo_gt.kinematic_prior`) and projected;
    that prediction, grown by ``grow`` px (default: width / 40), takes the above-table, non-robot
    regions lying at least ``inside`` within it, clipped to it: a neighbouring object touching the
    prediction is left out (if the object merged with it, the merged region's part near the
    prediction is kept). Where none qualifies (the object hidden), the prediction minus the robot
    stands.
    """
    W, H = data.size
    grow = grow or max(3, W // 40)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1, 2 * grow + 1))
    model = backproject_pixels(data.depth[0].numpy(), first, data)
    carrier = object_carrier(data, model.mean(0))
    prior, _ = kinematic_prior(np.eye(4), carrier.track, carrier.events())
    out = np.zeros((data.n_frames, H, W), dtype=bool)
    out[0] = first
    for f in range(1, data.n_frames):
        motion = prior[f] @ np.linalg.inv(prior[0])
        predicted = _splat_points(model @ motion[:3, :3].T + motion[:3, 3], data)
        robot = robot_masks[f].numpy()
        near = cv2.dilate(predicted.astype(np.uint8), kernel).astype(bool)
        labels = _above_table_components(data, f, robot, plane, min_height)
        counts = np.bincount(labels.ravel())
        within = np.bincount(labels[near].ravel(), minlength=len(counts))
        chosen = [i for i in range(1, len(counts)) if within[i] >= inside * counts[i]]
        if not chosen:  # the object merged with a neighbour: keep the merged region's part near it
            visible = int((predicted & (robot == 0)).sum())
            chosen = [i for i in range(1, len(counts)) if within[i] >= inside * visible > 0]
        out[f] = np.isin(labels, chosen) & near if chosen else predicted & (robot == 0)
    return out


@dataclass(frozen=True)
class Carrier:
    """The tool track that moves an object: ``track`` [T, 4, 4] TCP poses, the ``width`` [T] (m)
    and, where every arm that holds it records one, the ``effort`` [T] of the gripper holding it,
    and who ``holds`` it when."""

    track: np.ndarray
    width: np.ndarray
    effort: np.ndarray | None
    holds: list[Hold]

    def events(self) -> list[GripperEvents]:
        """The grasps and releases of the gripper that holds it (:func:`~manisplat.align.phases.gripper_events`)."""
        return gripper_events(self.width, effort=self.effort)


def object_carrier(data: EpisodeData, start: np.ndarray) -> Carrier:
    """The :class:`Carrier` of an object starting at ``start`` [3] (m, base/world frame). One arm:
    its own TCP and gripper. Several: the arm that handles it, carried on by each arm that takes
    it over (:func:`~manisplat.align.acting_arm.carrier_track`)."""
    efforts = {a: data.arm_gripper_effort(a) for a in data.arm_names}
    if len(data.arm_names) == 1:
        arm = data.arm_names[0]
        return Carrier(data.arm_tcp(arm).double().cpu().numpy(), data.arm_gripper(arm).double().cpu().numpy(),
                       efforts[arm], [Hold(arm, 0)])
    tcp = {a: data.arm_tcp(a).double().cpu().numpy() for a in data.arm_names}
    width = {a: data.arm_gripper(a).double().cpu().numpy() for a in data.arm_names}
    order = holds({a: T[:, :3, 3] for a, T in tcp.items()}, width, start)
    track, carried_width = carrier_track(tcp, width, order)
    effort = None
    if all(efforts[h.arm] is not None for h in order):
        effort = holders_values({h.arm: efforts[h.arm] for h in order}, order)
    return Carrier(track, carried_width, effort, order)


def _splat_points(points: np.ndarray, data: EpisodeData) -> np.ndarray:
    """[H, W] bool: pixels hit by base-frame points [M, 3], closed over one-pixel gaps."""
    W, H = data.size
    T = data.viewmat.double().numpy()
    cam = points @ T[:3, :3].T + T[:3, 3]
    cam = cam[cam[:, 2] > 1e-3]
    K = data.K_opencv.double().numpy()
    u = np.round(cam[:, 0] / cam[:, 2] * K[0, 0] + K[0, 2]).astype(int)
    v = np.round(cam[:, 1] / cam[:, 2] * K[1, 1] + K[1, 2]).astype(int)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    mask = np.zeros((H, W), np.uint8)
    mask[v[inside], u[inside]] = 1
    return cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)).astype(bool)


def object_mask_grabcut(rgb: np.ndarray, robot_mask: np.ndarray, box: tuple[int, int, int, int],
                        iterations: int = 5) -> np.ndarray:
    """The object's mask [H, W] bool inside ``box`` by GrabCut on the RGB image [H, W, 3] (no depth);
    robot pixels are marked background."""
    x0, y0, x1, y1 = box
    H, W = robot_mask.shape
    if not (0 <= x0 and 0 <= y0 and x1 < W and y1 < H):
        raise ReconstructionInputError(f"object box {box} is outside the {W}x{H} image")
    mask = np.full((H, W), cv2.GC_BGD, np.uint8)
    mask[y0:y1 + 1, x0:x1 + 1] = cv2.GC_PR_FGD
    mask[robot_mask > 0] = cv2.GC_BGD
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.grabCut(np.ascontiguousarray(rgb[..., ::-1]), mask, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    out = (mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)
    if out.sum() < 10:
        raise ReconstructionInputError(f"object box {box}: GrabCut found no object in it")
    n, labels = cv2.connectedComponents(out.astype(np.uint8))
    largest = 1 + int(np.argmax(np.bincount(labels[labels > 0])[1:])) if n > 2 else 1
    return labels == largest


def _above_table_components(data: EpisodeData, frame: int, robot_mask: np.ndarray, plane: Plane,
                            min_height: float) -> np.ndarray:
    """Connected components [H, W] int32 (0 = none) of pixels above the table and not robot."""
    depth = data.depth[frame].numpy()
    H, W = depth.shape
    keep = depth > 0
    points = backproject_pixels(depth, np.ones_like(keep), data).reshape(H, W, 3)
    above = keep & (plane.height(points) > min_height) & (robot_mask == 0)
    above = cv2.morphologyEx(above.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    return cv2.connectedComponents(above, connectivity=8)[1]


def backproject_pixels(depth: np.ndarray, keep: np.ndarray, data: EpisodeData) -> np.ndarray:
    """Base-frame points [M, 3] (float64) of the pixels where ``keep`` [H, W] (row-major order)."""
    K = data.K_opencv.double().numpy()
    rows, cols = np.nonzero(keep)
    z = depth[rows, cols].astype(np.float64)
    cam = np.stack([(cols - K[0, 2]) / K[0, 0] * z, (rows - K[1, 2]) / K[1, 1] * z, z], -1)
    T = torch.linalg.inv(data.viewmat.double()).numpy()
    return cam @ T[:3, :3].T + T[:3, 3]


def complete_masks(data: EpisodeData, links: list[str], prompts: list[ObjectPrompt], *,
                   progress: bool = True) -> bool:
    """Give an episode without masks its masks: the robot's drawn links, the prompted objects
    (the k-th prompt's object labelled ``OBJECT_LABEL + k``).

    Sets ``data.masks``, ``data.labels`` and ``data.objects``. Returns True when the objects are
    masked in the first frame only (no depth to follow them): their models at their tracked poses
    must give the other frames' (:func:`manisplat.reconstruct.pipeline.build`).

    Raises:
        ReconstructionInputError: objects are listed but no prompt says where one is; several
            prompts without a name each, or names twice; several objects without depth.
    """
    if not prompts and data.objects:
        raise ReconstructionInputError(
            f"{data.path}: no masks, and objects {data.objects} are listed: say where the object is in "
            "the first frame with --object-point U,V or --object-box X0,Y0,X1,Y1")
    names_given = [p.name for p in prompts]
    if len(set(names_given)) != len(names_given):
        raise ReconstructionInputError(f"object prompts {names_given}: each object needs its own name")
    if len(prompts) == 1 and len(data.objects) > 1 and prompts[0].name not in data.objects:
        raise ReconstructionInputError(
            f"{data.path}: objects {data.objects}: one prompt can segment only one object without masks; "
            "name each (--object-point NAME=U,V)")
    if len(prompts) > 1 and data.depth is None:
        raise ReconstructionInputError("several objects need depth to be segmented and followed")
    robot_masks, link_labels = render_robot_labels(data, links, progress=progress)
    masks = robot_masks.clone()
    names = {value: f"robot/{name}" for value, name in link_labels.items()}
    names[0] = "background"
    pending = False
    objects = []
    robot0 = robot_masks[0].numpy()
    plane = table_plane(data, robot0) if prompts and data.depth is not None else None
    for k, prompt in enumerate(prompts):
        name = data.objects[0] if len(prompts) == 1 and len(data.objects) == 1 else prompt.name
        label = OBJECT_LABEL + k
        if plane is not None:
            first = object_mask_from_depth(data, robot0, plane, prompt)
            object_masks = follow_object_masks(data, robot_masks, first, plane)
            masks[torch.from_numpy(object_masks) & (masks == 0)] = label
        else:
            if prompt.box is None:
                raise ReconstructionInputError("without depth, the object needs --object-box (GrabCut segments inside it)")
            first = object_mask_grabcut(data.rgb[0].numpy(), robot0, prompt.box)
            masks[0][torch.from_numpy(first)] = label
            pending = True
        names[label] = f"object/{name}"
        objects.append(name)
    data.objects = objects
    data.masks = masks
    data.label_names = dict(names)
    data.labels = Labels.from_meta(names, data.objects)
    data.mask_source = "drawn robot" + (", objects from depth" if plane is not None
                                        else ", object by GrabCut and its model" if prompts else "")
    return pending


__all__ = [
    "OBJECT_LABEL", "ObjectPrompt", "Plane", "backproject_pixels", "complete_masks", "draw_view_object_masks",
    "draw_view_robot_masks", "fit_plane_ransac", "follow_object_masks", "object_carrier", "object_mask_from_depth",
    "object_mask_grabcut", "redraw_robot_masks", "render_robot_labels", "table_plane",
]
