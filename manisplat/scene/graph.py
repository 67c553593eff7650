"""The scene graph: nodes of Gaussians and how they are placed at one frame.

``G(t) = G_background  U  (T_base_link(q_t) (x) G_link for each link)  U  (T_obj(t) (x) G_obj)``.
Group ids label the nodes' Gaussians in the union (0 background, 1 robot, 2 + k object k), so one
rasterization pass also returns each group's alpha.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from manisplat.compilation import compilable
from manisplat.geometry.normals import outward_normals
from manisplat.scene.gaussians import GaussianSet
from manisplat.scene.placement import Activated, join, place_scene
from manisplat.scene.shadows import DirectionalShadows, darken
from manisplat.scene.transforms import transform_gaussians
from manisplat.splat import GSPLAT_EPS2D

BACKGROUND, ROBOT = 0, 1
NORMAL_NEIGHBOURS = 12  # an object Gaussian's normal: the plane of its nearest centres (shaded receivers)


@dataclass(frozen=True)
class Node:
    """One node: its name ("background", "robot/<link>", "object/<name>"), Gaussians and group."""

    name: str
    gaussians: GaussianSet
    group: int


@dataclass
class Composed:
    """The union G(t) ready for rasterization, plus where each node's Gaussians are.

    Attributes:
        means, quats, scales, opacities, colors: [N, ...] world-frame activated parameters.
        groups: [N] int64 group id of every Gaussian.
        slices: node name -> (start, end) in the union.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    groups: torch.Tensor
    slices: dict[str, tuple[int, int]]


