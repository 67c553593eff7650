"""Cast shadows of the moving parts on the static background, from one directional light.

A moving arm darkens the table under it, and a static background cannot explain that: on the
shared pick-and-place episode a perfect static background caps the held-out PSNR at 26.8 dB.
Here the dynamic nodes (robot links, objects) are rendered from the light's point of view with
the same rasterizer (a shadow map: alpha and expected depth). Every background Gaussian is
projected into that view; where an occluder lies in front of it, its colour is scaled by
``1 - strength * occlusion`` (strength per colour channel, learned). The light direction is
learned too (through the rasterizer's viewmat gradient); it starts from a coarse search.
The occluders' geometry is detached in the light pass: shadows tune the light, not the robot.

The links cast from their meshes where the robot has them (``casters``: points sampled over each
link's surface, :func:`surface_casters`, drawn as small opaque round Gaussians): the Gaussians
fitted to a link reach past its surface, so the shadow they cast is wider than the link's (the
gripper's came out visibly too large). The objects, which have no mesh, cast from their Gaussians.

With ``receivers="all"`` the moving nodes' Gaussians receive shadows too (their positions detached
likewise), with a strength of their own (a table and a link's surface turned elsewhere lose
different shares of their light): the gripper darkens the object under it and the arm darkens
itself, as in the images, instead of that darkening being baked into their colours where the
recording had it and missing where a new demonstration puts it.

With ``receivers="shaded"`` the objects are also lit by the angle of their surface to the light:
a face turned away loses the light's share whether anything occludes it or not, one turned
towards it keeps it where nothing does (:func:`darken`'s ``lit``, each Gaussian's outward normal
from its neighbours, :func:`~manisplat.geometry.normals.outward_normals`). An object's learned
colours then hold its surface, not the shading of the poses it was recorded in: turned to a new
yaw (augmentation; another episode of a fused twin) a face takes the light that pose gives it.
The links, which have no such normals here, keep the "all" darkening.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
import trimesh

from manisplat.compilation import compilable
from manisplat.splat import rasterization

CASTER_SPACING = 0.004  # m between the surface samples that cast the links' shadows (surface_casters)
CASTER_SIGMA = 0.5 * CASTER_SPACING  # m, standard deviation of each sample's round Gaussian: neighbours overlap
LIGHT_DISTANCE = 100.0  # m: far enough that the pinhole light camera is nearly orthographic
RECEIVERS = ("all", "background", "shaded")  # which Gaussians receive the shadows (DirectionalShadows.receivers)


@compilable
def light_camera(direction: torch.Tensor, center: torch.Tensor, extent: float, resolution: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(viewmat [4, 4], K [3, 3]) of a camera far along ``direction`` [3] (towards the light) looking
    at ``center`` [3], whose image of ``resolution`` pixels spans ``extent`` metres there.

    Built with tensor operations on ``direction``'s device and dtype, without reading a value
    back (no host-device synchronisation on a GPU).
    """
    dtype, device = direction.dtype, direction.device
    light = direction / direction.norm().clamp_min(1e-12)
    eye = center.to(dtype) + LIGHT_DISTANCE * light
    z = -light
    axes = torch.eye(4, dtype=dtype, device=device)
    # "up" is the base z axis unless the light is (nearly) vertical, then x
    up = torch.where(light[2].detach().abs() < 0.99, axes[2, :3], axes[0, :3])
    x = torch.linalg.cross(z, up)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])  # rows: camera axes in world coordinates (world-to-camera rotation)
    view = torch.cat([torch.cat([R, -(R @ eye)[:, None]], dim=1), axes[3:]])
    f = LIGHT_DISTANCE / (extent / 2) * (resolution / 2)
    # [[f, 0, c], [0, f, c], [0, 0, 1]] from the identity's rows and Python scalars: writing a
    # scalar into a GPU tensor by index would copy it from the host and wait for the GPU
    e = axes[:3, :3]
    c = resolution / 2
    K = torch.stack([f * e[0] + c * e[2], f * e[1] + c * e[2], e[2]])
    return view, K


