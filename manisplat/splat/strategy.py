"""Adaptive density control of 3D Gaussian splatting as a strategy object (clone, split, prune,
opacity reset), with gsplat's ``DefaultStrategy`` defaults and hooks.

Written for this project because PyPI gsplat 1.5.3's opacity reset never fires (its condition
``step % reset_every == 0 & step > 0`` is a chained comparison that is always False; fixed
upstream after that release). The strategy keeps no hidden state: its running statistics live
in the ``state`` dict the caller holds.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch

from manisplat.compilation import compilable
from manisplat.splat import ops

log = logging.getLogger(__name__)


@dataclass
class DefaultStrategy:
    """Clone small Gaussians and split large ones where the image-space gradient is high; prune
    transparent and oversized ones; reset opacities periodically.

    Attributes (gsplat's defaults):
        prune_opa: 0.005. Prune Gaussians whose opacity falls below this.
        grow_grad2d: 0.0002. Densify where the mean image-space gradient of the centre (in
            half-image units, as gsplat) exceeds this.
        grow_scale3d: 0.01. Below this largest scale (x scene_scale) clone, above it split.
        grow_scale2d: 0.05. Also split when the screen radius exceeds this fraction of the image
            (only before ``refine_scale2d_stop_iter``).
        prune_scale3d: 0.1. After the first opacity reset, prune Gaussians larger than this
            (x scene_scale).
        prune_scale2d: 0.15. Prune screen radii above this fraction (before ``refine_scale2d_stop_iter``).
        refine_scale2d_stop_iter: 0. Screen-size rules off by default, as in 3DGS.
        refine_start_iter: 500. First step that refines.
        refine_stop_iter: 15000. Last step that refines.
        reset_every: 3000. Opacity reset period (steps); opacities are capped at 2 x prune_opa.
        refine_every: 100. Refinement period (steps).
        pause_refine_after_reset: 0. Steps without refinement after a reset.
        revised_opacity: False. Splits keep the parent's total opacity (Rota Bulo et al. 2024).
        cap_max: None. Grow no further than this many Gaussians; when growth would pass it, the
            candidates with the highest gradients grow first (as MCMC's cap).
        verbose: False. Log every refinement.
    """

    prune_opa: float = 0.005
    grow_grad2d: float = 0.0002
    grow_scale3d: float = 0.01
    grow_scale2d: float = 0.05
    prune_scale3d: float = 0.1
    prune_scale2d: float = 0.15
    refine_scale2d_stop_iter: int = 0
    refine_start_iter: int = 500
    refine_stop_iter: int = 15_000
    reset_every: int = 3000
    refine_every: int = 100
    pause_refine_after_reset: int = 0
    revised_opacity: bool = False
    cap_max: int | None = None
    verbose: bool = False

    REQUIRED = ("means", "scales", "quats", "opacities")

    def initialize_state(self, scene_scale: float = 1.0) -> dict:
        """A fresh state dict; per-Gaussian statistics are created on the first step."""
        return {"grad2d": None, "count": None, "radii": None, "scene_scale": float(scene_scale)}

    def check_sanity(self, params: ops.Params, optimizers: ops.Optimizers) -> None:
        """Raise ValueError unless params and optimizers fit this strategy."""
        missing = [k for k in self.REQUIRED if k not in params]
        if missing:
            raise ValueError(f"densification needs parameters {list(self.REQUIRED)}; missing {missing}")
        if set(params) != set(optimizers):
            raise ValueError(f"one optimizer per parameter is needed: params {sorted(params)}, optimizers {sorted(optimizers)}")
        n = {len(p) for p in params.values()}
        if len(n) != 1:
            raise ValueError(f"all parameters must have the same number of Gaussians, got {sorted(n)}")

    def step_pre_backward(self, params, optimizers, state: dict, step: int, info: dict) -> None:
        """Call after rendering, before ``loss.backward()``: keeps the 2D-mean gradient."""
        info["means2d"].retain_grad()

    def step_post_backward(self, params, optimizers, state: dict, step: int, info: dict) -> None:
        """Call after ``loss.backward()`` (before or after ``optimizer.step()``): accumulates the
        statistics and, on refinement steps, clones, splits, prunes and resets.

        ``info`` is the rasterization meta; instead of "means2d" it may carry "means2d_grad"
        [C, N, 2] (this node's slice when several were rendered together) with "radii" to match.
        """
        if step >= self.refine_stop_iter:
            return
        self._accumulate(params, state, info)
        if (
            step > self.refine_start_iter
            and step % self.refine_every == 0
            and step % self.reset_every >= self.pause_refine_after_reset
        ):
            n_clone, n_split = self._grow(params, optimizers, state, step)
            n_prune = self._prune(params, optimizers, state, step)
            if self.verbose:
                log.info("step %d: cloned %d, split %d, pruned %d; now %d Gaussians",
                         step, n_clone, n_split, n_prune, len(params["means"]))
            for key in ("grad2d", "count", "radii"):
                state[key].zero_()
        if step > 0 and step % self.reset_every == 0:
            ops.reset_opacity(params, optimizers, value=2.0 * self.prune_opa)

    @torch.no_grad()
    def _accumulate(self, params, state: dict, info: dict) -> None:
        """Add this step's image-space gradient norms [N], visibility counts [N] and (with the
        screen-size rules) largest radii [N] to ``state``, with masked element-wise sums: no
        index lists whose length would have to be read back from a GPU (no synchronisation)."""
        if "grad2d_norms" in info:  # computed for a larger union this node is a slice of
            norms, visible = info["grad2d_norms"], info["visible"]
        else:
            # "means2d_grad" lets a caller that rendered several nodes in one pass hand each node its slice
            grads = info["means2d_grad"] if "means2d_grad" in info else info["means2d"].grad  # [C, N, 2]
            if grads is None:
                raise RuntimeError("means2d has no gradient: call step_pre_backward before loss.backward()")
            norms, visible = gradient_statistics(grads, info["radii"], info["width"], info["height"])
        n = len(params["means"])
        if state["grad2d"] is None or len(state["grad2d"]) != n:
            device = norms.device
            state["grad2d"] = torch.zeros(n, device=device)
            state["count"] = torch.zeros(n, device=device)
            state["radii"] = torch.zeros(n, device=device)
        state["grad2d"] += norms
        state["count"] += visible
        if self.refine_scale2d_stop_iter > 0:
            seen = (info["radii"] > 0).all(dim=-1)  # [C, N]
            r = info["radii"].max(dim=-1).values.float() / max(info["width"], info["height"])  # [C, N]
            r = torch.where(seen, r, torch.zeros_like(r)).amax(0)
            torch.maximum(state["radii"], r, out=state["radii"])

    @torch.no_grad()
    def _grow(self, params, optimizers, state: dict, step: int) -> tuple[int, int]:
        grads = state["grad2d"] / state["count"].clamp_min(1)
        high = grads > self.grow_grad2d
        if self.cap_max is not None:
            room = max(self.cap_max - len(grads), 0)  # every clone or split adds one Gaussian
            if int(high.sum()) > room:
                keep = torch.zeros_like(high)
                if room:
                    keep[torch.topk(torch.where(high, grads, torch.zeros_like(grads)), room).indices] = True
                high = keep
        small = torch.exp(params["scales"]).max(dim=-1).values <= self.grow_scale3d * state["scene_scale"]
        clone = high & small
        split = high & ~small
        if step < self.refine_scale2d_stop_iter:
            split |= state["radii"] > self.grow_scale2d
        n_clone, n_split = int(clone.sum()), int(split.sum())
        if n_clone:
            ops.duplicate(params, optimizers, state, clone)
        split = torch.cat([split, torch.zeros(n_clone, dtype=torch.bool, device=split.device)])  # not the clones
        if n_split:
            ops.split(params, optimizers, state, split, revised_opacity=self.revised_opacity)
        return n_clone, n_split

    @torch.no_grad()
    def _prune(self, params, optimizers, state: dict, step: int) -> int:
        prune = torch.sigmoid(params["opacities"].flatten()) < self.prune_opa
        if step > self.reset_every:
            too_big = torch.exp(params["scales"]).max(dim=-1).values > self.prune_scale3d * state["scene_scale"]
            if step < self.refine_scale2d_stop_iter:
                too_big |= state["radii"] > self.prune_scale2d
            prune |= too_big
        n = int(prune.sum())
        if n:
            ops.remove(params, optimizers, state, prune)
        return n


@compilable
@torch.no_grad()
def gradient_statistics(grads: torch.Tensor, radii: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(summed image-space gradient norm [N], number of cameras that saw each Gaussian [N] float)
    of one rasterization's ``means2d`` gradient [C, N, 2] and radii [C, N, 2] (pixels), the
    gradient in half-image units as gsplat measures it; 0 where a Gaussian was not seen."""
    C = grads.shape[0]
    visible = (radii > 0).all(dim=-1)  # [C, N]
    norms = torch.hypot(grads[..., 0] * (width / 2.0 * C), grads[..., 1] * (height / 2.0 * C)).float()  # [C, N]
    return torch.where(visible, norms, torch.zeros_like(norms)).sum(0), visible.sum(0, dtype=torch.float32)
