"""The gsplat backend against the pure-PyTorch oracle, on a CUDA machine with gsplat installed.

Skipped elsewhere: it needs the hardware (run it on a GPU machine: pip install 'manisplat[gpu]').
"""

from __future__ import annotations

import pytest
import torch

from manisplat.splat import rasterization
from manisplat.splat.backends import gsplat_raster
from tests.splat.scenes import random_scene

pytestmark = pytest.mark.skipif(not gsplat_raster.available(), reason="needs CUDA and gsplat")


@pytest.mark.parametrize("mode", ["RGB", "RGB+ED"])
def test_gsplat_matches_the_oracle_on_cuda(mode):
    params, V, K, W, H = random_scene(500, 0, dtype=torch.float32, width=64, height=48)
    cuda = [p.cuda().requires_grad_(True) for p in params]
    ref = [p.cuda().requires_grad_(True) for p in params]
    groups = (torch.arange(500) % 2).cuda()
    out_g = rasterization(*cuda, V.cuda(), K.cuda(), W, H, backend="gsplat", render_mode=mode, group_ids=groups, num_groups=2)
    out_t = rasterization(*ref, V.cuda(), K.cuda(), W, H, backend="torch", render_mode=mode, group_ids=groups, num_groups=2)
    assert float((out_g[0] - out_t[0]).abs().max()) < 1e-4
    assert float((out_g[1] - out_t[1]).abs().max()) < 1e-4
    assert float((out_g[2]["group_alphas"] - out_t[2]["group_alphas"]).abs().max()) < 1e-4
    (out_g[0].sum() + out_g[1].sum()).backward()
    (out_t[0].sum() + out_t[1].sum()).backward()
    for a, b in zip(cuda, ref):
        assert float((a.grad - b.grad).norm()) <= 1e-3 * float(b.grad.norm())
