"""The CUDA backend: gsplat's own ``rasterization`` (optional extra ``manisplat[gpu]``).

Imported lazily and only for CUDA tensors (importing or calling gsplat on a CPU-only machine
tries a CUDA build). gsplat already follows the conventions the other backends copy; this module
only maps our options (group alphas as extra one-hot channels, meta keys) onto its call.
"""

from __future__ import annotations

import torch


def available() -> bool:
    """True when CUDA is usable and gsplat imports."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def rasterize(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, near_plane, far_plane,
              eps2d, sh_degree, backgrounds, render_mode, group_ids, num_groups, tile_size, rasterize_mode):
    """Same contract as :func:`manisplat.splat.rasterization` on CUDA tensors."""
    import gsplat

    def call(cols, mode, bgs, degree):
        return gsplat.rasterization(
            means, quats, scales, opacities, cols, viewmats, Ks, width, height, near_plane=near_plane,
            far_plane=far_plane, eps2d=eps2d, sh_degree=degree, backgrounds=bgs, render_mode=mode,
            packed=False, tile_size=tile_size, rasterize_mode=rasterize_mode,
        )

    C = viewmats.shape[0]
    one_hot = torch.nn.functional.one_hot(group_ids.long(), num_groups).to(means.dtype) if num_groups else None
    if one_hot is not None and sh_degree is None:
        D = colors.shape[-1]
        bgs = None
        if backgrounds is not None:
            bgs = torch.cat([backgrounds, backgrounds.new_zeros(C, num_groups)], dim=-1)
        out, alphas, meta = call(torch.cat([colors, one_hot], -1), render_mode, bgs, None)
        group_alphas = out[..., D : D + num_groups]
        out = torch.cat([out[..., :D], out[..., D + num_groups :]], dim=-1)
    else:
        out, alphas, meta = call(colors, render_mode, backgrounds, sh_degree)
        group_alphas = call(one_hot, "RGB", None, None)[0] if one_hot is not None else None
    radii = meta["radii"]
    visible = (radii > 0).all(dim=-1) if radii.dim() == 3 else radii > 0
    out_meta = {
        "means2d": meta["means2d"], "radii": radii, "depths": meta["depths"], "conics": meta["conics"],
        "visible": visible, "width": width, "height": height, "n_cameras": C, "backend": "gsplat",
    }
    if group_alphas is not None:
        out_meta["group_alphas"] = group_alphas
    return out, alphas, out_meta
