"""The scene graph's per-frame tensor work as pure functions: activating a node's parameters,
placing every moving node at its pose in one batch, and joining the parts into one union.

They take and return tensors only (the graph decides what goes in); :func:`place_scene` is
:func:`~manisplat.compilation.compilable`, so that compiled, all of a state's placement is one
graph of a few fused kernels.
"""

from __future__ import annotations

import torch

from manisplat.compilation import compilable
from manisplat.geometry import matrix_to_quat, quat_multiply
from manisplat.splat.sh import C0, spherical_harmonics

Activated = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


def _colors(means: torch.Tensor, sh0: torch.Tensor, shN: torch.Tensor | None, viewer: torch.Tensor | None,
            bands: torch.Tensor | None) -> torch.Tensor:
    """[N, 3] colours of SH coefficients seen from ``viewer`` ([3] or [N, 3], the node's frame).

    ``bands`` [K-1] weighs ``shN``'s coefficients: 1 where their band is in use, 0 where it is not
    yet. A tensor rather than a degree, so that a new band changes values, not the code compiled
    for them (a weight of 0 adds exact zeros: the colour of the bands in use). None, or no
    ``viewer``: the base colour alone."""
    if bands is not None and shN is not None and viewer is not None:
        degree = int(round((shN.shape[1] + 1) ** 0.5)) - 1
        coeffs = torch.cat([sh0[:, None], shN * bands[:, None]], dim=1)
        return (spherical_harmonics(degree, means - viewer, coeffs) + 0.5).clamp_min(0.0)
    return (0.5 + C0 * sh0).clamp_min(0.0)


def _scaled_by_light(colors: torch.Tensor, light_gain: torch.Tensor | None, light: torch.Tensor | None) -> torch.Tensor:
    """[N, 3] ``colors`` scaled by ``1 + light_gain . light`` (clamped at 0): each Gaussian's
    ``light_gain`` [N, 3] against the direction towards the light in its node's frame, ``light``
    [3] or [N, 3] (unit). Unchanged without either."""
    if light_gain is None or light is None:
        return colors
    return colors * (1.0 + (light_gain * light).sum(-1, keepdim=True)).clamp_min(0.0)


def activate(params: dict[str, torch.Tensor], camera_center: torch.Tensor | None = None,
             bands: torch.Tensor | None = None, light: torch.Tensor | None = None) -> Activated:
    """(means [N, 3], quats [N, 4], scales [N, 3], opacities [N], colours [N, 3]) of raw parameters
    (:class:`~manisplat.scene.gaussians.GaussianSet`'s), the SH bands that ``bands`` weighs
    (:meth:`~manisplat.scene.gaussians.GaussianSet.band_weights`) seen from ``camera_center`` [3]
    in the same frame (None: the base colour only), lit from the unit direction ``light`` [3] in
    that frame where the set has a ``light_gain`` (None: the colours unscaled)."""
    colors = _colors(params["means"], params["sh0"], params.get("shN"), camera_center, bands)
    colors = _scaled_by_light(colors, params.get("light_gain"), light)
    return params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]), colors


@compilable
def place_scene(background: dict[str, torch.Tensor] | None, moving: list[dict[str, torch.Tensor]], poses: torch.Tensor,
                index: torch.Tensor, camera_center: torch.Tensor | None, bands: torch.Tensor | None,
                background_bands: torch.Tensor | None, light: torch.Tensor | None = None) -> tuple[Activated | None, Activated]:
    """(the background activated in place with the SH bands ``background_bands`` weighs, or None;
    the moving nodes placed by :func:`place_nodes` with ``bands`` and ``light``): the scene's
    Gaussians at one state, before any shadow, in one function (one compiled graph)."""
    placed = place_nodes(moving, poses, index, camera_center, bands, light)
    return (None if background is None else activate(background, camera_center, background_bands)), placed


def place_nodes(params: list[dict[str, torch.Tensor]], poses: torch.Tensor, index: torch.Tensor,
                camera_center: torch.Tensor | None, bands: torch.Tensor | None,
                light: torch.Tensor | None = None) -> Activated:
    """Nodes' Gaussians activated and moved to their poses, as one union in node order.

    Args:
        params: each node's raw parameters (the same keys in every node), in local frames.
        poses: [K, 4, 4] float32 ``T_base_node`` of the K nodes.
        index: [M] int64, the node of each Gaussian of the union (M = the nodes' sizes summed).
        camera_center: [3] base frame, for the view-dependent bands (None: base colour only).
        bands: [K-1] weights of the view-dependent SH coefficients (1 in use, 0 not yet), or None.
        light: [3] unit direction towards the light, base frame: scales the colours of nodes
            with a ``light_gain`` by their Gaussians' response to it in each node's frame (None:
            unscaled).
    Returns (means, quats, scales, opacities, colours) [M, ...] in the base frame.
    """
    raw = {k: torch.cat([p[k] for p in params]) for k in params[0]}
    R, t = poses[:, :3, :3], poses[:, :3, 3]
    rotations = matrix_to_quat(R.double()).float()  # [K, 4]
    local = raw["means"]
    viewer = None
    if camera_center is not None:
        viewer = torch.einsum("kj,kji->ki", camera_center.float()[None] - t, R)[index]  # camera in each node's frame
    colors = _colors(local, raw["sh0"], raw.get("shN"), viewer, bands)
    if light is not None and "light_gain" in raw:
        towards = torch.einsum("j,kji->ki", light.float(), R)[index]  # the light in each node's frame
        colors = _scaled_by_light(colors, raw["light_gain"], towards)
    means = torch.einsum("nij,nj->ni", R[index], local) + t[index]
    quats = quat_multiply(rotations[index], raw["quats"])
    return means, quats, torch.exp(raw["scales"]), torch.sigmoid(raw["opacities"]), colors


def join(parts: list[Activated]) -> Activated:
    """The parts' Gaussians in one union (each of the five tensors concatenated in part order)."""
    return tuple(torch.cat(tensors) for tensors in zip(*parts))  # type: ignore[return-value]