def matched_resolution(center: torch.Tensor, extent: float, viewmat: torch.Tensor, K: torch.Tensor, *,
                       smallest: int = 64, largest: int = 768) -> int:
    """Shadow-map size (pixels a side, a multiple of 16) whose texel is about as wide as one camera
    pixel at ``center`` [3] (base frame, m), for a map spanning ``extent`` m, seen through ``viewmat``
    [4, 4] (base to camera) and ``K`` [3, 3]. A finer map adds nothing the camera can see (its cost
    grows with its area); a coarser one blurs the shadows' edges. Clamped to [smallest, largest];
    a centre less than 5 cm in front of the camera counts as 5 cm (the largest size, in practice).
    """
    V = viewmat.detach().double().cpu()
    depth = max(float(V[2, :3] @ center.detach().double().cpu() + V[2, 3]), 0.05)
    focal = 0.5 * float(K[0, 0] + K[1, 1])
    size = math.ceil(extent * focal / depth / 16) * 16
    return int(min(max(size, smallest), largest))


def direction_from_angles(azimuth: float, elevation: float) -> torch.Tensor:
    """Unit vector towards a light at ``azimuth`` (rad, from +x towards +y) and ``elevation`` (rad)."""
    return torch.tensor([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)])


class DirectionalShadows(torch.nn.Module):
    """Learned directional light: ``direction`` (towards the light) and per-channel ``strength``.

    Args:
        center, extent: where the shadow map looks (m) and how wide it is; cover the robot's reach.
        resolution: shadow-map size in pixels.
        softness: occluder depth margin (m) below which a point is not considered shadowed.
        receivers: which Gaussians the shadows darken: "background", "all" (the moving nodes
            too) or "shaded" (as "all", the objects also by their surfaces' angle to the light; see
            the module's docstring).
        casters: (points [P, 3] each in its link's frame, link index [P] in FK order) of the
            links' surfaces (:func:`surface_casters`), which then cast the links' shadows in place
            of their Gaussians; None: the links' Gaussians cast.
    """

    def __init__(self, direction: torch.Tensor, center: torch.Tensor, extent: float, *, resolution: int = 128,
                 softness: float = 0.02, strength: float = 0.4, receivers: str = "all",
                 casters: tuple[torch.Tensor, torch.Tensor] | None = None) -> None:
        if receivers not in RECEIVERS:
            raise ValueError(f"shadow receivers must be one of {RECEIVERS}, not {receivers!r}")
        super().__init__()
        self.direction = torch.nn.Parameter(direction.float() / direction.norm())
        self.strength_logit = torch.nn.Parameter(torch.full((3,), math.log(strength / (1 - strength))))
        self.moving_strength_logit = torch.nn.Parameter(self.strength_logit.detach().clone())
        self.register_buffer("center", center.float())
        self.extent, self.resolution, self.softness = float(extent), int(resolution), float(softness)
        self.receivers = receivers
        points, links = casters if casters is not None else (None, None)
        self.register_buffer("caster_points", None if points is None else points.float())
        self.register_buffer("caster_links", None if links is None else links.long())

    @property
    def strength(self) -> torch.Tensor:
        """[3] share of the light the background loses in full shadow."""
        return torch.sigmoid(self.strength_logit)

    @property
    def moving_strength(self) -> torch.Tensor | None:
        """[3] the same for the moving nodes' Gaussians (None when only the background receives)."""
        return torch.sigmoid(self.moving_strength_logit) if self.receivers != "background" else None

    @property
    def has_casters(self) -> bool:
        """Whether the links cast from their meshes' surface samples (else from their Gaussians)."""
        return self.caster_points is not None

    def occluders(self, moving: tuple[torch.Tensor, ...], link_poses: torch.Tensor,
                  link_gaussians: int) -> tuple[torch.Tensor, ...]:
        """(means, quats, scales, opacities) of what casts the shadows, from the moving nodes'
        placed Gaussians ``moving`` (those four [M, ...], the links' ``link_gaussians`` first, then
        the objects'): with casters, the links' surface samples at ``link_poses`` [L, 4, 4]
        (T_base_link, FK order) in place of the links' Gaussians."""
        if self.caster_points is None:
            return tuple(moving[:4])
        P = link_poses.detach().to(self.caster_points.dtype)[self.caster_links]
        means = torch.einsum("nij,nj->ni", P[:, :3, :3], self.caster_points) + P[:, :3, 3]
        n = len(means)
        identity = torch.cat([means.new_ones(n, 1), means.new_zeros(n, 3)], dim=1)  # built on the device: no host copy
        casters = (means, identity, means.new_full((n, 3), CASTER_SIGMA), means.new_ones(n))
        return tuple(torch.cat([c, x[link_gaussians:]]) for c, x in zip(casters, moving[:4]))

    def occlusion(self, points: torch.Tensor, occluders: tuple[torch.Tensor, ...]) -> torch.Tensor:
        """How much of the light each point [N, 3] loses to the occluders, in [0, 1]: [N].

        ``occluders`` = (means, quats, scales, opacities) of the dynamic Gaussians (world frame).
        """
        return _sample_occlusion(points, *self._shadow_map(occluders), self.softness)

    def shadow_inputs(self, occluders: tuple[torch.Tensor, ...]) -> tuple:
        """What :func:`darken` needs after the colours and points: (strength logit [3], the
        occluders' shadow map, its light camera, softness)."""
        return (self.strength_logit, *self._shadow_map(occluders), self.softness)

    def _shadow_map(self, occluders: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, ...]:
        """(alpha [R, R, 1], expected depth [R, R, 1], light viewmat [4, 4], K [3, 3]): the
        occluders rendered from the light (their geometry detached)."""
        view, K = light_camera(self.direction, self.center, self.extent, self.resolution)
        means, quats, scales, opacities = (x.detach() for x in occluders)
        depth_map, alpha_map, _ = rasterization(
            means, quats, scales, opacities, means.new_zeros(len(means), 0), view[None], K[None],
            self.resolution, self.resolution, render_mode="ED",
        )
        return alpha_map[0], depth_map[0], view, K


