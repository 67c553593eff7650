"""Compositing backends: each turns projected 2D Gaussians into an image, front to back.

Every backend implements ``composite(means2d, conics, opacities, colors, depths, radii, width,
height, tile_size) -> (image [H, W, D], alpha [H, W])`` for one camera with gsplat's rules:
pixel (i, j) sampled at (j + 0.5, i + 0.5); ``alpha = min(0.999, o exp(-sigma))``; splats with
``alpha < 1/255`` (or sigma < 0) are skipped; a pixel stops before the splat that would bring its
transmittance to 1e-4 or below. ``gsplat`` (CUDA) instead wraps the whole of gsplat.rasterization.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

from manisplat.splat.backends import cpu_raster, gsplat_raster, torch_raster
from manisplat.splat.backends.cpu_raster import BackendUnavailable
from manisplat.splat.projection import project_gaussians

BACKENDS = ("torch", "cpu", "gsplat")


@dataclass(frozen=True)
class Backend:
    """A backend: ``project`` + ``composite`` (torch, cpu), or the whole ``rasterize`` (gsplat)."""

    name: str
    project: Callable | None = None
    composite: Callable | None = None
    rasterize: Callable | None = None


def available_backends(device: torch.device | str = "cpu") -> list[str]:
    """Backends that can run on ``device`` here (building the C++ one if needed)."""
    names = ["torch"]
    if torch.device(device).type == "cpu":
        try:
            cpu_raster.load_extension()
            names.append("cpu")
        except BackendUnavailable:
            pass
    elif gsplat_raster.available():
        names.append("gsplat")
    return names


def resolve_backend(name: str, device: torch.device) -> Backend:
    """The backend called ``name`` ("auto", "torch", "cpu", "gsplat") for tensors on ``device``.

    "auto" is gsplat for CUDA tensors and the C++ backend for CPU tensors. Nothing falls back
    silently: an unusable backend raises :class:`BackendUnavailable` saying what is missing.
    """
    if name == "auto":
        name = "gsplat" if device.type == "cuda" else "cpu"
    if name == "torch":
        return Backend("torch", project=project_gaussians, composite=torch_raster.composite)
    if name == "cpu":
        if device.type != "cpu":
            raise BackendUnavailable(f"the 'cpu' backend takes CPU tensors, got {device}")
        cpu_raster.load_extension()
        return Backend("cpu", project=cpu_raster.project, composite=cpu_raster.composite)
    if name == "gsplat":
        if device.type != "cuda" or not gsplat_raster.available():
            raise BackendUnavailable(
                f"the 'gsplat' backend needs CUDA tensors and gsplat (pip install 'manisplat[gpu]'); "
                f"tensors are on {device}, CUDA available: {torch.cuda.is_available()}; or pass backend='torch'"
            )
        return Backend("gsplat", rasterize=gsplat_raster.rasterize)
    raise ValueError(f"unknown backend {name!r}; choose one of 'auto', {', '.join(map(repr, BACKENDS))}")
