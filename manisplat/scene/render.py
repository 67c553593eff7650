"""Render a scene graph in one state from one pinhole camera: colour, optional depth, and the
alpha of each group (by default background / robot / each object; or one group per node)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from manisplat.scene.graph import Composed, SceneGraph
from manisplat.splat import rasterization


@dataclass
class GraphRender:
    """One rendered view.

    Attributes:
        rgb: [H, W, 3] colour in [0, 1] (over the background colour).
        depth: [H, W] expected z-depth (m) where the alpha exceeds 0.5, else 0; None unless asked.
        alpha: [H, W] accumulated opacity.
        group_alphas: [H, W, G] alpha of each group.
        meta: the rasterizer's projection meta (``means2d`` etc.).
        composed: the union of the nodes' Gaussians that was rendered.
    """

    rgb: torch.Tensor
    depth: torch.Tensor | None
    alpha: torch.Tensor
    group_alphas: torch.Tensor
    meta: dict
    composed: Composed


def render_graph(graph: SceneGraph, link_poses: torch.Tensor, object_poses: dict[str, torch.Tensor], *,
                 viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int, background: torch.Tensor,
                 backend: str = "auto", link_quats: torch.Tensor | None = None, depth: bool = False,
                 groups_per_node: bool = False) -> GraphRender:
    """The graph with links at ``link_poses`` [L, 4, 4] (``T_base_link``, FK order) and objects at
    ``object_poses`` (name -> [4, 4] ``T_base_obj``), seen through ``viewmat`` [4, 4] (base to
    camera) and ``K`` [3, 3] (the rasterizer's half-pixel convention), over ``background`` [3].

    ``groups_per_node``: one alpha group per node in :meth:`SceneGraph.nodes` order (for label
    images) instead of the graph's background / robot / object groups. Drawn in the graph's
    ``rasterize_mode``, with its ``eps2d``.
    """
    V = viewmat.float()
    camera_center = -(V[:3, :3].transpose(0, 1) @ V[:3, 3])
    composed = graph.compose(link_poses.float(), {k: p.float() for k, p in object_poses.items()},
                             link_quats, camera_center)
    groups, num_groups = composed.groups, graph.num_groups
    if groups_per_node:
        groups = torch.empty_like(composed.groups)
        for k, node in enumerate(graph.nodes()):
            start, end = composed.slices[node.name]
            groups[start:end] = k
        num_groups = len(graph.nodes())
    colors, alphas, meta = rasterization(
        composed.means, composed.quats, composed.scales, composed.opacities, composed.colors,
        V[None], K.float()[None], width, height, group_ids=groups, num_groups=num_groups, backend=backend,
        backgrounds=background[None], render_mode="RGB+ED" if depth else "RGB", rasterize_mode=graph.rasterize_mode,
        eps2d=graph.eps2d,
    )
    alpha = alphas[0, ..., 0]
    z = torch.where(alpha > 0.5, colors[0, ..., 3], torch.zeros_like(alpha)) if depth else None
    return GraphRender(rgb=colors[0, ..., :3], depth=z, alpha=alpha, group_alphas=meta["group_alphas"][0],
                       meta=meta, composed=composed)
