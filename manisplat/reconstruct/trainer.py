"""Joint optimisation of the scene graph, the object poses and the light (the ManiSplat loss,
:mod:`manisplat.reconstruct.loss`). Each iteration renders one training frame of one camera,
drawn from the plan's distinct states of every camera (one image an iteration, whatever the
number of cameras). Every node densifies with its own strategy state.
"""

from __future__ import annotations

import collections
import logging
import math
import random
import time
import warnings
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from manisplat.cli_args import shown_value
from manisplat.compilation import compilation
from manisplat.reconstruct.chroma import subsample_chroma, subsampled
from manisplat.reconstruct.config import (RASTERIZE_MODES, SHADOW_CASTERS, SHARE_ALIKE, TrainConfig, resolve_compile,
                                          resolve_device)
from manisplat.reconstruct.data import EpisodeData
from manisplat.reconstruct.exposure import FrameExposure
from manisplat.reconstruct.extrinsic import ExtrinsicCorrection
from manisplat.reconstruct.rig_check import RigCheck
from manisplat.reconstruct.sensor import clipped
from manisplat.reconstruct.loss import frame_loss
from manisplat.reconstruct.metrics import psnr
from manisplat.reconstruct.plan import Plan
from manisplat.reconstruct.poses import ObjectTrajectory, TwistAdam
from manisplat.reconstruct.tensor_ops import TensorOpCounter
from manisplat.robot import link_meshes
from manisplat.scene import ROBOT, GaussianSet, Node, SceneGraph
from manisplat.scene.render import render_graph
from manisplat.scene.shadows import DirectionalShadows, matched_resolution, search_direction, surface_casters
from manisplat.geometry import se3_exp
from manisplat.splat import DEFAULT_EPS2D, GSPLAT_EPS2D, DefaultStrategy, value_checks
from manisplat.splat.strategy import gradient_statistics
from manisplat.splat.backends import resolve_backend

log = logging.getLogger(__name__)


class TrainingDiverged(FloatingPointError):
    """The loss became NaN or infinite (checked every ``log_every`` iterations)."""