class SceneGraph:
    """Background, robot links (by name, in link frames) and objects (canonical frames)."""

    def __init__(self, background: GaussianSet | None, links: dict[str, GaussianSet], link_order: list[str],
                 objects: dict[str, GaussianSet]) -> None:
        unknown = set(links) - set(link_order)
        if unknown:
            raise ValueError(f"links {sorted(unknown)} are not in the robot's link order {link_order}")
        self.background = background
        self.links = links
        self.link_index = {name: i for i, name in enumerate(link_order)}
        self.objects = objects
        self.shadows: DirectionalShadows | None = None  # cast shadows of the moving nodes (DirectionalShadows.receivers)
        #: how the Gaussians are drawn, as they were fitted: "classic" or "antialiased"
        #: (:func:`manisplat.splat.rasterization`'s ``rasterize_mode``)
        self.rasterize_mode = "classic"
        #: the 2D dilation (px^2) they were fitted with (``rasterization``'s ``eps2d``; the mode's
        #: :data:`manisplat.splat.DEFAULT_EPS2D` when trained, gsplat's in twins made before 2026-12-06)
        self.eps2d = GSPLAT_EPS2D
        self._index_cache: tuple | None = None  # see _node_index
        self._normals: dict[str, torch.Tensor] = {}  # see object_normals

    @property
    def object_names(self) -> list[str]:
        return list(self.objects)

    def nodes(self) -> list[Node]:
        out = [Node("background", self.background, BACKGROUND)] if self.background is not None else []
        out += [Node(f"robot/{name}", g, ROBOT) for name, g in self.links.items()]
        out += [Node(f"object/{name}", g, 2 + k) for k, (name, g) in enumerate(self.objects.items())]
        return out

    @property
    def num_groups(self) -> int:
        return 2 + len(self.objects)

    @property
    def device(self) -> torch.device:
        """Where the Gaussians are (every node is on one device)."""
        nodes = self.nodes()
        return nodes[0].gaussians.device if nodes else torch.device("cpu")

    def to(self, device: torch.device | str) -> "SceneGraph":
        """Move every node's Gaussians (with their optimizer state) and the light to ``device``, in place."""
        for node in self.nodes():
            node.gaussians.to(device)
        if self.shadows is not None:
            self.shadows.to(device)
        return self

    def compose(self, link_poses: torch.Tensor, object_poses: dict[str, torch.Tensor],
                link_quats: torch.Tensor | None = None, camera_center: torch.Tensor | None = None) -> Composed:
        """G(t) for link poses [L, 4, 4] (T_base_link, FK order) and object poses name -> [4, 4].

        ``link_quats`` [L, 4], the links' rotations as quaternions, may be passed precomputed (the
        batched placement derives every node's from its pose).
        ``camera_center`` [3] (base frame) enables view-dependent colour, evaluated in each
        node's own frame; the moving nodes that learn a ``light_gain`` respond to the shadows'
        light (:meth:`light_direction`) in their own frames.
        """
        batched = self._compose_batched(link_poses, object_poses, camera_center)
        if batched is not None:
            return batched
        light = self.light_direction()
        parts, slices, start = [], {}, 0
        for node in self.nodes():
            kind, _, name = node.name.partition("/")
            pose = link_poses[self.link_index[name]] if kind == "robot" else object_poses.get(name) if kind == "object" else None
            center = None
            if camera_center is not None:
                center = camera_center if pose is None else (camera_center - pose[:3, 3]) @ pose[:3, :3].to(camera_center.dtype)
            towards = None if light is None or pose is None else light @ pose[:3, :3].to(light.dtype)
            means, quats, scales, opacities, colors = node.gaussians.activated(center, towards)
            if kind == "robot":
                i = self.link_index[name]
                q = None if link_quats is None else link_quats[i]
                means, quats = transform_gaussians(pose, means, quats, q)
            elif kind == "object":
                means, quats = transform_gaussians(pose, means, quats)
            n = len(means)
            parts.append([means, quats, scales, opacities, colors,
                          torch.full((n,), node.group, dtype=torch.long, device=means.device)])
            slices[node.name] = (start, start + n)
            start += n
        groups = torch.cat([part[5] for part in parts])
        dynamic = parts[1:] if self.background is not None else parts
        if not dynamic:
            return Composed(*parts[0][:5], groups, slices=slices)
        bg = tuple(parts[0][:5]) if self.background is not None else None
        moving = tuple(torch.cat([part[k] for part in dynamic]) for k in range(5))
        return Composed(*self._join_shaded(bg, moving, link_poses, object_poses), groups, slices=slices)

    def _compose_batched(self, link_poses: torch.Tensor, object_poses: dict[str, torch.Tensor],
                         camera_center: torch.Tensor | None) -> Composed | None:
        """:meth:`compose` with every link and object placed in one set of operations
        (:func:`~manisplat.scene.placement.place_nodes`: their raw parameters concatenated, each
        Gaussian's node pose gathered by an index [M] rebuilt only when a node changes size, one
        activation, one SH evaluation and one transform). The same values as placing node by
        node, with about a tenth of the operations (on a GPU the per-node version is bound by
        kernel launches), and pure tensor functions that can run compiled. None when the dynamic
        nodes differ in parameters or active SH degree (then :meth:`compose` goes node by node)."""
        nodes = self.nodes()
        dynamic = [n for n in nodes if n.name != "background"]
        if not dynamic:
            return None
        keys = set(dynamic[0].gaussians.params)
        degree = dynamic[0].gaussians.active_degree
        if any(set(n.gaussians.params) != keys or n.gaussians.active_degree != degree for n in dynamic):
            return None
        device = dynamic[0].gaussians.device
        poses = []
        for n in dynamic:
            kind, _, name = n.name.partition("/")
            poses.append(link_poses[self.link_index[name]] if kind == "robot" else object_poses[name])
        counts = tuple(len(n.gaussians) for n in dynamic)
        background = 0 if self.background is None else len(self.background)
        index, groups = self._node_index(background, counts, [n.group for n in dynamic], device)
        background_params, background_bands = (None, None) if self.background is None else \
            (self.background.params, self.background.band_weights())
        bg, moving = place_scene(background_params, [n.gaussians.params for n in dynamic], torch.stack(poses).float(),
                                 index, camera_center, dynamic[0].gaussians.band_weights(), background_bands,
                                 self.light_direction())
        slices, start = {}, 0
        if bg is not None:
            slices["background"], start = (0, background), background
        for n, count in zip(dynamic, counts):
            slices[n.name] = (start, start + count)
            start += count
        return Composed(*self._join_shaded(bg, moving, link_poses, object_poses), groups, slices=slices)

    def light_direction(self) -> torch.Tensor | None:
        """[3] the unit direction towards the shadows' light (base frame, detached: the moving
        parts' ``light_gain`` learns their response to it, the shadows place it), or None without
        shadows."""
        if self.shadows is None:
            return None
        direction = self.shadows.direction.detach()
        return direction / direction.norm().clamp_min(1e-12)

    def object_normals(self, name: str) -> torch.Tensor:
        """[N, 3] float32 the outward unit normals of object ``name``'s Gaussians in its frame
        (:func:`~manisplat.geometry.normals.outward_normals` of their centres), made when first
        needed and again when their number changes or after :meth:`refresh_normals`."""
        g = self.objects[name]
        cached = self._normals.get(name)
        if cached is None or len(cached) != len(g):
            means = g.params["means"].detach().cpu().double().numpy()
            cached = torch.as_tensor(outward_normals(means, NORMAL_NEIGHBOURS), dtype=torch.float32).to(g.device)
            self._normals[name] = cached
        return cached

    def refresh_normals(self) -> None:
        """Let the next use remake the objects' normals (their Gaussians have moved)."""
        self._normals.clear()

    def _lit(self, object_poses: dict[str, torch.Tensor], moving: int) -> torch.Tensor:
        """[moving] the cosine (clamped at 0) of each moving Gaussian's surface to the light: the
        objects' from their normals at ``object_poses``, the links' 1 (they are darkened as with
        "all" receivers)."""
        towards = self.shadows.direction / self.shadows.direction.norm().clamp_min(1e-12)
        parts = [towards.new_ones(self.link_gaussians)]
        for name in self.objects:
            R = object_poses[name][:3, :3].to(towards.dtype)
            parts.append(((self.object_normals(name) @ R.T) @ towards).clamp_min(0.0))
        lit = torch.cat(parts)
        if len(lit) != moving:
            raise ValueError(f"shaded receivers: {len(lit)} link and object Gaussians, the union moves {moving}")
        return lit

    @property
    def link_gaussians(self) -> int:
        """How many of the moving nodes' Gaussians (the links', then the objects', in a union) are the links'."""
        return sum(len(g) for g in self.links.values())

    def _join_shaded(self, background: Activated | None, moving: Activated, link_poses: torch.Tensor,
                     object_poses: dict[str, torch.Tensor]) -> Activated:
        """The background's and the moving nodes' placed Gaussians as one set, darkened where the
        moving nodes (the links at ``link_poses`` [L, 4, 4], the objects at ``object_poses``)
        shadow the light (:meth:`DirectionalShadows.occluders`, :func:`_shade_and_join`; the moving
        nodes too when the shadows fall on every receiver, the objects by their surfaces' angle to
        the light too when "shaded")."""
        if self.shadows is None or background is None:
            return _shade_and_join(background, moving, None)
        shadow = self.shadows.shadow_inputs(self.shadows.occluders(moving, link_poses, self.link_gaussians))
        receivers = self.shadows.receivers
        moving_strength = self.shadows.moving_strength_logit if receivers != "background" else None
        lit = self._lit(object_poses, len(moving[0])) if receivers == "shaded" else None
        return _shade_and_join(background, moving, shadow, moving_strength, lit)

    def _node_index(self, background: int, counts: tuple[int, ...], groups: list[int],
                    device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """(node index [M] of the dynamic nodes' Gaussians, group id [background + M] of the
        union) for ``background`` Gaussians and the dynamic nodes' ``counts``, cached until a
        count changes (built on the host, copied once)."""
        key = (background, counts, tuple(groups), str(device))
        cached = self._index_cache
        if cached is None or cached[0] != key:
            sizes = torch.tensor(counts)
            index = torch.repeat_interleave(torch.arange(len(counts)), sizes)
            group_ids = torch.cat([torch.full((background,), BACKGROUND, dtype=torch.long),
                                   torch.repeat_interleave(torch.tensor(groups, dtype=torch.long), sizes)])
            cached = (key, index.to(device), group_ids.to(device))
            self._index_cache = cached
        return cached[1], cached[2]


@compilable
def _shade_and_join(background: Activated | None, moving: Activated, shadow: tuple | None,
                    moving_strength_logit: torch.Tensor | None = None, lit: torch.Tensor | None = None) -> Activated:
    """The union of the background (its colours darkened where ``shadow``, the inputs of
    :func:`~manisplat.scene.shadows.darken` after the colours and points, says) and the moving nodes
    (darkened too, by ``moving_strength_logit`` [3] in place of the background's strength, when
    given, and by their surfaces' ``lit`` [M] when given; their positions detached)."""
    if background is None:
        return moving
    if shadow is not None:
        means, quats, scales, opacities, colors = background
        background = (means, quats, scales, opacities, darken(colors, means, *shadow))
        if moving_strength_logit is not None:
            means, quats, scales, opacities, colors = moving
            moving = (means, quats, scales, opacities,
                      darken(colors, means.detach(), moving_strength_logit, *shadow[1:], lit))
    return join([background, moving])
