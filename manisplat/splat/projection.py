"""EWA projection of 3D Gaussians into pinhole cameras, in torch (shared by the torch and cpu
backends, so gradients to means, quaternions, scales and opacities come from autograd).

Conventions follow gsplat: ``viewmats`` map world to camera (OpenCV axes), ``Ks`` are pinhole
intrinsics whose pixel (i, j) is sampled at (j + 0.5, i + 0.5); a dilation ``eps2d`` (0.3 px^2
unless given) is added to every 2D covariance; x/z and y/z are clamped (principal-point aware,
0.3 tan(fov/2) beyond the image) when building the Jacobian only; splats outside [near, far], with a non-positive 2D
determinant, an opacity below 1/255 or a box that misses the image are culled (radius 0).
The per-axis box is the opacity-aware 3.33-sigma extent: it holds every pixel where
``opacity * exp(-sigma) >= 1/255``.

The arithmetic runs in float64 whatever the input dtype (a float32 determinant of a 1e3 m
Gaussian near the camera overflows); outputs are cast back to the input dtype.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

ALPHA_THRESHOLD = 1.0 / 255.0
MAX_EXTENT = 3.33  # sigmas; sqrt(2 ln 255) = 3.33, the box can never need more


@dataclass
class Projection:
    """Gaussians as seen by C cameras.

    Attributes:
        means2d: [C, N, 2] pixel coordinates of the centres.
        conics: [C, N, 3] inverse 2D covariance (a, b, c): sigma = 0.5 (a dx^2 + c dy^2) + b dx dy.
        depths: [C, N] camera-space z of the centres (m).
        radii: [C, N, 2] int32 half-widths of the pixel box, 0 where culled.
        opacities: [C, N] opacities (the input, per camera).
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    radii: torch.Tensor
    opacities: torch.Tensor

    @property
    def visible(self) -> torch.Tensor:
        """[C, N] bool: not culled."""
        return (self.radii > 0).all(dim=-1)


