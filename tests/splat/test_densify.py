"""Densification: the tensor surgery keeps parameters, Adam state and statistics consistent; the
strategy grows where gradients are high, prunes transparent splats and resets opacity on time."""

from __future__ import annotations

import math
import re

import pytest
import torch

from manisplat.splat import DefaultStrategy, ops, rasterization
from tests.splat.scenes import random_scene


def make(n=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    params = {
        "means": torch.nn.Parameter(torch.randn(n, 3, generator=g)),
        "scales": torch.nn.Parameter(torch.log(torch.rand(n, 3, generator=g) * 0.1 + 0.01)),
        "quats": torch.nn.Parameter(torch.randn(n, 4, generator=g)),
        "opacities": torch.nn.Parameter(torch.randn(n, generator=g)),
        "colors": torch.nn.Parameter(torch.rand(n, 3, generator=g)),
    }
    optimizers = {k: torch.optim.Adam([p], lr=0.01) for k, p in params.items()}
    loss = sum((p**2).sum() for p in params.values())
    loss.backward()
    for opt in optimizers.values():
        opt.step()
    state = {"grad2d": torch.arange(n, dtype=torch.float32), "count": torch.ones(n), "scene_scale": 1.0}
    return params, optimizers, state


def adam_state(optimizers, name):
    opt = optimizers[name]
    return opt.state[opt.param_groups[0]["params"][0]]


def test_duplicate_appends_copies_with_fresh_moments():
    params, optimizers, state = make()
    before = {k: v.detach().clone() for k, v in params.items()}
    old_moment = adam_state(optimizers, "means")["exp_avg"].clone()
    mask = torch.tensor([True, False, True, False, False, False])
    ops.duplicate(params, optimizers, state, mask)
    assert len(params["means"]) == 8 and len(state["grad2d"]) == 8
    assert torch.equal(params["means"][6:], before["means"][mask])
    moment = adam_state(optimizers, "means")["exp_avg"]
    assert torch.equal(moment[:6], old_moment) and not moment[6:].any()
    assert optimizers["means"].param_groups[0]["params"][0] is params["means"]


def test_split_replaces_parents_by_two_smaller_children_near_them():
    params, optimizers, state = make()
    mask = torch.zeros(6, dtype=torch.bool)
    mask[2] = True
    parent_mean, parent_scale = params["means"][2].detach().clone(), params["scales"][2].detach().clone()
    ops.split(params, optimizers, state, mask, generator=torch.Generator().manual_seed(1))
    assert len(params["means"]) == 7
    children = params["means"][5:].detach()
    assert torch.allclose(params["scales"][5:].detach(), (parent_scale - math.log(1.6)).expand(2, 3))
    assert float((children - parent_mean).norm(dim=-1).max()) < 5 * float(torch.exp(parent_scale).max())
    assert not adam_state(optimizers, "scales")["exp_avg_sq"][5:].any()


def test_split_with_revised_opacity_keeps_total_coverage():
    params, optimizers, state = make()
    o = torch.sigmoid(params["opacities"][0]).item()
    ops.split(params, optimizers, state, torch.tensor([True] + [False] * 5), revised_opacity=True)
    child = torch.sigmoid(params["opacities"][-1]).item()
    assert abs((1 - child) ** 2 - (1 - o)) < 1e-5


def test_remove_and_reset_opacity():
    params, optimizers, state = make()
    ops.remove(params, optimizers, state, torch.tensor([True, True, False, False, False, True]))
    assert len(params["quats"]) == 3 and len(state["count"]) == 3 and state["scene_scale"] == 1.0
    ops.reset_opacity(params, optimizers, value=0.01)
    assert float(torch.sigmoid(params["opacities"].detach()).max()) <= 0.01 + 1e-6
    assert not adam_state(optimizers, "opacities")["exp_avg"].any()


def train(strategy, steps, n=200):
    torch.manual_seed(0)  # splits sample from the global generator, as gsplat's do
    scene, V, K, W, H = random_scene(n, 7, dtype=torch.float32, width=48, height=36, scale=(0.003, 0.2))
    params = {
        "means": torch.nn.Parameter(scene[0]), "quats": torch.nn.Parameter(scene[1]),
        "scales": torch.nn.Parameter(torch.log(scene[2])), "opacities": torch.nn.Parameter(torch.logit(scene[3])),
        "colors": torch.nn.Parameter(scene[4]),
    }
    optimizers = {k: torch.optim.Adam([p], lr=0.01) for k, p in params.items()}
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)
    target = torch.zeros(1, H, W, 3)
    target[:, : H // 2] = torch.tensor([1.0, 0.2, 0.1])
    history = []
    for step in range(steps):
        img, _, info = rasterization(params["means"], params["quats"], torch.exp(params["scales"]),
                                     torch.sigmoid(params["opacities"]), params["colors"], V, K, W, H)
        loss = ((img - target) ** 2).mean()
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss.backward()
        strategy.step_post_backward(params, optimizers, state, step, info)
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        history.append((step, len(params["means"]), float(loss.detach()), float(torch.sigmoid(params["opacities"].detach()).max())))
    return params, state, history


def test_strategy_grows_prunes_and_resets_on_schedule(caplog):
    strategy = DefaultStrategy(refine_start_iter=5, refine_every=10, reset_every=30, grow_grad2d=1e-4,
                               refine_stop_iter=1000, verbose=True)
    with caplog.at_level("INFO", logger="manisplat.splat.strategy"):
        params, state, history = train(strategy, 41)
    events = [tuple(int(w) for w in re.findall(r"(?:cloned|split|pruned) (\d+)", r.message)) for r in caplog.records]
    assert any(c > 0 for c, _, _ in events) and any(s > 0 for _, s, _ in events) and any(p > 0 for _, _, p in events)
    counts = [n for _, n, _, _ in history]
    assert counts[0] == 200 and max(counts) > 200  # grew at step 10 or 20
    assert len(state["grad2d"]) == len(params["means"])
    after_reset = next(h for h in history if h[0] == 30)
    assert after_reset[3] <= 2 * strategy.prune_opa + 0.02  # capped at step 30, then one Adam step
    assert history[-1][2] < history[0][2]  # still learning


def test_sanity_checks_name_the_problem():
    strategy = DefaultStrategy()
    params, optimizers, _ = make()
    del params["quats"]
    with pytest.raises(ValueError, match="quats"):
        strategy.check_sanity(params, optimizers)


def test_cap_limits_growth_to_the_strongest_gradients():
    strategy = DefaultStrategy(refine_start_iter=5, refine_every=10, reset_every=1000, grow_grad2d=1e-4,
                               refine_stop_iter=1000, cap_max=230)
    params, state, history = train(strategy, 25)
    assert max(n for _, n, _, _ in history) <= 230
    assert len(params["means"]) == 230 or any(n == 230 for _, n, _, _ in history)
