"""``rasterization``: render 3D Gaussians into C cameras, modelled on ``gsplat.rasterization``.

Colours, depth and per-group alphas are composited in one pass as channels of one colour
tensor: depth is the camera z of each splat, and a group's alpha is a one-hot channel (the
summed blending weight of that group's splats, e.g. the dynamic parts for a mask loss).
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import numbers
from collections.abc import Iterator

import torch

from manisplat.splat.backends import resolve_backend
from manisplat.splat.projection import opacity_compensation
from manisplat.splat.sh import num_sh_bases, spherical_harmonics

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
RASTERIZE_MODES = ("classic", "antialiased")
#: gsplat's 2D dilation (px^2) in both of its modes, and so every mode's here before 2026-12-06
GSPLAT_EPS2D = 0.3
#: each rasterize mode's 2D dilation ``eps2d`` (px^2, added to every splat's screen covariance):
#: classic keeps gsplat's 0.3, which holds a splat at least about a pixel wide at full opacity;
#: antialiased uses Mip-Splatting's 2D filter, 0.1 (a one-pixel box filter's Gaussian stand-in).
#: At 0.3 the antialiased twin of the camera-like Cobot Magic dual sample, trained on all three
#: cameras, drew the head camera's objects 27.3 dB, at 0.1 28.1 (docs/benchmarks.md).
DEFAULT_EPS2D = {"classic": GSPLAT_EPS2D, "antialiased": 0.1}


def is_dilation(eps2d: object) -> bool:
    """Whether ``eps2d`` is a usable 2D dilation: a finite real number >= 0 (px^2)."""
    return isinstance(eps2d, numbers.Real) and not isinstance(eps2d, bool) and math.isfinite(eps2d) and eps2d >= 0.0


class RasterizationError(ValueError):
    """Inputs of the wrong shape, dtype or value (NaN, negative scales, ...)."""


_CHECK_VALUES: contextvars.ContextVar[bool] = contextvars.ContextVar("manisplat_splat_check_values", default=True)


@contextlib.contextmanager
def value_checks(enabled: bool) -> Iterator[None]:
    """Turn the checks of input *values* (NaN/Inf, negative scales, opacities outside [0, 1],
    group ids out of range) on or off inside the block; shapes and dtypes are always checked.

    Each value check reads a result back from the tensors' device: on a GPU that waits for all
    queued work (a host-device synchronisation), about 1 ms per call. A training loop on CUDA
    turns them off and checks its loss instead (``manisplat.reconstruct`` does).
    """
    token = _CHECK_VALUES.set(bool(enabled))
    try:
        yield
    finally:
        _CHECK_VALUES.reset(token)


def _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree) -> None:
    N = means.shape[0] if means.ndim == 2 else -1
    expected = {"means": (means, (N, 3)), "quats": (quats, (N, 4)), "scales": (scales, (N, 3)), "opacities": (opacities, (N,))}
    for name, (tensor, shape) in expected.items():
        if tuple(tensor.shape) != shape:
            raise RasterizationError(f"{name} must have shape {shape} (N = len(means)), got {tuple(tensor.shape)}")
    if sh_degree is None:
        if colors.ndim != 2 or colors.shape[0] != N:
            raise RasterizationError(f"colors must be [N, D] (or SH [N, K, 3] with sh_degree), got {tuple(colors.shape)}")
    elif colors.ndim != 3 or colors.shape[0] != N or colors.shape[1] < num_sh_bases(sh_degree):
        raise RasterizationError(
            f"SH colours for degree {sh_degree} must be [N, K >= {num_sh_bases(sh_degree)}, D], got {tuple(colors.shape)}"
        )
    if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4) or Ks.shape != (viewmats.shape[0], 3, 3):
        raise RasterizationError(f"viewmats must be [C, 4, 4] and Ks [C, 3, 3], got {tuple(viewmats.shape)}, {tuple(Ks.shape)}")
    if width <= 0 or height <= 0:
        raise RasterizationError(f"image size must be positive, got {width}x{height}")
    if not _CHECK_VALUES.get():
        return
    for name, tensor in (("means", means), ("quats", quats), ("scales", scales), ("opacities", opacities),
                         ("colors", colors), ("viewmats", viewmats), ("Ks", Ks)):
        if not bool(torch.isfinite(tensor).all()):
            raise RasterizationError(f"{name} contains NaN or Inf")
    if bool((scales < 0).any()):
        raise RasterizationError("scales must be non-negative (pass activated scales, e.g. exp(log_scales))")
    if bool(((opacities < 0) | (opacities > 1)).any()):
        raise RasterizationError("opacities must be in [0, 1] (pass activated opacities, e.g. sigmoid(logits))")


def rasterization(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    *,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float | None = None,
    sh_degree: int | None = None,
    backgrounds: torch.Tensor | None = None,
    render_mode: str = "RGB",
    group_ids: torch.Tensor | None = None,
    num_groups: int | None = None,
    backend: str = "auto",
    tile_size: int = 16,
    rasterize_mode: str = "classic",
) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Render N Gaussians into C cameras.

    Args:
        means: [N, 3] world positions (m). quats: [N, 4] (w, x, y, z), any norm (zero gives identity).
        scales: [N, 3] activated standard deviations (m). opacities: [N] activated, in [0, 1].
        colors: [N, D] activated colours, or SH coefficients [N, K, D] with ``sh_degree``
            (colour = max(SH(view direction) + 0.5, 0), as gsplat).
        viewmats: [C, 4, 4] world-to-camera (OpenCV axes). Ks: [C, 3, 3]; pixel (i, j) is sampled
            at (j + 0.5, i + 0.5); convert an episode's OpenCV K with ``opencv_to_splat_K``.
        width, height: image size in pixels.
        near_plane, far_plane: depth range kept (m).
        eps2d: 2D dilation (px^2); None: the rasterize mode's :data:`DEFAULT_EPS2D`.
        backgrounds: [C, D] colour behind the splats (default black).
        render_mode: "RGB", "D" (accumulated depth), "ED" (expected depth = D / alpha),
            "RGB+D" or "RGB+ED"; depth is the last channel.
        group_ids: [N] int64 in [0, num_groups): also return each group's alpha map.
        backend: "auto" (gsplat on CUDA tensors when installed, else the C++ "cpu" backend),
            "cpu", "torch" (pure PyTorch reference) or "gsplat".
        rasterize_mode: "classic" (the 2D dilation adds area at full opacity) or "antialiased"
            (each opacity scaled by :func:`~manisplat.splat.projection.opacity_compensation`, as
            gsplat's mode of that name: Gaussians far below a pixel keep their integral).

    Returns:
        render_colors: [C, H, W, X]; render_alphas: [C, H, W, 1];
        meta: dict with "means2d" [C, N, 2] (call ``retain_grad()`` on it for densification),
        "radii" [C, N, 2], "depths" [C, N], "conics" [C, N, 3], "visible" [C, N], "width",
        "height", "n_cameras", "backend", and "group_alphas" [C, H, W, G] with ``group_ids``.
    """
    if render_mode not in RENDER_MODES:
        raise RasterizationError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if rasterize_mode not in RASTERIZE_MODES:
        raise RasterizationError(f"rasterize_mode must be one of {RASTERIZE_MODES}, got {rasterize_mode!r}")
    if eps2d is None:
        eps2d = DEFAULT_EPS2D[rasterize_mode]
    elif not is_dilation(eps2d):
        raise RasterizationError(f"eps2d must be a finite dilation >= 0 px^2, got {eps2d!r}")
    _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree)
    impl = resolve_backend(backend, means.device)
    C, N = viewmats.shape[0], means.shape[0]
    G = 0
    if group_ids is not None:
        if num_groups is None or num_groups < 1:
            raise RasterizationError("group_ids needs num_groups >= 1")
        if group_ids.shape != (N,) or group_ids.dtype not in (torch.int32, torch.int64):
            raise RasterizationError(f"group_ids must be an int tensor of shape ({N},), got {tuple(group_ids.shape)} {group_ids.dtype}")
        if N and _CHECK_VALUES.get() and (int(group_ids.min()) < 0 or int(group_ids.max()) >= num_groups):
            raise RasterizationError(f"group_ids must lie in [0, {num_groups})")
        G = num_groups
    if impl.name == "gsplat":
        return impl.rasterize(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane=near_plane,
            far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree, backgrounds=backgrounds,
            render_mode=render_mode, group_ids=group_ids, num_groups=G, tile_size=tile_size,
            rasterize_mode=rasterize_mode,
        )

    proj = impl.project(
        means, quats, scales, opacities, viewmats, Ks, width, height,
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d,
    )
    splat_opacities = proj.opacities
    if rasterize_mode == "antialiased":
        splat_opacities = proj.opacities * opacity_compensation(proj.conics, eps2d)
    want_rgb = render_mode.startswith("RGB")
    want_depth = render_mode != "RGB"
    outputs, alphas, group_alphas = [], [], []
    for cam in range(C):
        channels = []
        if want_rgb:
            channels.append(_camera_colors(colors, means, viewmats[cam], sh_degree))
        if want_depth:
            channels.append(proj.depths[cam][:, None])
        if G:
            channels.append(torch.nn.functional.one_hot(group_ids.long(), G).to(means.dtype))
        feats = torch.cat(channels, dim=-1) if channels else means.new_zeros(N, 0)
        image, alpha = impl.composite(
            proj.means2d[cam], proj.conics[cam], splat_opacities[cam], feats, proj.depths[cam],
            proj.radii[cam], width, height, tile_size,
        )
        D_rgb = colors.shape[-1] if want_rgb else 0
        rgb = image[..., :D_rgb]
        if want_rgb and backgrounds is not None:
            rgb = rgb + (1.0 - alpha[..., None]) * backgrounds[cam]
        parts = [rgb] if want_rgb else []
        if want_depth:
            depth = image[..., D_rgb : D_rgb + 1]
            if render_mode.endswith("ED"):
                depth = depth / alpha[..., None].clamp_min(1e-10)
            parts.append(depth)
        outputs.append(torch.cat(parts, dim=-1))
        alphas.append(alpha[..., None])
        if G:
            group_alphas.append(image[..., -G:])
    meta = {
        "means2d": proj.means2d, "radii": proj.radii, "depths": proj.depths, "conics": proj.conics,
        "visible": proj.visible, "width": width, "height": height, "n_cameras": C, "backend": impl.name,
    }
    if G:
        meta["group_alphas"] = torch.stack(group_alphas)
    return torch.stack(outputs), torch.stack(alphas), meta


def _camera_colors(colors: torch.Tensor, means: torch.Tensor, viewmat: torch.Tensor, sh_degree: int | None) -> torch.Tensor:
    """[N, D] colours for one camera: as given, or SH evaluated along camera-to-Gaussian rays."""
    if sh_degree is None:
        return colors
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    camera_center = -(R.transpose(0, 1) @ t)
    return torch.clamp_min(spherical_harmonics(sh_degree, means - camera_center, colors) + 0.5, 0.0)
