"""Fit Gaussians to one image with the rasterizer, densification and a PLY export.

    python examples/fit_image.py OUT_DIR [--steps 300] [--backend cpu]

Uses frame 0 of the built-in sample episode as the target. OUT_DIR must be new or empty; it gets
the sample (episode/), fit.png (target | render) and fit.ply (open it in any 3DGS viewer).
"""

from __future__ import annotations

import argparse
import sys
import math

import cv2
import numpy as np
import torch
from tqdm import tqdm

from manisplat.episode import Episode
from manisplat.episode.synthetic import write_sample_episode
from manisplat.output_folder import new_or_empty_folder
from manisplat.splat import DefaultStrategy, rasterization, save_ply
from manisplat.splat.sh import C0


def main(out_dir: str, steps: int = 300, backend: str = "cpu") -> dict:
    out = new_or_empty_folder(out_dir)  # never written into an existing episode or earlier results
    episode = Episode.open(write_sample_episode(out / "episode", frames=8))
    target = torch.from_numpy(episode.rgb(0)).float() / 255.0  # [H, W, 3]
    H, W = target.shape[:2]
    torch.manual_seed(0)
    n = 2000
    # Gaussians on a plane 2 m in front of an identity camera, spread over the field of view
    f = 1.0 * W
    K = torch.tensor([[[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]]])
    view = torch.eye(4)[None]
    xy = (torch.rand(n, 2) - 0.5) * torch.tensor([W / f, H / f]) * 2.0
    params = {
        "means": torch.nn.Parameter(torch.cat([xy, torch.full((n, 1), 2.0)], -1)),
        "quats": torch.nn.Parameter(torch.tensor([1.0, 0, 0, 0]).repeat(n, 1)),
        "scales": torch.nn.Parameter(torch.full((n, 3), math.log(0.02))),
        "opacities": torch.nn.Parameter(torch.full((n,), math.log(0.1 / 0.9))),
        "colors": torch.nn.Parameter(torch.rand(n, 3)),
    }
    lrs = {"means": 1.6e-4 * 2, "quats": 1e-3, "scales": 5e-3, "opacities": 5e-2, "colors": 2.5e-3 * 4}
    optimizers = {k: torch.optim.Adam([p], lr=lrs[k], eps=1e-15) for k, p in params.items()}
    every = max(steps // 6, 1)  # refine a few times, none in the last sixth
    strategy = DefaultStrategy(refine_start_iter=every - 1, refine_every=every, reset_every=10_000,
                               refine_stop_iter=steps - every)
    state = strategy.initialize_state(scene_scale=1.0)
    for step in tqdm(range(steps), desc="fitting", unit="step"):
        img, _, info = rasterization(params["means"], params["quats"], torch.exp(params["scales"]),
                                     torch.sigmoid(params["opacities"]), params["colors"], view, K, W, H,
                                     backend=backend)
        loss = (img[0] - target).abs().mean()
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss.backward()
        strategy.step_post_backward(params, optimizers, state, step, info)
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
    render = img[0].detach().clamp(0, 1)
    psnr = float(-10 * torch.log10(((render - target) ** 2).mean()))
    sheet = (torch.cat([target, render], dim=1).numpy() * 255).astype(np.uint8)
    cv2.imwrite(str(out / "fit.png"), cv2.cvtColor(cv2.resize(sheet, None, fx=2, fy=2), cv2.COLOR_RGB2BGR))
    save_ply(out / "fit.ply", {
        "means": params["means"], "scales": params["scales"], "quats": params["quats"],
        "opacities": params["opacities"], "sh0": ((params["colors"] - 0.5) / C0)[:, None, :],
    })
    print(f"{len(params['means'])} Gaussians, L1 {float(loss.detach()):.4f}, PSNR {psnr:.1f} dB; wrote {out / 'fit.png'}, {out / 'fit.ply'}")
    return {"psnr": psnr, "gaussians": len(params["means"])}


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--backend", default="cpu", choices=("cpu", "torch"))
    args = parser.parse_args()
    try:
        main(args.out_dir, args.steps, args.backend)
    except ValueError as exc:  # a used OUT_DIR
        sys.exit(f"error: {exc}")
