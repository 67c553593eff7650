"""The moving parts' response to the light (``--light-response``): each link or object Gaussian's
colour scaled by ``1 + light_gain . l``, ``l`` the direction towards the shadows' light in the
part's own frame, so a part turned under the light changes its shading while the cameras that ride
on it see it from one direction."""

from __future__ import annotations

import math

import pytest
import torch

from manisplat.episode.synthetic import write_sample_episode
from manisplat.reconstruct.cli import main as reconstruct_main
from manisplat.reconstruct.config import resolve_light_response
from manisplat.scene.gaussians import GaussianSet
from manisplat.scene.graph import SceneGraph
from manisplat.scene.shadows import DirectionalShadows
from manisplat.twin import Twin

BASE = 0.6  # every Gaussian's colour before the light's gain


@pytest.fixture(scope="module")
def pick(tmp_path_factory):
    return write_sample_episode(tmp_path_factory.mktemp("pick") / "ep", frames=16, width=64, height=48)


def _part(points: torch.Tensor, sh_degree: int = 0) -> GaussianSet:
    return GaussianSet.from_points(points, torch.full_like(points, BASE), 0.01, opacity=0.95, sh_degree=sh_degree)


def _turned_about_x(angle: float) -> torch.Tensor:
    T = torch.eye(4)
    c, s = math.cos(angle), math.sin(angle)
    T[1:3, 1:3] = torch.tensor([[c, -s], [s, c]])
    T[:3, 3] = torch.tensor([0.3, 0.0, 0.2])
    return T


def _scene(sh_degree: int = 0, table: bool = True) -> SceneGraph:
    """A table (or none: no shadow map to draw), one link and one box, both parts learning a
    response to the light (light from straight above, shadows on the background only: the parts'
    colours are their gain alone)."""
    points = torch.tensor([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]])
    background = _part(torch.tensor([[0.0, 0.0, -0.02], [0.5, 0.5, -0.02]])) if table else None
    graph = SceneGraph(background, {"link1": _part(points, sh_degree)}, ["link1"], {"box": _part(points)})
    for part in (graph.links["link1"], graph.objects["box"]):
        part.learn_light_response()
    graph.shadows = DirectionalShadows(torch.tensor([0.0, 0.0, 1.0]), torch.zeros(3), extent=1.2,
                                       receivers="background")
    return graph


@pytest.mark.parametrize("path", ["batched", "node by node"])
def test_a_part_turned_under_the_light_takes_its_gain_and_the_table_does_not(path):
    """A gain along the part's z axis brightens it by half with its z towards the light, darkens it
    by half turned upside down, and leaves it as it was turned sideways; the table keeps its colour.
    Both ways of composing agree (SH bands on the link alone make the graph go node by node)."""
    graph = _scene(sh_degree=int(path == "node by node"))
    with torch.no_grad():
        for part in (graph.links["link1"], graph.objects["box"]):
            part.params["light_gain"][:] = torch.tensor([0.0, 0.0, 0.5])
    for angle, factor in ((0.0, 1.5), (math.pi, 0.5), (math.pi / 2, 1.0)):
        T = _turned_about_x(angle)
        with torch.no_grad():
            g = graph.compose(T[None], {"box": T})
        for name in ("robot/link1", "object/box"):
            start, end = g.slices[name]
            torch.testing.assert_close(g.colors[start:end], torch.full((end - start, 3), BASE * factor),
                                       atol=1e-4, rtol=0, msg=f"{path} {name} at {angle:.2f} rad")
        start, end = g.slices["background"]
        torch.testing.assert_close(g.colors[start:end], torch.full((end - start, 3), BASE), atol=1e-4, rtol=0)


def test_without_the_shadows_light_the_gain_has_nothing_to_follow():
    graph = _scene()
    with torch.no_grad():
        graph.links["link1"].params["light_gain"][:] = torch.tensor([0.0, 0.0, 0.5])
    graph.shadows = None
    g = graph.compose(torch.eye(4)[None], {"box": torch.eye(4)})
    torch.testing.assert_close(g.colors, torch.full_like(g.colors, BASE), atol=1e-4, rtol=0)


def test_the_gain_is_learned_from_a_part_whose_shading_follows_its_turn():
    """Seen in four orientations whose shading is ``1 + 0.4 l_z``, a part fits it with the gain
    (one colour cannot: its error stays at the shading's spread)."""
    angles = (0.0, math.pi / 3, 2 * math.pi / 3, math.pi)
    targets = [BASE * (1 + 0.4 * math.cos(a)) for a in angles]  # l_z in the part's frame is cos(angle)

    def fitted_error(respond: bool) -> float:
        graph = _scene(table=False)
        link = graph.links["link1"]
        if not respond:
            link.params.pop("light_gain")
        for name in ("sh0", "light_gain"):
            link.set_learning_rate(name, 1e-2)  # a few steps' worth: the test fits, not the schedule
        for _ in range(120):
            for angle, target in zip(angles, targets):
                T = _turned_about_x(angle)
                g = graph.compose(T[None], {"box": T})
                start, end = g.slices["robot/link1"]
                ((g.colors[start:end] - target) ** 2).mean().backward()
            link.optimizer.step()
            link.optimizer.zero_grad(set_to_none=True)
        with torch.no_grad():
            errors = []
            for angle, target in zip(angles, targets):
                T = _turned_about_x(angle)
                g = graph.compose(T[None], {"box": T})
                start, end = g.slices["robot/link1"]
                errors.append(float((g.colors[start:end] - target).abs().max()))
        return max(errors)

    assert fitted_error(respond=True) < 0.01
    assert fitted_error(respond=False) > 0.1


def test_the_cli_trains_the_parts_response_and_the_twin_keeps_it(pick, tmp_path):
    out = tmp_path / "twin"
    assert reconstruct_main([str(pick), "--out", str(out), "--iters", "400", "--light-response", "on", "-q"]) == 0
    twin = Twin.load(out)
    moving = [*twin.graph.links.values(), *twin.graph.objects.values()]
    assert moving and all("light_gain" in g.params for g in moving)
    assert "light_gain" not in twin.graph.background.params
    learned = torch.cat([g.params["light_gain"].detach().abs().amax(-1) for g in moving])
    assert float(learned.max()) > 0  # the shadows started at iteration 300: the gains moved after


def test_light_response_without_shadows_is_refused(pick, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        reconstruct_main([str(pick), "--out", str(tmp_path / "twin"), "--light-response", "on", "--no-shadows"])
    assert exit_info.value.code == 2
    assert "--light-response on follows the shadows' light" in capsys.readouterr().err


def test_auto_learns_the_response_where_a_camera_rides_on_an_arm():
    assert resolve_light_response("auto", riding=True) is True
    assert resolve_light_response("auto", riding=False) is False
    assert resolve_light_response("on", riding=False) is True and resolve_light_response("off", riding=True) is False
    with pytest.raises(ValueError, match="unknown light response 'sometimes'"):
        resolve_light_response("sometimes", riding=True)
