"""The training settings of ``manisplat-reconstruct``: a plain dataclass, importable without torch
(the command line reads its defaults before deciding whether to load anything)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class TrainConfig:
    """Optimisation settings (defaults used for the measurements in the README).

    Attributes:
        iters: training iterations (one frame each).
        lambda_app, lambda_mask, lambda_pose: loss weights (paper: 1.0 each).
        ssim_weight: D-SSIM share of the render and appearance losses.
        densify: clone/split/prune (gsplat defaults; refine every ``refine_every`` from
            ``refine_start`` to ``refine_stop_fraction`` of the iterations), each node growing to
            at most ``growth_cap`` times its initial size (unbounded growth on these sharp
            synthetic images multiplied the Gaussians by 6 and the time with them).
        shadows: learn cast shadows of the moving parts (searched at ``shadow_start``).
        sh_degree, sh_every: view-dependent colour bands (evaluated in each node's frame), one
            more band switched on every ``sh_every`` iterations.
        refine_camera: also optimise a correction of the camera extrinsic.
        backend: rasterizer backend ("auto", "cpu", "torch", "gsplat").
        eval_every: iterations between held-out PSNR estimates (for the progress bar).
        seed: random seed (frame order, densification samples).
    """

    iters: int = 3000
    lambda_app: float = 1.0
    lambda_mask: float = 1.0
    lambda_pose: float = 1.0
    ssim_weight: float = 0.2
    densify: bool = True
    refine_start: int = 300
    refine_every: int = 100
    refine_stop_fraction: float = 0.7
    grow_grad2d: float = 0.0002
    growth_cap: float = 2.0
    shadows: bool = True
    shadow_start: int = 300
    sh_degree: int = 2
    sh_every: int = 500
    refine_camera: bool = False
    backend: str = "auto"
    eval_every: int = 250
    seed: int = 0
