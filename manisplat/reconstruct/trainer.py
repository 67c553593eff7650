"""Joint optimisation of the scene graph, the object poses and the light (the ManiSplat loss).

``L = L_render + l_app * L_app + l_mask * L_mask + l_pose * L_pose`` (paper: all weights 1):
L_render is (1 - s) L1 + s D-SSIM on the frame (s = 0.2); L_app the same over the dynamic
pixels (robot and objects in the ground-truth mask); L_mask the L1 between the rendered alpha of
the dynamic nodes and that mask; L_pose the objects' squared SE(3) distance to the pseudo ground
truth (:mod:`manisplat.reconstruct.poses`). Each iteration renders one training frame, drawn
from the plan's distinct states. Every node densifies with its own strategy state.
"""

from __future__ import annotations

import logging
import math
import random
import time
from dataclasses import asdict
from pathlib import Path

import kornia
import numpy as np
import torch
from tqdm import tqdm

from manisplat.reconstruct.config import TrainConfig
from manisplat.reconstruct.data import EpisodeData
from manisplat.reconstruct.metrics import psnr
from manisplat.reconstruct.plan import Plan
from manisplat.reconstruct.poses import ObjectTrajectory
from manisplat.scene import ROBOT, GaussianSet, SceneGraph
from manisplat.scene.render import render_graph
from manisplat.scene.shadows import DirectionalShadows, search_direction
from manisplat.geometry import se3_exp
from manisplat.splat import DefaultStrategy
from manisplat.splat.backends import resolve_backend

log = logging.getLogger(__name__)


