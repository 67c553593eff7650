"""Gaussian rasterizer: ms per training iteration per backend (splatting.md workload and a realistic one).

Workload "fit" is splatting.md section 3 (gsplat's image-fitting example): 10k Gaussians, means
U[-1, 1]^3 seen from z = -8 with a 90 deg horizontal FOV at 256x192, raw scales U(0, 1) used as
scales, opacity logit 1, colour logits U(0, 1), fitting an image that is white with a red
top-left and a blue bottom-right quadrant, MSE loss, Adam lr 0.01 on all five parameter tensors.
Workload "scene" is closer to a reconstruction: 100k Gaussians filling a 2 x 1.5 x 1 m box 1-2 m
in front of a 640x480 camera, scales log-uniform 3-30 mm, opacities U(0.1, 0.9), RGB colours.
Rows give the median over the timed iterations (after warm-up), the loss before and after, and
the number of tile-splat pairs of the first frame. gsplat runs only where CUDA is present.
"""

from __future__ import annotations

import math
import statistics
import time

import torch

from manisplat.splat import available_backends, rasterization
from manisplat.splat.backends.tiles import tile_rects

THREADED = True


def fit_workload(n: int, width: int, height: int, generator: torch.Generator):
    """splatting.md section 3: returns (leaf parameters, render closure inputs, target image)."""
    means = 2 * (torch.rand(n, 3, generator=generator) - 0.5)
    scales = torch.rand(n, 3, generator=generator)
    u, v, w = (torch.rand(n, 1, generator=generator) for _ in range(3))
    quats = torch.cat([torch.sqrt(1 - u) * torch.sin(2 * math.pi * v), torch.sqrt(1 - u) * torch.cos(2 * math.pi * v),
                       torch.sqrt(u) * torch.sin(2 * math.pi * w), torch.sqrt(u) * torch.cos(2 * math.pi * w)], -1)
    rgbs = torch.rand(n, 3, generator=generator)
    opacities = torch.ones(n)
    view = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 8], [0, 0, 0, 1]])
    f = 0.5 * width / math.tan(0.5 * math.pi / 2)
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    target = torch.ones(height, width, 3)
    target[: height // 2, : width // 2] = torch.tensor([1.0, 0.0, 0.0])
    target[height // 2 :, width // 2 :] = torch.tensor([0.0, 0.0, 1.0])
    leaves = [means, quats, scales, rgbs, opacities]

    def activate(p):
        return p[0], p[1], p[2].clamp_min(0), torch.sigmoid(p[4]), torch.sigmoid(p[3])

    return leaves, activate, view[None], K[None], target


def scene_workload(n: int, width: int, height: int, generator: torch.Generator):
    means = torch.rand(n, 3, generator=generator) * torch.tensor([2.0, 1.5, 1.0]) + torch.tensor([-1.0, -0.75, 1.0])
    quats = torch.randn(n, 4, generator=generator)
    log_scales = math.log(0.003) + torch.rand(n, 3, generator=generator) * math.log(10.0)
    logits = torch.logit(0.1 + 0.8 * torch.rand(n, generator=generator))
    colors = torch.rand(n, 3, generator=generator)
    view = torch.eye(4)
    f = 0.9 * width
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    target = torch.rand(height, width, 3, generator=generator)
    leaves = [means, quats, log_scales, colors, logits]

    def activate(p):
        return p[0], p[1], torch.exp(p[2]), torch.sigmoid(p[4]), p[3]

    return leaves, activate, view[None], K[None], target


def run_training(backend, workload, n, width, height, iters, warmup):
    leaves, activate, view, K, target = workload(n, width, height, torch.Generator().manual_seed(0))
    params = [p.clone().requires_grad_(True) for p in leaves]
    optimizer = torch.optim.Adam(params, lr=0.01)
    times, losses, pairs = [], [], 0
    for it in range(warmup + iters):
        start = time.perf_counter()
        means, quats, scales, opacities, colors = activate(params)
        img, _, meta = rasterization(means, quats, scales, opacities, colors, view, K, width, height, backend=backend)
        loss = ((img[0] - target) ** 2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        elapsed = time.perf_counter() - start
        if it == 0:
            rect = tile_rects(meta["means2d"][0].detach(), meta["radii"][0], width, height, 16)
            pairs = int(((rect[:, 2] - rect[:, 0]).clamp_min(0) * (rect[:, 3] - rect[:, 1]).clamp_min(0)).sum())
        losses.append(float(loss.detach()))
        if it >= warmup:
            times.append(elapsed)
    return statistics.median(times) * 1000, losses[0], losses[-1], pairs


def run(ctx) -> list[dict]:
    backends = [b for b in ("cpu", "torch") if b in available_backends("cpu")]
    cases = [("fit", fit_workload, 10_000, 256, 192), ("scene", scene_workload, 100_000, 640, 480)]
    if ctx.quick:
        cases = [("fit", fit_workload, 2_000, 128, 96), ("scene", scene_workload, 10_000, 160, 120)]
    rows = []
    for name, workload, n, width, height in cases:
        for backend in backends:
            # the pure-PyTorch oracle is far slower: fewer timed iterations
            iters = 3 if backend == "torch" else 20
            if backend == "torch" and name == "scene" and not ctx.quick:
                iters = 1
            ms, loss0, loss1, pairs = run_training(backend, workload, n, width, height, iters, warmup=1)
            rows.append({"workload": name, "N": n, "size": f"{width}x{height}", "backend": backend,
                         "ms_per_iter": ms, "iters_timed": iters, "loss_first": loss0, "loss_last": loss1,
                         "tile_pairs": pairs})
    if torch.cuda.is_available():
        ctx.notes.append("CUDA present: run the gsplat comparison on the device (see README)")
    else:
        ctx.notes.append("no CUDA here: the gsplat backend was not measured")
    ctx.notes.append("target for the cpu backend: <= 100 ms per iteration at 1 thread on 'fit' (splatting.md)")
    return rows
