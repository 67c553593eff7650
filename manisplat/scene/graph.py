"""The scene graph: nodes of Gaussians and how they are placed at one frame.

``G(t) = G_background  U  (T_base_link(q_t) (x) G_link for each link)  U  (T_obj(t) (x) G_obj)``.
Group ids label the nodes' Gaussians in the union (0 background, 1 robot, 2 + k object k), so one
rasterization pass also returns each group's alpha.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from manisplat.scene.gaussians import GaussianSet
from manisplat.scene.shadows import DirectionalShadows
from manisplat.scene.transforms import transform_gaussians

BACKGROUND, ROBOT = 0, 1


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
        self.shadows: DirectionalShadows | None = None  # cast shadows of moving nodes on the background

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

    def compose(self, link_poses: torch.Tensor, object_poses: dict[str, torch.Tensor],
                link_quats: torch.Tensor | None = None, camera_center: torch.Tensor | None = None) -> Composed:
        """G(t) for link poses [L, 4, 4] (T_base_link, FK order) and object poses name -> [4, 4].

        ``link_quats`` [L, 4], the links' rotations as quaternions, may be passed precomputed.
        ``camera_center`` [3] (base frame) enables view-dependent colour, evaluated in each
        node's own frame.
        """
        parts, slices, start = [], {}, 0
        for node in self.nodes():
            kind, _, name = node.name.partition("/")
            pose = link_poses[self.link_index[name]] if kind == "robot" else object_poses.get(name) if kind == "object" else None
            center = None
            if camera_center is not None:
                center = camera_center if pose is None else (camera_center - pose[:3, 3]) @ pose[:3, :3].to(camera_center.dtype)
            means, quats, scales, opacities, colors = node.gaussians.activated(center)
            if kind == "robot":
                i = self.link_index[name]
                q = None if link_quats is None else link_quats[i]
                means, quats = transform_gaussians(pose, means, quats, q)
            elif kind == "object":
                means, quats = transform_gaussians(pose, means, quats)
            n = len(means)
            parts.append([means, quats, scales, opacities, colors, torch.full((n,), node.group, dtype=torch.long)])
            slices[node.name] = (start, start + n)
            start += n
        if self.shadows is not None and self.background is not None and len(parts) > 1:
            occluders = tuple(torch.cat([p[k] for p in parts[1:]]) for k in range(4))
            parts[0][4] = self.shadows.shade(parts[0][4], parts[0][0], occluders)
        cat = [torch.cat(x) for x in zip(*parts)]
        return Composed(*cat, slices=slices)
