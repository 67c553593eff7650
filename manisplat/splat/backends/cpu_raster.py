"""The C++/OpenMP backend: projection and compositing, forward and hand-written backward (``csrc/``).

Built on first use with ``torch.utils.cpp_extension`` and cached (``$TORCH_EXTENSIONS_DIR``, by
default ``~/.cache/torch_extensions``) under a name that hashes the source, the flags and the
torch version, so an edit or an upgrade rebuilds and nothing stale is loaded. AVX2/FMA code is
generated when torch reports the CPU supports it. Threads follow ``torch.set_num_threads``.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
from pathlib import Path
from types import ModuleType

import torch

from manisplat.splat.backends.tiles import tile_rects
from manisplat.splat.projection import Projection

log = logging.getLogger(__name__)
CSRC = Path(__file__).resolve().parent.parent / "csrc"
SOURCES = (CSRC / "rasterize_cpu.cpp", CSRC / "project_cpu.cpp")
HEADERS = (CSRC / "splat_cpu.h",)
_extension: ModuleType | None = None


class BackendUnavailable(RuntimeError):
    """A rasterizer backend cannot run here (no compiler, no GPU, gsplat missing, ...)."""


def _flags() -> list[str]:
    flags = ["-O3", "-fopenmp", "-std=c++17"]
    if torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512"):
        flags += ["-mavx2", "-mfma"]
    return flags


def load_extension() -> ModuleType:
    """The compiled extension, building it once if needed.

    Raises:
        BackendUnavailable: no C++ compiler or the build failed; the message says how to fix it
            or to choose ``backend="torch"`` explicitly.
    """
    global _extension
    if _extension is not None:
        return _extension
    compiler = os.environ.get("CXX", "c++")
    if shutil.which(compiler) is None:
        raise BackendUnavailable(
            f"the 'cpu' rasterizer needs a C++ compiler ({compiler!r} not found; install g++ or set CXX), "
            "or pass backend='torch' for the slow pure-PyTorch one"
        )
    from torch.utils import cpp_extension

    flags = _flags()
    digest = hashlib.sha1()
    for path in SOURCES + HEADERS:
        digest.update(path.read_bytes())
    digest.update((" ".join(flags) + torch.__version__).encode())
    name = f"manisplat_raster_cpu_{digest.hexdigest()[:12]}"
    log.info("loading the C++ rasterizer %s (the first build takes about a minute; it is cached)", name)
    try:
        _extension = cpp_extension.load(
            name=name, sources=[str(p) for p in SOURCES], extra_include_paths=[str(CSRC)], extra_cflags=flags,
            extra_ldflags=["-fopenmp"], verbose=False,
        )
    except Exception as exc:  # compiler and ninja errors come in several types
        raise BackendUnavailable(
            f"building the 'cpu' rasterizer failed ({exc}); fix the toolchain or pass backend='torch'"
        ) from exc
    return _extension


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, radii, rects, order, width, height, tile_size):
        ext = load_extension()
        tensors = [t.contiguous() for t in (means2d, conics, opacities, colors)]
        image, alpha, final_T, last, offsets, lists = ext.forward(
            *tensors, radii.contiguous(), rects.contiguous(), order.contiguous(), width, height, tile_size
        )
        ctx.save_for_backward(*tensors, radii, offsets, lists, final_T, last)
        ctx.size = (width, height, tile_size)
        return image, alpha

    @staticmethod
    def backward(ctx, grad_image, grad_alpha):
        means2d, conics, opacities, colors, radii, offsets, lists, final_T, last = ctx.saved_tensors
        width, height, tile_size = ctx.size
        g_means, g_conics, g_opac, g_colors = load_extension().backward(
            means2d, conics, opacities, colors, radii.contiguous(), offsets, lists, final_T, last,
            grad_image.contiguous(), grad_alpha.contiguous(), width, height, tile_size,
        )
        return g_means, g_conics, g_opac, g_colors, None, None, None, None, None, None


def composite(means2d, conics, opacities, colors, depths, radii, width, height, tile_size=16):
    """Image [H, W, D] and alpha [H, W]; see :mod:`manisplat.splat.backends` for the rules."""
    if means2d.device.type != "cpu":
        raise BackendUnavailable("the 'cpu' backend takes CPU tensors")
    dtype = colors.dtype
    rects = tile_rects(means2d, radii, width, height, tile_size)
    order = torch.argsort(depths.detach(), stable=True)
    return _Composite.apply(
        means2d.to(dtype), conics.to(dtype), opacities.to(dtype), colors, radii.to(torch.int32), rects, order,
        width, height, tile_size,
    )


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, viewmat, K, opacities, width, height, near, far, eps2d):
        ext = load_extension()
        inputs = [t.contiguous() for t in (means, quats, scales, viewmat, K)]
        means2d, conics, depths, radii = ext.project_forward(
            *inputs[:3], opacities.detach().contiguous(), *inputs[3:], width, height, near, far, eps2d
        )
        ctx.save_for_backward(*inputs, radii)
        ctx.args = (width, height, eps2d)
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, radii

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, _):
        means, quats, scales, viewmat, K, radii = ctx.saved_tensors
        width, height, eps2d = ctx.args
        g_means, g_quats, g_scales, g_view = load_extension().project_backward(
            means, quats, scales, viewmat, K, width, height, eps2d, radii,
            g_means2d.contiguous(), g_conics.contiguous(), g_depths.contiguous(),
        )
        return g_means, g_quats, g_scales, g_view, None, None, None, None, None, None, None


def project(means, quats, scales, opacities, viewmats, Ks, width, height, *, near_plane=0.01, far_plane=1e10,
            eps2d=0.3) -> Projection:
    """:func:`manisplat.splat.projection.project_gaussians` in C++ (same conventions and results)."""
    if means.device.type != "cpu":
        raise BackendUnavailable("the 'cpu' backend takes CPU tensors")
    dtype = means.dtype
    parts = [
        _Project.apply(means, quats.to(dtype), scales.to(dtype), viewmats[c].to(dtype), Ks[c].to(dtype),
                       opacities.to(dtype), width, height, float(near_plane), float(far_plane), float(eps2d))
        for c in range(viewmats.shape[0])
    ]
    means2d, conics, depths, radii = (torch.stack(x) for x in zip(*parts))
    return Projection(means2d, conics, depths, radii, opacities.to(dtype)[None].expand(viewmats.shape[0], -1))