def splat_rotations(quats: torch.Tensor) -> torch.Tensor:
    """Rotations [..., 3, 3] of Gaussian quaternions (w, x, y, z) [..., 4], any norm.

    Normalised with a floor of 1e-12 on the norm, so a zero quaternion gives the identity
    (finite values and gradients) instead of NaN: the splatting convention, unlike
    :func:`manisplat.geometry.quat_to_matrix`, which rejects zero quaternions in poses.
    """
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def quat_scale_to_covariance(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """3D covariances [N, 3, 3] = R S S^T R^T of quaternions [N, 4] (see :func:`splat_rotations`)
    and scales [N, 3]."""
    M = splat_rotations(quats) * scales[..., None, :]
    return M @ M.transpose(-1, -2)


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    *,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
) -> Projection:
    """Project N Gaussians into C cameras (see the module docstring for the conventions).

    Args:
        means: [N, 3] world positions; quats: [N, 4]; scales: [N, 3] (activated, m);
        opacities: [N] (activated, in [0, 1]); viewmats: [C, 4, 4] world-to-camera;
        Ks: [C, 3, 3]; width, height: image size in pixels.
    """
    dtype = means.dtype
    f64 = torch.float64
    means, quats, scales, opacities = (x.to(f64) for x in (means, quats, scales, opacities))
    viewmats, Ks = viewmats.to(f64), Ks.to(f64)
    R, t = viewmats[:, None, :3, :3], viewmats[:, None, :3, 3]  # [C, 1, 3, 3], [C, 1, 3]
    mc = (R @ means[None, :, :, None])[..., 0] + t  # [C, N, 3] camera-space centres
    tx, ty, tz = mc.unbind(-1)
    in_depth = (tz >= near_plane) & (tz <= far_plane)
    tz_safe = torch.where(in_depth, tz, torch.ones_like(tz))  # no division by z <= 0, even in backward

    fx, fy = Ks[:, None, 0, 0], Ks[:, None, 1, 1]  # [C, 1]
    cx, cy = Ks[:, None, 0, 2], Ks[:, None, 1, 2]
    u = fx * tx / tz_safe + cx
    v = fy * ty / tz_safe + cy

    # Jacobian with the view-frustum clamp on x/z, y/z (gradient of the clamped part goes to z).
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_y, cy / fy + 0.3 * tan_y
    x_cl = torch.maximum(torch.minimum(tx / tz_safe, lim_x_pos), -lim_x_neg) * tz_safe
    y_cl = torch.maximum(torch.minimum(ty / tz_safe, lim_y_pos), -lim_y_neg) * tz_safe
    zero = torch.zeros_like(tz_safe)
    J = torch.stack(
        [fx / tz_safe, zero, -fx * x_cl / tz_safe**2, zero, fy / tz_safe, -fy * y_cl / tz_safe**2], dim=-1
    ).reshape(*tz.shape, 2, 3)  # [C, N, 2, 3]

    cov_world = quat_scale_to_covariance(quats, scales)  # [N, 3, 3]
    cov_cam = R @ cov_world[None] @ R.transpose(-1, -2)  # [C, N, 3, 3]
    cov2d = J @ cov_cam @ J.transpose(-1, -2)
    a = cov2d[..., 0, 0] + eps2d
    b = cov2d[..., 0, 1]
    c = cov2d[..., 1, 1] + eps2d
    det = a * c - b * b
    ok_det = det > 0
    det_safe = torch.where(ok_det, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)

    o = opacities[None].expand_as(tz)
    ok_opacity = o >= ALPHA_THRESHOLD
    extent = torch.sqrt(2.0 * torch.log(torch.where(ok_opacity, o, torch.ones_like(o)) / ALPHA_THRESHOLD))
    extent = extent.clamp(max=MAX_EXTENT)
    with torch.no_grad():
        rx = torch.ceil(extent * a.clamp_min(0).sqrt())
        ry = torch.ceil(extent * c.clamp_min(0).sqrt())
        on_image = (u + rx > 0) & (u - rx < width) & (v + ry > 0) & (v - ry < height)
        keep = in_depth & ok_det & ok_opacity & on_image & (rx > 0) & (ry > 0)
        keep &= torch.isfinite(rx) & torch.isfinite(ry)
        radii = torch.stack([rx, ry], dim=-1).clamp(max=2**30).to(torch.int32) * keep[..., None]
    return Projection(
        means2d=torch.stack([u, v], dim=-1).to(dtype),
        conics=conics.to(dtype),
        depths=tz.to(dtype),
        radii=radii,
        opacities=o.to(dtype),
    )


def opacity_compensation(conics: torch.Tensor, eps2d: float) -> torch.Tensor:
    """[...] the factor ``sqrt(det(cov2d) / det(cov2d + eps2d I))`` of dilated 2D Gaussians given their
    ``conics`` [..., 3] (the inverse of the dilated covariance, :class:`Projection`) and the
    dilation ``eps2d`` (px^2): Mip-Splatting's 2D filter, gsplat's ``rasterize_mode="antialiased"``.

    Multiplying a splat's opacity by it keeps its integral: a Gaussian far smaller than a pixel
    (fitted to a close-up, seen from afar) covers a pixel's worth of area at a fraction of its
    opacity, where the plain dilation draws it a whole pixel wide at full opacity. In float64,
    from ``det(cov2d) / det(cov2d + eps I) = 1 - eps tr(conic) + eps^2 det(conic)``; floored at
    0.01 (the square at 1e-4), so that its gradient stays finite.
    """
    a, b, c = conics.double().unbind(-1)
    ratio = 1.0 - eps2d * (a + c) + eps2d**2 * (a * c - b * b)
    return torch.sqrt(ratio.clamp_min(1e-4)).to(conics.dtype)


def opencv_to_splat_K(K: torch.Tensor) -> torch.Tensor:
    """Intrinsics with OpenCV's integer pixel centres (episodes) -> the rasterizer's half-pixel ones.

    OpenCV puts pixel (i, j)'s centre at (j, i); gsplat and this rasterizer sample it at
    (j + 0.5, i + 0.5). Shifting cx and cy by +0.5 makes both agree.
    """
    out = K.clone()
    out[..., 0, 2] += 0.5
    out[..., 1, 2] += 0.5
    return out


__all__ = ["ALPHA_THRESHOLD", "Projection", "opacity_compensation", "opencv_to_splat_K", "project_gaussians",
           "quat_scale_to_covariance", "splat_rotations"]
