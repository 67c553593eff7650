"""Cast shadows: the light camera, which points are occluded, what they darken, and finding the light
direction."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

from manisplat.reconstruct.config import SHADOW_RECEIVERS
from manisplat.scene.gaussians import GaussianSet
from manisplat.scene.graph import SceneGraph
from manisplat.scene.shadows import (RECEIVERS, DirectionalShadows, darken, direction_from_angles, light_camera,
                                     matched_resolution, search_direction, surface_casters)


def blob(center, radius=0.05, n=200, seed=0):
    """Opaque Gaussians filling a ball: (means, quats, scales, opacities)."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g)
    means = torch.as_tensor(center, dtype=torch.float32) + radius * d / d.norm(dim=-1, keepdim=True) * torch.rand(n, 1, generator=g)
    return means, torch.tensor([1.0, 0, 0, 0]).repeat(n, 1), torch.full((n, 3), radius / 3), torch.full((n,), 0.95)


def test_light_camera_is_nearly_orthographic_along_the_light():
    direction = direction_from_angles(0.3, 1.0)
    center = torch.tensor([0.2, 0.1, 0.0])
    view, K = light_camera(direction, center, extent=1.0, resolution=100)
    for p in (center, center + 0.5 * direction):  # same ray of light -> same pixel
        cam = view[:3, :3] @ p + view[:3, 3]
        uv = cam[:2] / cam[2] * K[0, 0] + K[0, 2]
        assert torch.allclose(uv, torch.tensor([50.0, 50.0]), atol=0.6)


