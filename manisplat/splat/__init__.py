"""Differentiable Gaussian splatting: one ``rasterization`` function, several backends.

Backends: "torch" (pure PyTorch, the test oracle), "cpu" (C++/OpenMP with a hand-written
backward, the default on CPU) and "gsplat" (CUDA, optional). All follow gsplat's conventions.
"""

from manisplat.splat.backends import BACKENDS, BackendUnavailable, available_backends
from manisplat.splat.ply import PlyFormatError, load_ply, save_ply
from manisplat.splat.projection import Projection, opencv_to_splat_K, project_gaussians
from manisplat.splat.rasterization import (DEFAULT_EPS2D, GSPLAT_EPS2D, RASTERIZE_MODES, RENDER_MODES, RasterizationError,
                                           is_dilation, rasterization, value_checks)
from manisplat.splat.sh import num_sh_bases, spherical_harmonics
from manisplat.splat.strategy import DefaultStrategy

__all__ = [
    "BACKENDS",
    "BackendUnavailable",
    "DEFAULT_EPS2D",
    "DefaultStrategy",
    "GSPLAT_EPS2D",
    "PlyFormatError",
    "Projection",
    "RASTERIZE_MODES",
    "RENDER_MODES",
    "RasterizationError",
    "available_backends",
    "is_dilation",
    "load_ply",
    "num_sh_bases",
    "opencv_to_splat_K",
    "project_gaussians",
    "rasterization",
    "save_ply",
    "spherical_harmonics",
    "value_checks",
]