class Reconstruction:
    """The trainable twin of one episode: scene graph, object trajectories, light, camera."""

    def __init__(self, data: EpisodeData, plan: Plan, graph: SceneGraph, trajectories: dict[str, ObjectTrajectory],
                 config: TrainConfig) -> None:
        self.data, self.plan, self.graph, self.trajectories, self.config = data, plan, graph, trajectories, config
        self.step = 0
        self.pose_optimizer = (
            torch.optim.Adam([t.xi for t in trajectories.values()], lr=5e-4) if trajectories else None
        )
        self.camera_delta = torch.nn.Parameter(torch.zeros(6, dtype=torch.float64))
        # colour behind everything (sky, depth holes): learned, starts mid-grey
        self.background_logit = torch.nn.Parameter(torch.zeros(3))
        self.background_optimizer = torch.optim.Adam([self.background_logit], lr=1e-2)
        self.camera_optimizer = torch.optim.Adam([self.camera_delta], lr=1e-4) if config.refine_camera else None
        self.light_optimizer: torch.optim.Optimizer | None = None
        self.scene_scale = graph.background.scene_scale if graph.background is not None else 1.0
        self.strategies = {
            node.name: DefaultStrategy(
                refine_start_iter=config.refine_start, refine_every=config.refine_every,
                refine_stop_iter=int(config.iters * config.refine_stop_fraction), reset_every=10 ** 9,
                grow_grad2d=config.grow_grad2d, cap_max=int(config.growth_cap * len(node.gaussians)),
            )
            for node in graph.nodes()
        }
        for node in graph.nodes():
            node.gaussians.strategy_state = self.strategies[node.name].initialize_state(self.scene_scale)
        self._dynamic = torch.tensor(sorted(set(data.labels.robot) | set(data.labels.objects)), dtype=torch.uint8)
        self._rng = random.Random(config.seed)
        torch.manual_seed(config.seed)

    # ------------------------------------------------------------------ rendering
    def object_poses(self, frame: int, evaluation: dict[str, np.ndarray] | None = None) -> dict[str, torch.Tensor]:
        if evaluation is not None:
            return {name: torch.as_tensor(p[frame]).float() for name, p in evaluation.items()}
        return {name: traj.pose(frame).float() for name, traj in self.trajectories.items()}

    def viewmat(self) -> torch.Tensor:
        V = self.data.viewmat
        if self.camera_optimizer is None:
            return V
        return (se3_exp(self.camera_delta) @ V.double()).float()

    def render(self, frame: int, evaluation: dict[str, np.ndarray] | None = None):
        """(image [H, W, 3], alpha [H, W], dynamic alpha [H, W], meta, composed) at ``frame``."""
        return self.render_state(self.data.link_poses[frame], self.object_poses(frame, evaluation),
                                 self.data.link_quats[frame])

    def render_state(self, link_poses: torch.Tensor, object_poses: dict[str, torch.Tensor],
                     link_quats: torch.Tensor | None = None):
        """The twin in any state: link poses [L, 4, 4] (``T_base_link``, FK order, e.g. FK of new
        joint angles) and object poses name -> [4, 4] ``T_base_obj``, seen from the episode's camera.

        Returns (image [H, W, 3], alpha [H, W], dynamic alpha [H, W], meta, composed); ``meta``
        holds ``group_alphas`` [1, H, W, groups] (0 background, 1 robot, 2 + k object k).
        """
        W, H = self.data.size
        view = render_graph(self.graph, link_poses, object_poses, viewmat=self.viewmat(), K=self.data.K, width=W,
                            height=H, background=torch.sigmoid(self.background_logit), backend=self.config.backend,
                            link_quats=link_quats)
        dynamic = view.group_alphas[..., ROBOT:].sum(-1)
        return view.rgb, view.alpha, dynamic, view.meta, view.composed

    # ------------------------------------------------------------------ losses
    def losses(self, frame: int) -> tuple[dict[str, torch.Tensor], dict, object]:
        c = self.config
        image, _, dynamic_alpha, meta, composed = self.render(frame)
        target = self.data.image(frame)
        l1, ssim_map = _error_maps(image, target)  # computed once for the render and appearance terms
        terms = {"render": _photometric(l1, ssim_map, None, c.ssim_weight)}
        if self.data.masks is not None:
            dyn_mask = torch.isin(self.data.masks[frame], self._dynamic)
            if bool(dyn_mask.any()):
                terms["app"] = c.lambda_app * _photometric(l1, ssim_map, dyn_mask, c.ssim_weight)
            terms["mask"] = c.lambda_mask * (dynamic_alpha - dyn_mask.float()).abs().mean()
        if self.trajectories:
            terms["pose"] = c.lambda_pose * sum(t.pose_loss(frame) for t in self.trajectories.values()).float()
        return terms, meta, composed

    # ------------------------------------------------------------------ training
    def train(self, *, progress: bool = True, callback=None) -> None:
        """Run the remaining iterations (``config.iters - step``)."""
        c = self.config
        states = self.plan.distinct_train_states or self.plan.train_frames
        resolve_backend(c.backend, self.data.rgb.device)  # a first build of the C++ rasterizer logs before the bar
        bar = tqdm(total=c.iters, initial=self.step, desc="reconstructing", unit="it", disable=not progress)
        last_psnr, mean_loss = math.nan, math.nan  # mean_loss: over about the last 50 frames
        while self.step < c.iters:
            if c.shadows and self.graph.shadows is None and self.step >= c.shadow_start and self.data.masks is not None:
                self.start_shadows()
            degree = min(c.sh_degree, self.step // max(c.sh_every, 1))
            for node in self.graph.nodes():
                node.gaussians.active_degree = min(degree, node.gaussians.sh_degree)
            frame = self._rng.choice(states)
            terms, meta, composed = self.losses(frame)
            loss = sum(terms.values())
            meta["means2d"].retain_grad()
            loss.backward()
            self._densify_and_step(meta, composed)
            self.step += 1
            if self.step % c.eval_every == 0 or self.step == c.iters:
                last_psnr = self.quick_psnr()
            value = float(loss.detach())
            mean_loss = value if math.isnan(mean_loss) else 0.98 * mean_loss + 0.02 * value
            bar.set_postfix(_progress_fields(mean_loss, last_psnr, sum(len(n.gaussians) for n in self.graph.nodes())))
            bar.update(1)
            if callback is not None:
                callback(self)
        bar.close()

    def _densify_and_step(self, meta: dict, composed) -> None:
        grad = meta["means2d"].grad
        for node in self.graph.nodes():
            start, end = composed.slices[node.name]
            g = node.gaussians
            if self.config.densify:
                info = {"means2d_grad": grad[:, start:end], "radii": meta["radii"][:, start:end],
                        "width": meta["width"], "height": meta["height"], "n_cameras": meta["n_cameras"]}
                self.strategies[node.name].step_post_backward(g.params, g.optimizers, g.strategy_state, self.step, info)
            g.step()
        for opt in (self.pose_optimizer, self.camera_optimizer, self.light_optimizer, self.background_optimizer):
            if opt is not None:
                opt.step()
                opt.zero_grad(set_to_none=True)
        if self.graph.background is not None:  # position learning rate decays 100x over training
            frac = min(self.step / max(self.config.iters, 1), 1.0)
            base = 1.6e-4 * self.scene_scale
            for node in self.graph.nodes():
                node.gaussians.set_learning_rate("means", base * 0.01 ** frac)

    @torch.no_grad()
    def quick_psnr(self, frames: int = 3) -> float:
        """Mean PSNR over a few held-out frames, with poses interpolated as in evaluation."""
        evaluation = self.evaluation_poses()
        chosen = self.plan.test_frames[:: max(1, len(self.plan.test_frames) // frames)][:frames]
        return float(np.mean([psnr(self.render(f, evaluation)[0], self.data.image(f)) for f in chosen]))

    def evaluation_poses(self) -> dict[str, np.ndarray]:
        return {name: t.evaluation_poses(self.plan.train_frames) for name, t in self.trajectories.items()}

    # ------------------------------------------------------------------ shadows
    @torch.no_grad()
    def start_shadows(self, frames: int = 8) -> None:
        """Search the light direction on the current background, then learn it with the rest."""
        d = self.data
        links = d.link_poses[:, :, :3, 3].reshape(-1, 3)
        center = links.mean(0)
        extent = 2.2 * float((links - center).norm(dim=-1).max())
        model = DirectionalShadows(torch.tensor([0.0, 0.0, 1.0]), center, extent)
        points, _, _, _, colors = (x.detach() for x in self.graph.background.activated())
        V, K = self.viewmat().detach(), d.K
        cam = points @ V[:3, :3].T + V[:3, 3]
        uv = cam[:, :2] / cam[:, 2:3] * torch.stack([K[0, 0], K[1, 1]]) + torch.stack([K[0, 2], K[1, 2]])
        W, H = d.size
        px = uv.floor().long()
        inside = (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H) & (cam[:, 2] > 0)
        px[:, 0].clamp_(0, W - 1)
        px[:, 1].clamp_(0, H - 1)
        observations = []
        chosen = self.plan.train_frames[:: max(1, len(self.plan.train_frames) // frames)]
        for f in chosen:
            composed = self.graph.compose(d.link_poses[f], self.object_poses(f))
            start, end = composed.slices["background"]
            occluders = tuple(torch.cat([x[:start], x[end:]]) for x in
                              (composed.means, composed.quats, composed.scales, composed.opacities))
            valid = inside & d.region(f, d.labels.static)[px[:, 1], px[:, 0]]
            if d.depth is not None:
                valid &= (d.depth[f][px[:, 1], px[:, 0]] - cam[:, 2]).abs() < 0.02
            observations.append((occluders, d.image(f)[px[:, 1], px[:, 0]], valid))
        t0 = time.perf_counter()
        direction, strength, _ = search_direction(model, points, colors, observations)
        model.direction.copy_(direction)
        model.strength_logit.copy_(torch.logit(strength.clamp(0.05, 0.95)))
        self.graph.shadows = model
        self.light_optimizer = torch.optim.Adam(
            [{"params": [model.direction], "lr": 1e-3}, {"params": [model.strength_logit], "lr": 1e-2}]
        )
        log.info("shadows: light direction %s, strength %s (searched in %.1f s)",
                 np.round(direction.numpy(), 3).tolist(), np.round(strength.numpy(), 3).tolist(),
                 time.perf_counter() - t0)

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        nodes = {}
        for node in self.graph.nodes():
            g = node.gaussians
            nodes[node.name] = {
                "params": {k: v.detach() for k, v in g.params.items()},
                "optimizer": g.optimizer.state_dict(),
                "strategy_state": g.strategy_state,
            }
        return {
            "step": self.step, "config": asdict(self.config), "nodes": nodes,
            "trajectories": {k: t.state_dict() for k, t in self.trajectories.items()},
            "pose_optimizer": self.pose_optimizer.state_dict() if self.pose_optimizer else None,
            "camera_delta": self.camera_delta.detach(),
            "background": self.background_logit.detach(), "background_optimizer": self.background_optimizer.state_dict(),
            "shadows": self.graph.shadows.state_dict() if self.graph.shadows is not None else None,
            "shadow_geometry": (self.graph.shadows.extent, self.graph.shadows.resolution) if self.graph.shadows else None,
            "light_optimizer": self.light_optimizer.state_dict() if self.light_optimizer else None,
            "rng": self._rng.getstate(), "torch_rng": torch.get_rng_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        for node in self.graph.nodes():
            saved = state["nodes"][node.name]
            g = GaussianSet(saved["params"], scene_scale=node.gaussians.scene_scale)
            g.optimizer.load_state_dict(saved["optimizer"])
            g.active_degree = node.gaussians.active_degree
            g.strategy_state = saved["strategy_state"]
            _replace_node(self.graph, node.name, g)
        for name, t in self.trajectories.items():
            t.load_state_dict(state["trajectories"][name])
        if self.pose_optimizer is not None:
            self.pose_optimizer = torch.optim.Adam([t.xi for t in self.trajectories.values()], lr=5e-4)
            self.pose_optimizer.load_state_dict(state["pose_optimizer"])
        with torch.no_grad():
            self.camera_delta.copy_(state["camera_delta"])
            self.background_logit.copy_(state["background"])
        self.background_optimizer.load_state_dict(state["background_optimizer"])
        if state["shadows"] is not None:
            extent, resolution = state["shadow_geometry"]
            sh = DirectionalShadows(torch.tensor([0.0, 0.0, 1.0]), torch.zeros(3), extent, resolution=resolution)
            sh.load_state_dict(state["shadows"])
            self.graph.shadows = sh
            self.light_optimizer = torch.optim.Adam(
                [{"params": [sh.direction], "lr": 1e-3}, {"params": [sh.strength_logit], "lr": 1e-2}]
            )
            self.light_optimizer.load_state_dict(state["light_optimizer"])
        self.step = state["step"]
        self._rng.setstate(state["rng"])
        torch.set_rng_state(state["torch_rng"])

    def save_checkpoint(self, path: Path) -> None:
        tmp = path.with_name(path.name + ".tmp")
        torch.save(self.state_dict(), tmp)
        tmp.replace(path)


def _progress_fields(mean_loss: float, held_out_psnr: float, gaussians: int) -> dict[str, str | int]:
    """The progress bar's fields; the held-out PSNR (dB) appears once it has been measured."""
    fields: dict[str, str | int] = {"loss": f"{mean_loss:.4f}"}
    if not math.isnan(held_out_psnr):
        fields["held-out PSNR"] = f"{held_out_psnr:.2f} dB"
    fields["gaussians"] = gaussians
    return fields


def _replace_node(graph: SceneGraph, name: str, g: GaussianSet) -> None:
    kind, _, rest = name.partition("/")
    if kind == "background":
        graph.background = g
    elif kind == "robot":
        graph.links[rest] = g
    else:
        graph.objects[rest] = g


def _error_maps(image: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel L1 [H, W] and SSIM [H, W] (11 x 11 Gaussian window, kornia) of [H, W, 3] images."""
    l1 = (image - target).abs().mean(-1)
    ssim_map = kornia.metrics.ssim(image.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], 11)[0].mean(0)
    return l1, ssim_map


def _photometric(l1: torch.Tensor, ssim_map: torch.Tensor, region: torch.Tensor | None, ssim_weight: float) -> torch.Tensor:
    """(1 - w) L1 + w (1 - SSIM) over the image, or averaged over ``region`` [H, W] pixels."""
    if region is None:
        return (1 - ssim_weight) * l1.mean() + ssim_weight * (1 - ssim_map.mean())
    return (1 - ssim_weight) * l1[region].mean() + ssim_weight * (1 - ssim_map[region].mean())