def test_the_shadow_map_texel_matches_a_camera_pixel_at_the_robot():
    """A texel as wide as one camera pixel where the robot is: a camera 1 m away with a 200 px focal
    length sees 5 mm a pixel, so a map spanning 0.8 m needs 160 texels; twice as far, half."""
    K = torch.tensor([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
    view = torch.eye(4)
    view[2, 3] = 1.0  # the base origin 1 m in front of the camera
    center = torch.zeros(3)
    assert matched_resolution(center, 0.8, view, K) == 160
    assert matched_resolution(center + torch.tensor([0, 0, 1.0]), 0.8, view, K) == 80
    assert matched_resolution(center, 0.81, view, K) == 176  # rounded up to whole 16-pixel tiles
    assert matched_resolution(center + torch.tensor([0, 0, 10.0]), 0.8, view, K) == 64  # the smallest
    assert matched_resolution(center, 0.8, view, 10 * K) == 768  # the largest
    assert matched_resolution(center - torch.tensor([0, 0, 2.0]), 0.8, view, K) == 768  # behind: the largest


def test_points_under_an_occluder_are_shadowed_and_others_not():
    light = direction_from_angles(0.0, math.radians(60))
    model = DirectionalShadows(light, torch.zeros(3), extent=1.2)
    ground_under = torch.tensor([0.0, 0.0, 0.0])
    occluder = blob(ground_under + 0.3 * light)
    points = torch.stack([ground_under, torch.tensor([0.4, 0.4, 0.0]), ground_under + 0.6 * light])
    occ = model.occlusion(points, occluder)
    assert occ[0] > 0.9  # behind the ball as seen from the light
    assert occ[1] < 0.01  # elsewhere on the ground
    assert occ[2] < 0.01  # between the ball and the light: lit
    shaded = darken(torch.ones(3, 3), points, *model.shadow_inputs(occluder))
    assert torch.allclose(shaded[1], torch.ones(3)) and bool((shaded[0] < 1).all())


def test_search_recovers_the_light_direction():
    true = direction_from_angles(math.radians(-45), math.radians(55))
    truth = DirectionalShadows(true, torch.zeros(3), extent=1.5, strength=0.5, resolution=64)
    xs = torch.linspace(-0.6, 0.6, 40)
    grid = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    points = torch.cat([grid, torch.zeros(len(grid), 1)], -1)
    colors = torch.full((len(points), 3), 0.8)
    observations = []
    for k, centre in enumerate(([0.1, 0.0, 0.25], [-0.2, 0.2, 0.3], [0.2, -0.3, 0.2])):
        occluder = blob(centre, radius=0.08, seed=k)
        with torch.no_grad():
            observed = darken(colors, points, *truth.shadow_inputs(occluder))
        observations.append((occluder, observed, torch.ones(len(points), dtype=torch.bool)))
    model = DirectionalShadows(torch.tensor([0.0, 0.0, 1.0]), torch.zeros(3), extent=1.5, resolution=64)
    direction, strength, _ = search_direction(model, points, colors, observations)
    angle = math.degrees(math.acos(float(torch.clamp(direction @ true, -1, 1))))
    assert angle < 6.0  # the fine grid is 10 deg in azimuth and 5 deg in elevation
    assert torch.allclose(strength, torch.full((3,), 0.5), atol=0.15)


def _node(points: torch.Tensor, sh_degree: int = 0) -> GaussianSet:
    return GaussianSet.from_points(points, torch.full_like(points, 0.8), 0.01, opacity=0.95, sh_degree=sh_degree)


@pytest.mark.parametrize("path", ["batched", "node by node"])
@pytest.mark.parametrize("receivers", ["all", "background"])
def test_the_moving_parts_receive_shadows_with_their_own_strength(path, receivers):
    """A link held above an object between it and the light darkens the object by the moving
    parts' strength (not the table's) when they receive shadows, and never an object beside it;
    with ``receivers="background"`` only the table darkens. Both ways of composing agree."""
    light = direction_from_angles(0.0, math.radians(60))
    under = torch.tensor([0.0, 0.0, 0.05])
    link_points = blob(torch.zeros(3), radius=0.05, n=300)[0]  # in the link's frame
    link_pose = torch.eye(4)
    link_pose[:3, 3] = under + 0.3 * light
    box = torch.tensor([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]])
    table = torch.tensor([[0.0, 0.0, -0.02], [0.5, 0.5, -0.02]])
    graph = SceneGraph(_node(table), {"link1": _node(link_points, sh_degree=int(path == "node by node"))},
                       ["link1"], {"shaded": _node(box), "lit": _node(box)})
    graph.shadows = DirectionalShadows(light, torch.zeros(3), extent=1.2, receivers=receivers)
    with torch.no_grad():
        graph.shadows.strength_logit.fill_(math.log(0.2 / 0.8))  # the table loses 20 %
        graph.shadows.moving_strength_logit.fill_(math.log(0.6 / 0.4))  # the moving parts 60 %
    lit_pose = torch.eye(4)
    lit_pose[:3, 3] = torch.tensor([0.4, -0.4, 0.05])
    shaded_pose = torch.eye(4)
    shaded_pose[:3, 3] = under
    with torch.no_grad():
        g = graph.compose(link_pose[None], {"shaded": shaded_pose, "lit": lit_pose})
    colour = {name: g.colors[start:end] for name, (start, end) in g.slices.items()}
    base = torch.sigmoid(torch.logit(torch.tensor(0.8)))
    assert 1 - colour["background"][0].mean() / base == pytest.approx(0.2, abs=0.03)  # under the link
    assert torch.allclose(colour["background"][1], torch.full((3,), base), atol=1e-4)
    darkened = {name: float(1 - colour[f"object/{name}"].mean() / base) for name in ("shaded", "lit")}
    if receivers == "all":
        assert darkened["shaded"] == pytest.approx(0.6, abs=0.05)
        # a surface's own Gaussians, at the shadow map's depth, sit within its softness margin
        assert darkened["lit"] < 0.1
    else:
        assert darkened == {"shaded": pytest.approx(0.0, abs=1e-6), "lit": pytest.approx(0.0, abs=1e-6)}


def _cube_surface(half: float = 0.02, n: int = 7) -> torch.Tensor:
    """Points [6 n^2, 3] on the faces of a cube of half-side ``half`` (m) centred at the origin."""
    u = torch.linspace(-half, half, n)
    a, b = (x.reshape(-1) for x in torch.meshgrid(u, u, indexing="ij"))
    faces = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = torch.zeros(len(a), 3)
            p[:, axis] = sign * half
            p[:, [k for k in range(3) if k != axis]] = torch.stack([a, b], dim=1)
            faces.append(p)
    return torch.cat(faces)


@pytest.mark.parametrize("path", ["batched", "node by node"])
def test_shaded_objects_take_the_light_their_pose_turns_them_to(path):
    """With "shaded" receivers a cube's face the light only grazes loses the moving parts' share of
    it though nothing occludes it ("all" leaves it half lit), the face towards it keeps most; turned a
    quarter round, the same Gaussians swap: the shading follows the pose, not the colours. A link
    keeps the "all" darkening."""
    light = direction_from_angles(0.0, math.radians(30))  # from +x, 30 deg up: the +-y faces grazed
    cube = _cube_surface()
    graph = SceneGraph(_node(torch.tensor([[0.0, 0.0, -0.5], [0.5, 0.5, -0.5]])),
                       {"link1": _node(blob(torch.zeros(3))[0], sh_degree=int(path == "node by node"))},
                       ["link1"], {"box": _node(cube)})
    graph.shadows = DirectionalShadows(light, torch.zeros(3), extent=1.2, receivers="shaded")
    with torch.no_grad():
        graph.shadows.moving_strength_logit.fill_(math.log(0.6 / 0.4))  # the moving parts' surfaces facing it: 60 %
    far = torch.eye(4)
    far[:3, 3] = torch.tensor([0.4, 0.4, 0.3])
    base = float(torch.sigmoid(torch.logit(torch.tensor(0.8))))
    inner = (cube[:, 2].abs() < 0.015)  # off the top and bottom edges, whose normals lean
    plus_x = inner & (cube[:, 0] > 0.019) & (cube[:, 1].abs() < 0.015)
    plus_y = inner & (cube[:, 1] > 0.019) & (cube[:, 0].abs() < 0.015)

    def darkened(turn: float, receivers: str) -> tuple[float, float, torch.Tensor]:
        graph.shadows.receivers = receivers
        pose = torch.eye(4)
        pose[:2, :2] = torch.tensor([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
        with torch.no_grad():
            g = graph.compose(far[None], {"box": pose})
        start, end = g.slices["object/box"]
        box = 1 - g.colors[start:end].mean(-1) / base
        return float(box[plus_x].mean()), float(box[plus_y].mean()), g.colors[slice(*g.slices["robot/link1"])]

    facing, grazed, link = darkened(0.0, "shaded")
    assert grazed == pytest.approx(0.6, abs=0.05) and facing < 0.3
    unshaded_facing, unshaded_grazed, unshaded_link = darkened(0.0, "all")
    assert unshaded_grazed < grazed - 0.15 and torch.allclose(link, unshaded_link, atol=1e-6)
    turned_x, turned_y, _ = darkened(-math.pi / 2, "shaded")  # +y now faces the light, +x is grazed
    assert turned_x == pytest.approx(0.6, abs=0.05) and turned_y == pytest.approx(facing, abs=0.05)


def test_surface_casters_cover_each_link_about_a_spacing_apart():
    plate = trimesh.creation.box((0.1, 0.1, 0.01))
    points, links = surface_casters({2: plate, 0: trimesh.creation.box((0.02, 0.02, 0.02))}, spacing=0.005)
    assert points.dtype == torch.float32 and links.dtype == torch.int64
    on_plate = points[links == 2]
    assert plate.area / 0.005 ** 2 * 0.6 <= len(on_plate) <= math.ceil(plate.area / 0.005 ** 2)
    assert (on_plate.abs().max(0).values <= torch.tensor([0.05, 0.05, 0.005]) + 1e-6).all()  # on the surface
    gaps = torch.cdist(on_plate, on_plate).fill_diagonal_(1.0).min(1).values
    assert float(gaps.min()) >= 0.0025 - 1e-6  # no two samples closer than half the spacing
    with pytest.raises(ValueError, match="no link mesh"):
        surface_casters({})


@pytest.mark.parametrize("path", ["batched", "node by node"])
def test_a_links_mesh_casts_its_shadow_as_wide_as_the_link_and_moves_with_it(path):
    """A link whose fitted Gaussians reach 6 cm past its 2 cm mesh (as a soft fit reaches past a
    surface): with its mesh as the caster the table 4 cm beside the link's shadow stays lit, where
    the Gaussians darkened it; under the link it is dark either way; the shadow follows the link's
    pose; the objects keep casting from their Gaussians."""
    light = torch.tensor([0.0, 0.0, 1.0])  # straight above: a shadow right under its caster
    xs = torch.linspace(-0.2, 0.2, 81)
    table = torch.stack([xs, torch.zeros_like(xs), torch.full_like(xs, -0.02)], -1)  # a line on the table
    wide = blob(torch.zeros(3), radius=0.08, n=400)[0]  # the link's Gaussians, in its frame
    box = torch.tensor([[0.0, 0.0, 0.0]])
    graph = SceneGraph(_node(table), {"link1": _node(wide, sh_degree=int(path == "node by node"))}, ["link1"],
                       {"box": _node(box)})
    mesh = trimesh.creation.box((0.02, 0.02, 0.02))

    def darkened(casters, link_x: float) -> torch.Tensor:
        graph.shadows = DirectionalShadows(light, torch.zeros(3), extent=0.8, resolution=160,
                                           casters=None if casters is None else surface_casters({0: casters}))
        with torch.no_grad():
            graph.shadows.strength_logit.fill_(0.0)  # half the light
            pose = torch.eye(4)
            pose[:3, 3] = torch.tensor([link_x, 0.0, 0.2])
            box_pose = torch.eye(4)
            box_pose[:3, 3] = torch.tensor([0.0, 0.3, 0.1])  # beside the line: its shadow falls elsewhere
            g = graph.compose(pose[None], {"box": box_pose})
        start, end = g.slices["background"]
        return 1 - g.colors[start:end].mean(-1) / g.colors[start:end].max()

    def at(x: float) -> int:
        return int(torch.argmin((xs - x).abs()))

    with_gaussians, with_mesh = darkened(None, 0.0), darkened(mesh, 0.0)
    assert with_mesh[at(0.0)] > 0.45 and with_gaussians[at(0.0)] > 0.45  # under the link
    assert with_gaussians[at(0.04)] > 0.2  # the Gaussians' shadow reaches past the link
    assert with_mesh[at(0.04)] < 0.01  # the mesh's does not
    moved = darkened(mesh, 0.1)
    assert moved[at(0.1)] > 0.45 and moved[at(0.0)] < 0.01  # the shadow follows the link
    assert graph.shadows.occluders(
        (box, torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.01), torch.ones(1)), torch.eye(4)[None], 0,
    )[0].shape[0] == len(graph.shadows.caster_points) + 1  # the objects cast from their Gaussians


def test_unknown_receivers_are_refused():
    with pytest.raises(ValueError, match="receivers"):
        DirectionalShadows(torch.tensor([0.0, 0.0, 1.0]), torch.zeros(3), extent=1.0, receivers="robot")


def test_the_cli_offers_the_shadow_models_receivers():
    assert SHADOW_RECEIVERS == RECEIVERS  # the CLI's torch-free copy