class Reconstruction:
    """The trainable twin of one episode: scene graph, object trajectories, light, cameras.

    ``data`` is the reference camera's view of the episode (fixed: it anchors the scene, its
    extrinsic may be refined); ``views`` the other cameras' (e.g. wrist cameras riding on link6),
    each with its own images, masks, exposure and per-frame pose, trained at once.

    Everything it trains and reads in the iteration lives on ``config.device`` (resolved by
    :func:`~manisplat.reconstruct.config.resolve_device`): the episode's tensors (moved after
    alignment, images kept uint8), the Gaussians, the trajectories, the light. One Adam
    optimizer updates every parameter (one group per parameter kind and learning rate across all
    nodes, plus the background colour, camera and light): one fused step per iteration;
    the object poses have their own (:class:`~manisplat.reconstruct.poses.TwistAdam`: only the
    rendered frame's twists step).
    """

    def __init__(self, data: EpisodeData, plan: Plan, graph: SceneGraph, trajectories: dict[str, ObjectTrajectory],
                 config: TrainConfig, views: dict[str, EpisodeData] | None = None) -> None:
        self.device = torch.device(resolve_device(config.device, config.backend))
        #: the torch.compile mode of the iteration's tensor functions, None: eager (:mod:`manisplat.compilation`)
        self.compiled = resolve_compile(config.compile, self.device.type, config.iters)
        self.data, self.plan, self.graph, self.trajectories, self.config = data.to(self.device), plan, graph, trajectories, config
        #: camera name -> its view of the episode, the reference camera (``data``) first
        self.views = {data.camera_name: self.data, **{name: v.to(self.device) for name, v in (views or {}).items()}}
        if len(self.views) != 1 + len(views or {}):
            raise ValueError(f"camera {data.camera_name} is both the reference and another view")
        if config.rasterize_mode not in RASTERIZE_MODES:
            raise ValueError(f"rasterize_mode must be one of {RASTERIZE_MODES}, not {config.rasterize_mode!r}")
        self.graph.rasterize_mode = config.rasterize_mode
        self.graph.eps2d = DEFAULT_EPS2D[config.rasterize_mode]
        self.graph.to(self.device)
        for t in trajectories.values():
            t.to(self.device)
        self.step = 0
        self.camera_delta = torch.nn.Parameter(torch.zeros(6, dtype=torch.float64, device=self.device))
        # colour behind everything (sky, depth holes): learned, starts mid-grey
        self.background_logit = torch.nn.Parameter(torch.zeros(3, device=self.device))
        #: camera name -> its per-frame exposure gains (None without ``config.exposure``)
        self.exposures = ({name: FrameExposure(v.n_frames, plan.train_frames, self.device) for name, v in self.views.items()}
                          if config.exposure else None)
        #: what the robot's depth said about the camera extrinsic (set by the pipeline; None: not checked)
        self.extrinsic: ExtrinsicCorrection | None = None
        #: what the robots' depth said about the other arms' bases and the riding cameras (None: one
        #: arm and one camera, or not checked)
        self.rig: RigCheck | None = None
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
        self.optimizer = self._make_optimizer()
        self.pose_optimizer = TwistAdam(trajectories)
        #: object -> {trained frame: its trained neighbours' twists} for the smoothness loss
        self._neighbours = {name: t.trained_neighbours(plan.train_frames) for name, t in trajectories.items()}
        # per camera, [T, H, W] bool: the dynamic pixels of every frame, computed once (no label look-ups per iteration)
        self._dynamic_masks = {name: _dynamic_pixels(v) for name, v in self.views.items()}
        self._valid = {name: v.valid.float() if v.valid is not None else None for name, v in self.views.items()}
        #: per camera, how its recording subsampled the colour (None: not known to)
        self._chroma = {name: subsampled(v.chroma_subsampling) for name, v in self.views.items()}
        self._rng = random.Random(config.seed)
        torch.manual_seed(config.seed)
        self._loss_average: torch.Tensor | None = None  # running mean of the loss, on the device
        #: the latest :meth:`quick_psnr` of training (dB; every ``eval_every`` iterations), NaN before the first
        self.held_out_psnr = math.nan

    def _make_optimizer(self) -> torch.optim.Adam:
        """One Adam over every trained tensor: the Gaussians of all nodes, one group per parameter
        kind and learning-rate scale (:meth:`_lr_scale`: the objects' positions apart; the rate from
        the first node's own optimizer, the positions' from the schedule of :meth:`_step_and_densify`
        when there is a background), then the background colour, the
        camera correction (with ``refine_camera``) and the light (once shadows start). Fused
        kernels on every device (on the CPU 2.4-3.5x faster a step than ``foreach``: README, the
        CPU iteration)."""
        groups: dict[tuple[str, float], dict] = {}
        for node in self.graph.nodes():
            for group in node.gaussians.optimizer.param_groups:
                name = group["name"]
                scale = self._lr_scale(node, name)
                key = (name, scale)
                groups.setdefault(key, {"params": [], "lr": float(group["lr"]) * scale, "name": name,
                                        "eps": group["eps"], "lr_scale": scale})
                groups[key]["params"] += group["params"]
        param_groups = list(groups.values())
        self._schedule_means(param_groups)
        param_groups.append({"params": [self.background_logit], "lr": 1e-2, "name": "background"})
        if self.config.refine_camera:
            param_groups.append({"params": [self.camera_delta], "lr": 1e-4, "name": "camera"})
        if self.graph.shadows is not None:
            param_groups += self._light_groups(self.graph.shadows)
        optimizer = torch.optim.Adam(param_groups, fused=True)
        for node in self.graph.nodes():
            node.gaussians.use_optimizer(optimizer)
        return optimizer

    def _lr_scale(self, node: Node, parameter: str) -> float:
        """The factor on the learning rate of ``node``'s ``parameter``: the objects' positions at
        ``config.object_position_rate`` of the scene's, everything else 1."""
        return self.config.object_position_rate if parameter == "means" and node.group > ROBOT else 1.0

    @property
    def exposure(self) -> FrameExposure | None:
        """The reference camera's per-frame exposure gains (None without ``config.exposure``)."""
        return None if self.exposures is None else self.exposures[self.data.camera_name]

    def view(self, camera: str | None) -> EpisodeData:
        """The view of ``camera`` (None: the reference camera)."""
        return self.data if camera is None else self.views[camera]

    @property
    def light_optimizer(self) -> torch.optim.Optimizer | None:
        """The optimizer that updates the light (the shared one), or None before shadows start."""
        names = {g["name"] for g in self.optimizer.param_groups}
        return self.optimizer if "light_direction" in names else None

    @staticmethod
    def _light_groups(model: DirectionalShadows) -> list[dict]:
        groups = [{"params": [model.direction], "lr": 1e-3, "name": "light_direction"},
                  {"params": [model.strength_logit], "lr": 1e-2, "name": "light_strength"}]
        if model.receivers != "background":
            groups.append({"params": [model.moving_strength_logit], "lr": 1e-2, "name": "light_strength_moving"})
        return groups

    # ------------------------------------------------------------------ rendering
    def object_poses(self, frame: int, evaluation: dict[str, np.ndarray] | None = None) -> dict[str, torch.Tensor]:
        """name -> T_base_obj [4, 4] float32 on the device: trained, or from ``evaluation`` poses."""
        if evaluation is not None:
            return {name: torch.as_tensor(p[frame]).float().to(self.device) for name, p in evaluation.items()}
        return {name: traj.pose(frame).float() for name, traj in self.trajectories.items()}

    def viewmat(self) -> torch.Tensor:
        """[4, 4] float32 base-to-camera, with the learned correction when ``refine_camera``."""
        V = self.data.viewmat
        if not self.config.refine_camera:
            return V
        return (se3_exp(self.camera_delta) @ V.double()).float()

    def render(self, frame: int, evaluation: dict[str, np.ndarray] | None = None, camera: str | None = None, *,
               recorded: bool = True):
        """(image [H, W, 3], alpha [H, W], dynamic alpha [H, W], meta, composed) at ``frame`` seen by
        ``camera`` (None: the reference camera), the image in the frame's exposure and white
        balance (with ``exposure``) and, ``recorded``, with its colour subsampled as the
        camera's recording was (:mod:`manisplat.reconstruct.chroma`)."""
        image, *rest = self._render_scene(frame, evaluation, camera)
        name = self.view(camera).camera_name
        if self.exposures is not None:
            image = image * self.exposures[name].gains_of(frame)
        return (self.as_recorded(image, camera) if recorded else image, *rest)

    def as_recorded(self, image: torch.Tensor, camera: str | None = None) -> torch.Tensor:
        """A render [H, W, 3] of ``camera`` (None: the reference camera) with its colour subsampled
        as the camera's recording was; unchanged where the recording's is not known to be."""
        stored = self._chroma[self.view(camera).camera_name]
        return image if stored is None else subsample_chroma(image, stored)

    def _render_scene(self, frame: int, evaluation: dict[str, np.ndarray] | None = None, camera: str | None = None):
        """:meth:`render_state` at ``frame``'s recorded state (as ``camera`` saw it, at its own
        time): the scene without the frame's exposure."""
        view = self.view(camera)
        viewmat = None if camera is None or camera == self.data.camera_name else view.view_at(frame)
        return self.render_state(view.link_poses[frame], self.object_poses(frame, evaluation), view.link_quats[frame],
                                 camera=camera, viewmat=viewmat)

    def render_state(self, link_poses: torch.Tensor, object_poses: dict[str, torch.Tensor],
                     link_quats: torch.Tensor | None = None, *, camera: str | None = None,
                     viewmat: torch.Tensor | None = None):
        """The twin in any state: link poses [L, 4, 4] (``T_base_link``, FK order, e.g. FK of new
        joint angles) and object poses name -> [4, 4] ``T_base_obj``, seen by ``camera`` (None: the
        reference camera, with its refinement) from ``viewmat`` [4, 4] (None: the reference
        camera's; a riding camera's pose depends on the state: pass it).

        Returns (image [H, W, 3], alpha [H, W], dynamic alpha [H, W], meta, composed); ``meta``
        holds ``group_alphas`` [1, H, W, groups] (0 background, 1 robot, 2 + k object k).
        """
        data = self.view(camera)
        if viewmat is None and data is not self.data:
            raise ValueError(f"camera {camera} is not the reference camera: pass its viewmat")
        W, H = data.size
        link_poses = link_poses.to(self.device)
        link_quats = None if link_quats is None else link_quats.to(self.device)
        object_poses = {k: v.to(self.device) for k, v in object_poses.items()}
        viewmat = self.viewmat() if viewmat is None else viewmat.to(self.device)
        view = render_graph(self.graph, link_poses, object_poses, viewmat=viewmat, K=data.K, width=W,
                            height=H, background=torch.sigmoid(self.background_logit), backend=self.config.backend,
                            link_quats=link_quats)
        dynamic = view.group_alphas[..., ROBOT:].sum(-1)
        return view.rgb, view.alpha, dynamic, view.meta, view.composed

    # ------------------------------------------------------------------ losses
    def losses(self, frame: int, camera: str | None = None) -> tuple[torch.Tensor, dict, object]:
        """(the loss [] of training frame ``frame`` of ``camera`` (None: the reference camera), the
        rasterizer's meta, the composed union); the frame's exposure gains are fitted and kept on the
        way (:func:`frame_loss`)."""
        c = self.config
        view = self.view(camera)
        name = view.camera_name
        image, _, dynamic_alpha, meta, composed = self._render_scene(frame, camera=camera)
        masks = self._dynamic_masks[name]
        dynamic = masks[frame] if masks is not None else None
        exposure = self.exposures[name].fit_inputs(frame) if self.exposures is not None else None
        twists = [t.twist(frame) for t in self.trajectories.values()]
        loss, gains = frame_loss(image, dynamic_alpha, view.rgb[frame], dynamic, self._valid[name], exposure, twists,
                                 (c.ssim_weight, c.lambda_app, c.lambda_mask, c.lambda_pose), self._chroma[name])
        smoothness = [t.smoothness_loss(frame, self._neighbours[k][frame]) for k, t in self.trajectories.items()
                      if c.lambda_smooth and frame in self._neighbours[k]]
        if smoothness:
            loss = loss + c.lambda_smooth * sum(smoothness).float()
        if gains is not None:
            self.exposures[name].keep(frame, gains)
        return loss, meta, composed

    # ------------------------------------------------------------------ training
    def train(self, *, progress: bool = True, callback=None) -> None:
        """Run the remaining iterations (``config.iters - step``).

        The iteration reads nothing back from the device (no host-device synchronisation), except
        on densification steps (the Gaussians change number), every ``log_every`` iterations (the
        running loss for the progress bar, checked to be finite) and every ``eval_every`` (the
        held-out PSNR). The rasterizer's input value checks are off inside the iteration (on a
        GPU each is a synchronisation; on the CPU they took 6 % of the iteration); the loss
        check stands in for them.
        """
        c = self.config
        states = self._train_states()
        resolve_backend(c.backend, self.device)  # a first build of the C++ rasterizer logs before the bar
        bar = tqdm(total=c.iters, initial=self.step, desc="reconstructing", unit="it", disable=not progress)
        mean_loss = math.nan  # over about the last 50 frames
        with compilation(self.compiled):  # entered once: see manisplat.compilation
            while self.step < c.iters:
                self._iteration(states)
                if self.step % max(c.log_every, 1) == 0 or self.step % c.eval_every == 0 or self.step == c.iters:
                    mean_loss = self._read_loss()
                with compilation(None):  # evaluation and callbacks run eagerly
                    if self.step % c.eval_every == 0 or self.step == c.iters:
                        self.held_out_psnr = self.quick_psnr()
                    if callback is not None:
                        callback(self)
                bar.set_postfix(_progress_fields(mean_loss, self.held_out_psnr, sum(len(n.gaussians) for n in self.graph.nodes())),
                                refresh=False)
                bar.update(1)
        bar.close()
        if self.exposure is not None and self.step >= c.iters:
            self.refit_exposure()

    def _train_states(self) -> TrainStates:
        """The (camera, frame) pairs an iteration draws from: every camera's distinct states, else
        every training frame (None: the reference camera), drawn by ``config.fixed_camera_share``."""
        frames = self.plan.distinct_train_states or self.plan.train_frames
        cameras = [None, *(name for name in self.views if name != self.data.camera_name)]
        riding = {camera for camera in cameras if self.view(camera).riding}
        return TrainStates([(camera, f) for camera in cameras for f in frames], riding, self.config.fixed_camera_share)

    def _iteration(self, states: TrainStates) -> None:
        """One training iteration on a (camera, frame) drawn from ``states`` (the light is searched
        first, eagerly, when its start is reached)."""
        c = self.config
        if c.shadows and self.graph.shadows is None and self.step >= c.shadow_start and self.data.masks is not None:
            with compilation(None):
                self.start_shadows()
        degree = min(c.sh_degree, self.step // max(c.sh_every, 1))
        for node in self.graph.nodes():
            node.gaussians.active_degree = min(degree, node.gaussians.sh_degree)
        camera, frame = states.draw(self._rng)
        with value_checks(False):
            loss, meta, composed = self.losses(frame, camera)
            self._before_backward(meta)
            loss.backward()
            self._weigh_fixed_camera(camera)
            self._step_and_densify(frame, meta, composed)
        self._average_loss(loss.detach())
        self.step += 1

    def _weigh_fixed_camera(self, camera: str | None) -> None:
        """Scale the gradients a fixed camera's frame gave the objects' Gaussians by
        ``config.fixed_camera_weight`` (a riding camera's frames, the other nodes, the poses and the
        image-space statistics of densification: as they are)."""
        weight = self.config.fixed_camera_weight
        if weight == 1.0 or self.view(camera).riding:
            return
        for gaussians in self.graph.objects.values():
            for parameter in gaussians.params.values():
                if parameter.grad is not None:
                    parameter.grad.mul_(weight)

    def _average_loss(self, loss: torch.Tensor) -> None:
        """Fold this iteration's loss into the running mean (weight 0.02, about 50 frames), on the device."""
        if self._loss_average is None:
            self._loss_average = loss.clone()
        else:
            self._loss_average.mul_(0.98).add_(loss, alpha=0.02)

    def _read_loss(self) -> float:
        """The running mean of the loss (a synchronisation); raise :class:`TrainingDiverged` if not finite."""
        value = float(self._loss_average) if self._loss_average is not None else math.nan
        if not math.isfinite(value):
            raise TrainingDiverged(f"the loss is {value} at iteration {self.step} (training diverged); "
                                   "try another --seed or smaller learning rates")
        return value

    def _before_backward(self, meta: dict) -> None:
        """The strategies' pre-backward hook (keeps the 2D means' gradient for densification)."""
        if self.config.densify:
            for node in self.graph.nodes():
                g = node.gaussians
                self.strategies[node.name].step_pre_backward(g.params, g.optimizers, g.strategy_state, self.step, meta)

    def _step_and_densify(self, frame: int, meta: dict, composed) -> None:
        """One optimizer step over everything (the object poses: the twists ``frame`` used), then
        densification (gsplat's order: a node that grows or is pruned still takes this
        iteration's update)."""
        for node in self.graph.nodes():  # before its first band, shN is weighed 0 and takes no step:
            g = node.gaussians           # its Adam moments start with its first band's gradient
            if g.active_degree == 0 and "shN" in g.params:
                g.params["shN"].grad = None
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.pose_optimizer.step(frame, scale=self._pose_rate())
        if self.config.densify and any(self.step < s.refine_stop_iter for s in self.strategies.values()):
            # the image-space statistics of the whole union at once, each node given its slice
            norms, visible = gradient_statistics(meta["means2d"].grad, meta["radii"], meta["width"], meta["height"])
            for node in self.graph.nodes():
                start, end = composed.slices[node.name]
                g = node.gaussians
                info = {"grad2d_norms": norms[start:end], "visible": visible[start:end],
                        "radii": meta["radii"][:, start:end], "width": meta["width"], "height": meta["height"],
                        "n_cameras": meta["n_cameras"]}
                self.strategies[node.name].step_post_backward(g.params, g.optimizers, g.strategy_state, self.step, info)
        self._schedule_means(self.optimizer.param_groups)
        if self.step % max(self.config.refine_every, 1) == 0:
            self.graph.refresh_normals()  # the objects' Gaussians have moved: remake their normals when next used

    def _schedule_means(self, param_groups: list[dict]) -> None:
        """Set the positions' groups to the schedule's rate at the current step (times each group's
        ``lr_scale``) when there is a background; without one they keep their own rate."""
        if self.graph.background is None:
            return
        lr = self._means_lr()
        for group in param_groups:
            if group["name"] == "means":
                group["lr"] = lr * group["lr_scale"]

    def _means_lr(self) -> float:
        """The positions' learning rate at the current step: 1.6e-4 x scene scale, decaying
        exponentially from 1x at the start to 0.01x at the end of training."""
        return 1.6e-4 * self.scene_scale * self._decay(0.01)

    def _pose_rate(self) -> float:
        """The object poses' learning-rate factor at the current step: 1 at the start,
        ``config.pose_rate_final`` at the end (exponential; 0.1 by default)."""
        return self._decay(self.config.pose_rate_final)

    def _decay(self, final: float) -> float:
        """An exponential schedule's factor at the current step: 1 at the start, ``final`` at the end."""
        return final ** min(self.step / max(self.config.iters, 1), 1.0)

    @torch.no_grad()
    def refit_exposure(self) -> None:
        """Fit every training frame's exposure gains again on the twin as it is now. During
        training each frame's gains were fitted whenever it was drawn, against the render of that
        moment; a held-out frame's gains, interpolated between two of them, would carry their
        difference (2 % frame to frame on the clean shared pick-and-place). Every camera's."""
        for name, view in self.views.items():
            camera = None if view is self.data else name
            for frame in self.plan.train_frames:
                image = self._render_scene(frame, camera=camera)[0]
                self.exposures[name].fit(frame, image, view.image(frame), self._static_region(frame, name))

    def _static_region(self, frame: int, camera: str) -> torch.Tensor | None:
        """[H, W] float 0/1: the pixels of ``camera``'s frame that are neither robot nor object and
        that the recording covers (None: every pixel)."""
        masks, valid = self._dynamic_masks[camera], self._valid[camera]
        static = None if masks is None else 1 - masks[frame].float()
        if valid is not None:
            static = valid if static is None else static * valid
        return static

    @torch.no_grad()
    def quick_psnr(self, frames: int = 3) -> float:
        """Mean PSNR over a few held-out frames, with poses interpolated as in evaluation."""
        evaluation = self.evaluation_poses()
        chosen = self.plan.test_frames[:: max(1, len(self.plan.test_frames) // frames)][:frames]
        return float(np.mean([psnr(self.render(f, evaluation)[0], self.data.image(f), self.data.valid)
                              for f in chosen]))

    def evaluation_poses(self) -> dict[str, np.ndarray]:
        """name -> [T, 4, 4] float64 (numpy, host) poses of every frame, held-out ones interpolated."""
        return {name: t.evaluation_poses(self.plan.train_frames) for name, t in self.trajectories.items()}

    # ------------------------------------------------------------------ shadows
    @torch.no_grad()
    def start_shadows(self, frames: int = 8) -> None:
        """Search the light direction on the current background, then learn it with the rest."""
        d = self.data
        links = d.link_poses[:, :, :3, 3].reshape(-1, 3)
        center = links.mean(0)
        extent = 2.2 * float((links - center).norm(dim=-1).max())
        resolution = self.config.shadow_resolution or matched_resolution(center, extent, self.viewmat(), d.K)
        casters = self._shadow_casters()
        model = DirectionalShadows(torch.tensor([0.0, 0.0, 1.0]), center.cpu(), extent, resolution=resolution,
                                   receivers=self.config.shadow_receivers, casters=casters).to(self.device)
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
            moving = tuple(torch.cat([x[:start], x[end:]]) for x in
                           (composed.means, composed.quats, composed.scales, composed.opacities))
            occluders = model.occluders(moving, d.link_poses[f].to(self.device), self.graph.link_gaussians)
            valid = inside & d.region(f, d.labels.static)[px[:, 1], px[:, 0]]
            if d.depth is not None:
                valid &= (d.depth[f][px[:, 1], px[:, 0]] - cam[:, 2]).abs() < 0.02
            observed = d.image(f)[px[:, 1], px[:, 0]]
            valid &= ~clipped(observed).any(-1)  # a clipped colour is not the surface's brightness
            observations.append((occluders, observed, valid))
        t0 = time.perf_counter()
        direction, strength, _ = search_direction(model, points, colors, observations)
        model.direction.copy_(direction)
        model.strength_logit.copy_(torch.logit(strength.clamp(0.05, 0.95)))
        model.moving_strength_logit.copy_(model.strength_logit)
        self.graph.shadows = model
        for group in self._light_groups(model):
            self.optimizer.add_param_group(group)
        log.info("shadows: light direction %s, strength %s (searched in %.1f s; shadow map %d px a side)",
                 np.round(direction.cpu().numpy(), 3).tolist(), np.round(strength.cpu().numpy(), 3).tolist(),
                 time.perf_counter() - t0, resolution)

    def _shadow_casters(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The links' surface samples that cast their shadows (``DirectionalShadows``' casters), or
        None when ``shadow_casters`` is "gaussians" or the robot description has no link mesh."""
        if self.config.shadow_casters not in SHADOW_CASTERS:
            raise ValueError(f"shadow casters must be one of {SHADOW_CASTERS}, not {self.config.shadow_casters!r}")
        if self.config.shadow_casters == "gaussians":
            return None
        meshes = {self.graph.link_index[name]: mesh for name, mesh in link_meshes(self.data.robot.visuals).items()
                  if name in self.graph.link_index}
        if not meshes:
            log.warning("shadows: the robot description has no link meshes; the links' Gaussians cast their "
                        "shadows (wider than the links')")
            return None
        points, links = surface_casters(meshes)
        log.info("shadows: cast by %d points on the meshes of %d links", len(points), len(meshes))
        return points, links

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        """Everything needed to continue training (tensors on the training device; load with
        ``torch.load(..., map_location="cpu")`` anywhere, then :meth:`load_state_dict` moves them)."""
        nodes = {}
        for node in self.graph.nodes():
            g = node.gaussians
            nodes[node.name] = {"params": {k: v.detach() for k, v in g.params.items()}, "strategy_state": g.strategy_state}
        return {
            "step": self.step, "config": asdict(self.config), "eps2d": self.graph.eps2d, "nodes": nodes,
            "optimizer": self.optimizer.state_dict(), "pose_optimizer": self.pose_optimizer.state_dict(),
            "trajectories": {k: t.state_dict() for k, t in self.trajectories.items()},
            "camera_delta": self.camera_delta.detach(), "background": self.background_logit.detach(),
            "exposure": self.exposure.fitted.clone() if self.exposure is not None else None,
            "view_exposures": {name: e.fitted.clone() for name, e in (self.exposures or {}).items()
                               if name != self.data.camera_name},
            "shadows": self.graph.shadows.state_dict() if self.graph.shadows is not None else None,
            "shadow_geometry": (self.graph.shadows.extent, self.graph.shadows.resolution,
                                self.graph.shadows.receivers) if self.graph.shadows else None,
            "rng": self._rng.getstate(), "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state(self.device) if self.device.type == "cuda" else None,
        }

    def load_state_dict(self, state: dict) -> None:
        """Continue from :meth:`state_dict`, saved on this or another device (tensors are moved here)."""
        if "optimizer" not in state:
            raise ValueError("the checkpoint was written by an older manisplat-reconstruct (one optimizer per node); "
                             "start a new run (--overwrite)")
        if self.trajectories and "pose_optimizer" not in state:
            raise ValueError("the checkpoint was written by an older manisplat-reconstruct (object poses in the "
                             "shared Adam); start a new run (--overwrite)")
        for flag, field, before, what in RESUMED_ALIKE:
            trained, asked = state["config"].get(field, before), getattr(self.config, field)
            if trained != asked:
                trained, asked = (shown_value(v, unset=SHARE_ALIKE) for v in (trained, asked))  # None: the share
                raise ValueError(f"the checkpoint was trained with --{flag} {trained}, this run asks for {asked}; "
                                 f"resume with the same {what}, or start a new run (--overwrite)")
        dilation = state.get("eps2d", GSPLAT_EPS2D)  # checkpoints before the modes' own dilations: gsplat's in both
        if dilation != self.graph.eps2d:
            raise ValueError(f"the checkpoint's splats were fitted with a {dilation:g} px^2 2D dilation, this version "
                             f"draws {self.config.rasterize_mode} splats with {self.graph.eps2d:g}; start a new run "
                             "(--overwrite)")
        dev = self.device

        def here(x):
            return x.to(dev) if isinstance(x, torch.Tensor) else x

        for node in self.graph.nodes():
            saved = state["nodes"][node.name]
            g = GaussianSet(saved["params"], scene_scale=node.gaussians.scene_scale, device=dev)
            g.active_degree = node.gaussians.active_degree
            g.strategy_state = {k: here(v) for k, v in saved["strategy_state"].items()}
            _replace_node(self.graph, node.name, g)
        for name, t in self.trajectories.items():
            t.load_state_dict(state["trajectories"][name])
        with torch.no_grad():
            self.camera_delta.copy_(state["camera_delta"])
            self.background_logit.copy_(state["background"])
            if self.exposure is not None:
                if state.get("exposure") is None:
                    raise ValueError("the checkpoint has no per-frame exposure (it was trained without it); "
                                     "resume with the same settings, or start a new run (--overwrite)")
                self.exposure.fitted.copy_(state["exposure"])
                for name, fitted in state.get("view_exposures", {}).items():
                    if name not in self.exposures:
                        raise ValueError(f"the checkpoint was trained with camera {name}, this run has not it; "
                                         "resume with the same cameras, or start a new run (--overwrite)")
                    self.exposures[name].fitted.copy_(fitted)
        self.graph.shadows = None
        if state["shadows"] is not None:
            extent, resolution, *receivers = state["shadow_geometry"]  # checkpoints before receivers: background
            casters = state["shadows"].get("caster_points"), state["shadows"].get("caster_links")
            sh = DirectionalShadows(torch.tensor([0.0, 0.0, 1.0]), torch.zeros(3), extent, resolution=resolution,
                                    receivers=receivers[0] if receivers else "background",
                                    casters=None if casters[0] is None else casters)
            sh.load_state_dict(state["shadows"], strict=bool(receivers))
            self.graph.shadows = sh.to(dev)
        self.optimizer = self._make_optimizer()
        self.optimizer.load_state_dict(state["optimizer"])  # moves the moments to the parameters' device
        if self.trajectories:
            self.pose_optimizer.load_state_dict(state["pose_optimizer"])
        self.step = state["step"]
        self._rng.setstate(state["rng"])
        torch.set_rng_state(state["torch_rng"].cpu())
        if dev.type == "cuda" and state.get("cuda_rng") is not None:
            torch.cuda.set_rng_state(state["cuda_rng"].cpu(), dev)

    def host_syncs(self, iters: int) -> collections.Counter:
        """Run ``iters`` more training iterations on CUDA and count the host-device synchronisations
        they make, by source site ("file:line"), from ``torch.cuda.set_sync_debug_mode("warn")``:
        the iterations alone, not :meth:`train`'s loss reads, evaluations and closing exposure fit."""
        if self.device.type != "cuda":
            raise ValueError(f"host_syncs counts CUDA synchronisations; this reconstruction is on {self.device}")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            with warnings.catch_warnings(record=True) as caught, compilation(self.compiled):
                warnings.simplefilter("always")
                self._iterate(iters)
        finally:
            torch.cuda.set_sync_debug_mode("default")
        return collections.Counter(f"{w.filename}:{w.lineno}" for w in caught
                                   if "synchroniz" in str(w.message).lower())

    def tensor_ops(self, iters: int) -> TensorOpCounter:
        """Run ``iters`` more training iterations eagerly and count their tensor operations (forward,
        backward, optimizer steps; :mod:`manisplat.reconstruct.tensor_ops`): on a GPU, the kernel
        launches that bound a small scene's iteration. The iterations alone, as :meth:`host_syncs`."""
        with TensorOpCounter() as ops:
            self._iterate(iters)
        return ops

    def _iterate(self, iters: int) -> None:
        """``iters`` more training iterations alone (no loss reads, evaluations or exposure fit),
        for the diagnostics above."""
        self.config.iters = self.step + iters
        states = self._train_states()
        for _ in range(iters):
            self._iteration(states)

    def save_checkpoint(self, path: Path) -> None:
        tmp = path.with_name(path.name + ".tmp")
        torch.save(self.state_dict(), tmp)
        tmp.replace(path)


class TrainStates:
    """The (camera, frame) pairs training draws its iterations from, and how: each alike, or a
    fixed camera's with probability ``fixed_share`` (spread evenly over the fixed cameras' pairs)
    and a riding camera's otherwise."""

    def __init__(self, states: list[tuple[str | None, int]], riding: set[str | None], fixed_share: float | None):
        if fixed_share is not None and not 0.0 < fixed_share < 1.0:
            raise ValueError(f"a fixed camera's share of the iterations is within (0, 1), not {fixed_share}")
        self.states = states
        self.fixed = [s for s in states if s[0] not in riding]
        self.riding = [s for s in states if s[0] in riding]
        if fixed_share is not None and not (self.fixed and self.riding):
            raise ValueError("a fixed camera's share of the iterations needs fixed and riding cameras trained, not "
                             f"{'riding' if self.riding else 'fixed'} ones only")
        self.fixed_share = fixed_share

    def draw(self, rng: random.Random) -> tuple[str | None, int]:
        """One (camera, frame) pair."""
        if self.fixed_share is None:
            return rng.choice(self.states)
        return rng.choice(self.fixed if rng.random() < self.fixed_share else self.riding)


#: the options a checkpoint resumes only with: (flag, ``TrainConfig`` field, the value of checkpoints
#: from before the option, what to keep the same)
RESUMED_ALIKE = (("rasterize-mode", "rasterize_mode", "classic", "mode"),
                 ("object-position-rate", "object_position_rate", 1.0, "rate"),  # before: the scene's rate
                 ("pose-rate-final", "pose_rate_final", 1.0, "rate"),  # before the schedule: constant
                 ("sh-degree", "sh_degree", 2, "degree"),
                 ("fixed-camera-weight", "fixed_camera_weight", 1.0, "weight"),
                 ("fixed-camera-share", "fixed_camera_share", None, "share"),
                 ("light-response", "light_response", False, "setting"))


def _progress_fields(mean_loss: float, held_out_psnr: float, gaussians: int) -> dict[str, str | int]:
    """The progress bar's fields; the loss and the held-out PSNR (dB) appear once they have been read."""
    fields: dict[str, str | int] = {} if math.isnan(mean_loss) else {"loss": f"{mean_loss:.4f}"}
    if not math.isnan(held_out_psnr):
        fields["held-out PSNR"] = f"{held_out_psnr:.2f} dB"
    fields["gaussians"] = gaussians
    return fields


def _dynamic_pixels(view: EpisodeData) -> torch.Tensor | None:
    """[T, H, W] bool: the robot's and the objects' pixels of every frame of ``view`` (None without masks)."""
    if view.masks is None:
        return None
    dynamic = torch.tensor(view.labels.moving, dtype=torch.uint8)
    return torch.isin(view.masks, dynamic.to(view.masks.device))


def _replace_node(graph: SceneGraph, name: str, g: GaussianSet) -> None:
    kind, _, rest = name.partition("/")
    if kind == "background":
        graph.background = g
    elif kind == "robot":
        graph.links[rest] = g
    else:
        graph.objects[rest] = g