def surface_casters(meshes: dict[int, trimesh.Trimesh],
                    spacing: float = CASTER_SPACING) -> tuple[torch.Tensor, torch.Tensor]:
    """(points [P, 3] float32 in their links' frames, link index [P] int64) sampled about ``spacing``
    m apart over the surfaces of ``meshes`` (link index -> its mesh in its link's frame, m), the
    ``casters`` of :class:`DirectionalShadows`. ValueError without any mesh."""
    if not meshes:
        raise ValueError("no link mesh to cast shadows from")
    points, links = [], []
    for index, mesh in sorted(meshes.items()):
        count = max(int(math.ceil(mesh.area / spacing ** 2)), 1)
        p, _ = trimesh.sample.sample_surface_even(mesh, count, radius=0.5 * spacing, seed=index)
        points.append(torch.as_tensor(p, dtype=torch.float32))
        links.append(torch.full((len(p),), index, dtype=torch.long))
    return torch.cat(points), torch.cat(links)


def _sample_occlusion(points: torch.Tensor, alpha_map: torch.Tensor, depth_map: torch.Tensor, view: torch.Tensor,
                      K: torch.Tensor, softness: float) -> torch.Tensor:
    """[N] occlusion of points [N, 3] by the shadow map (alpha and expected depth [R, R, 1]) of the
    light camera ``view`` [4, 4], ``K`` [3, 3]: the map's alpha where its occluder lies in front."""
    resolution = alpha_map.shape[0]
    cam = points @ view[:3, :3].T + view[:3, 3]  # [N, 3] in the light camera
    uv = cam[:, :2] / cam[:, 2:3] * K[0, 0] + K[0, 2]
    grid = (uv / resolution * 2 - 1)[None, None]  # [1, 1, N, 2], half-pixel convention
    maps = torch.cat([alpha_map, depth_map], dim=-1).permute(2, 0, 1)[None]  # [1, 2, R, R]
    sampled = F.grid_sample(maps, grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0, :, 0]
    alpha, occluder_depth = sampled[0], sampled[1]
    in_front = torch.sigmoid((cam[:, 2] - occluder_depth - softness) / (0.5 * softness))
    return alpha * in_front


