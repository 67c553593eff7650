"""Tensor surgery for densification: grow, split, remove and reset Gaussians while keeping every
parameter, its Adam state and the strategy's running statistics consistent.

``params`` maps names to ``torch.nn.Parameter`` [N, ...] (per-Gaussian first dimension);
``optimizers`` maps the same names to optimizers that hold exactly that parameter. Activations
follow 3DGS: ``scales`` are log scales, ``opacities`` logits, ``quats`` unnormalised (w, x, y, z).
"""

from __future__ import annotations

from typing import Callable

import torch

from manisplat.splat.projection import splat_rotations

Params = dict[str, torch.nn.Parameter]
Optimizers = dict[str, torch.optim.Optimizer]


def _rebuild(
    params: Params,
    optimizers: Optimizers,
    new_param: Callable[[str, torch.Tensor], torch.Tensor],
    new_optimizer_value: Callable[[str, torch.Tensor], torch.Tensor],
    names: list[str] | None = None,
) -> None:
    """Replace each parameter by ``new_param(name, old)`` and each per-Gaussian optimizer tensor
    (Adam's ``exp_avg``, ``exp_avg_sq``) by ``new_optimizer_value(key, old)``."""
    for name in names or list(params):
        old = params[name]
        fresh = torch.nn.Parameter(new_param(name, old.data), requires_grad=old.requires_grad)
        optimizer = optimizers.get(name)
        if optimizer is not None:
            for group in optimizer.param_groups:
                for i, p in enumerate(group["params"]):
                    if p is not old:
                        continue
                    slot = optimizer.state.pop(p, {})
                    for key, value in slot.items():
                        if key != "step" and isinstance(value, torch.Tensor) and value.shape == old.shape:
                            slot[key] = new_optimizer_value(key, value)
                    group["params"][i] = fresh
                    optimizer.state[fresh] = slot
        params[name] = fresh


@torch.no_grad()
def duplicate(params: Params, optimizers: Optimizers, state: dict, mask: torch.Tensor) -> None:
    """Append a copy of every Gaussian in ``mask`` [N] (clone); the copies' Adam moments are 0."""
    sel = mask.nonzero().squeeze(-1)
    n = len(mask)
    _rebuild(params, optimizers, lambda _, p: torch.cat([p, p[sel]]), lambda _, v: torch.cat([v, torch.zeros_like(v[sel])]))
    _resize_state(state, n, lambda v: torch.cat([v, v[sel]]))


@torch.no_grad()
def split(
    params: Params, optimizers: Optimizers, state: dict, mask: torch.Tensor, *, revised_opacity: bool = False,
    generator: torch.Generator | None = None,
) -> None:
    """Replace every Gaussian in ``mask`` [N] by two samples drawn from it, scaled down 1.6x.

    With ``revised_opacity`` the two keep the original's total opacity (Rota Bulo et al. 2024):
    ``o' = 1 - sqrt(1 - o)``.
    """
    sel = mask.nonzero().squeeze(-1)
    rest = (~mask).nonzero().squeeze(-1)
    scales = torch.exp(params["scales"][sel])  # [S, 3]
    R = splat_rotations(params["quats"][sel])  # [S, 3, 3]
    noise = torch.randn(2, len(sel), 3, generator=generator, dtype=scales.dtype).to(scales.device)
    offsets = (R[None] @ (scales[None] * noise)[..., None])[..., 0]  # [2, S, 3]

    def new_param(name: str, p: torch.Tensor) -> torch.Tensor:
        if name == "means":
            children = (p[sel][None] + offsets).reshape(-1, 3)
        elif name == "scales":
            children = torch.log(scales / 1.6).repeat(2, 1)
        elif name == "opacities" and revised_opacity:
            o = torch.sigmoid(p[sel])
            children = torch.logit(1.0 - torch.sqrt(1.0 - o), eps=1e-6).repeat(2)
        else:
            children = p[sel].repeat(2, *[1] * (p.dim() - 1))
        return torch.cat([p[rest], children])

    _rebuild(params, optimizers, new_param,
             lambda _, v: torch.cat([v[rest], torch.zeros((2 * len(sel), *v.shape[1:]), dtype=v.dtype, device=v.device)]))
    _resize_state(state, len(mask), lambda v: torch.cat([v[rest], v[sel].repeat(2, *[1] * (v.dim() - 1))]))


@torch.no_grad()
def remove(params: Params, optimizers: Optimizers, state: dict, mask: torch.Tensor) -> None:
    """Delete every Gaussian in ``mask`` [N] (prune)."""
    keep = (~mask).nonzero().squeeze(-1)
    _rebuild(params, optimizers, lambda _, p: p[keep], lambda _, v: v[keep])
    _resize_state(state, len(mask), lambda v: v[keep])


@torch.no_grad()
def reset_opacity(params: Params, optimizers: Optimizers, value: float) -> None:
    """Cap every opacity at ``value`` (activated, in (0, 1)) and zero its Adam moments."""
    cap = torch.logit(torch.tensor(value)).item()
    _rebuild(params, optimizers, lambda _, p: torch.clamp(p, max=cap), lambda _, v: torch.zeros_like(v), names=["opacities"])


def _resize_state(state: dict, n: int, fn: Callable[[torch.Tensor], torch.Tensor]) -> None:
    """Apply the same row selection to the per-Gaussian running statistics (tensors [n, ...])."""
    for key, value in state.items():
        if isinstance(value, torch.Tensor) and value.dim() >= 1 and value.shape[0] == n:
            state[key] = fn(value)