def darken(colors: torch.Tensor, points: torch.Tensor, strength_logit: torch.Tensor, alpha_map: torch.Tensor,
           depth_map: torch.Tensor, view: torch.Tensor, K: torch.Tensor, softness: float,
           lit: torch.Tensor | None = None) -> torch.Tensor:
    """Colours [N, 3] of points [N, 3] scaled by ``1 - strength * (1 - lit * (1 - occlusion))``
    (strength [3] from its logit: the light's share of a surface facing it; the occlusion from the
    shadow map, as :func:`_sample_occlusion`; ``lit`` [N] the cosine of each surface's angle to the
    light, clamped at 0; None: 1, ``1 - strength * occlusion``)."""
    occlusion = _sample_occlusion(points, alpha_map, depth_map, view, K, softness)
    unlit = occlusion if lit is None else 1.0 - lit * (1.0 - occlusion)
    return colors * (1.0 - torch.sigmoid(strength_logit) * unlit[:, None])


@torch.no_grad()
def search_direction(
    model: DirectionalShadows,
    points: torch.Tensor,
    colors: torch.Tensor,
    observations: list[tuple[tuple[torch.Tensor, ...], torch.Tensor, torch.Tensor]],
) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Best light direction over the upper hemisphere, coarse to fine, as a starting point.

    For every candidate, the occlusion of the background points [N, 3] (base colours [N, 3]) is
    predicted in each observed frame and the per-channel strength fitted in closed form to
    ``observed = colour * (1 - strength * occlusion)``; the candidate with the smallest residual
    wins. A 30 x 20 deg grid is searched first, then a 10 x 5 deg grid around its best.
    ``observations`` holds, per frame, (occluders, observed colours [N, 3], valid [N] bool).

    Returns (direction [3], strength [3], residual).
    """
    original = model.direction.detach().clone()
    coarse = [(math.radians(a), math.radians(e)) for e in (25, 45, 65, 85) for a in range(0, 360, 30)]
    best = _best_of(model, coarse, points, colors, observations)
    az, el = best[3]
    fine = [(az + math.radians(da), min(math.radians(89), el + math.radians(de)))
            for da in (-20, -10, 0, 10, 20) for de in (-10, -5, 0, 5, 10)]
    best = min(best, _best_of(model, fine, points, colors, observations), key=lambda b: b[2])
    model.direction.copy_(original)
    return best[0], best[1], best[2]


def _best_of(model, candidates, points, colors, observations):
    """(direction, strength, residual, (azimuth, elevation)) of the best candidate angles."""
    best = (None, None, math.inf, None)
    for azimuth, elevation in candidates:
        direction = direction_from_angles(azimuth, elevation).to(model.direction.device)
        model.direction.copy_(direction)
        num, den, terms = points.new_zeros(3), points.new_zeros(3), []
        for occluders, observed, valid in observations:
            occ = model.occlusion(points, occluders)[valid]
            shade = colors[valid] * occ[:, None]  # predicted darkening per unit strength
            gap = colors[valid] - observed[valid]
            num += (gap * shade).sum(0)
            den += (shade * shade).sum(0)
            terms.append((gap, shade))
        strength = (num / den.clamp_min(1e-9)).clamp(0.0, 0.95)
        residual = float(sum(((gap - strength * shade) ** 2).sum() for gap, shade in terms))
        if residual < best[2]:
            best = (direction, strength, residual, (azimuth, elevation))
    return best
