"""Gaussian scenes as PLY files in the standard 3DGS layout, which common splat viewers open.

One ``vertex`` element, binary little-endian float32 properties: ``x, y, z, nx, ny, nz`` (normals
0, as 3DGS writes them), ``f_dc_0..2`` (SH degree-0 coefficients), ``f_rest_*`` (higher SH bands,
channel-major: all of red, then green, then blue), ``opacity`` (logit), ``scale_0..2`` (log),
``rot_0..3`` (quaternion w, x, y, z, not necessarily unit). Values are stored as the raw
(pre-activation) parameters, exactly as 3DGS stores them.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement


class PlyFormatError(ValueError):
    """A PLY file that is not a 3DGS Gaussian scene (missing or inconsistent properties)."""


def save_ply(path: str | Path, splats: dict[str, torch.Tensor]) -> Path:
    """Write ``splats`` to ``path`` (atomically: a temporary file renamed into place).

    Args:
        splats: "means" [N, 3], "scales" [N, 3] log, "quats" [N, 4], "opacities" [N] logit,
            "sh0" [N, 1, 3] and optionally "shN" [N, K-1, 3] (K = (degree + 1)^2 coefficients).
    """
    n = len(splats["means"])
    expected = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "opacities": (n,), "sh0": (n, 1, 3)}
    for key, shape in expected.items():
        if key not in splats or tuple(splats[key].shape) != shape:
            got = tuple(splats[key].shape) if key in splats else "missing"
            raise ValueError(f"save_ply: {key!r} must have shape {shape}, got {got}")
    shN = splats.get("shN")
    if shN is not None and (shN.dim() != 3 or shN.shape[0] != n or shN.shape[2] != 3):
        raise ValueError(f"save_ply: 'shN' must be [N, K-1, 3], got {tuple(shN.shape)}")

    def cpu(x: torch.Tensor) -> np.ndarray:
        return x.detach().to("cpu", torch.float32).numpy()

    columns: list[tuple[str, np.ndarray]] = [(f"{a}", cpu(splats["means"])[:, i]) for i, a in enumerate("xyz")]
    columns += [(name, np.zeros(n, np.float32)) for name in ("nx", "ny", "nz")]
    columns += [(f"f_dc_{i}", cpu(splats["sh0"])[:, 0, i]) for i in range(3)]
    if shN is not None:
        rest = cpu(shN).transpose(0, 2, 1).reshape(n, -1)  # channel-major, as 3DGS
        columns += [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
    columns.append(("opacity", cpu(splats["opacities"]).reshape(n)))
    columns += [(f"scale_{i}", cpu(splats["scales"])[:, i]) for i in range(3)]
    columns += [(f"rot_{i}", cpu(splats["quats"])[:, i]) for i in range(4)]
    data = np.empty(n, dtype=[(name, "<f4") for name, _ in columns])
    for name, values in columns:
        data[name] = values
    if not all(np.isfinite(data[name]).all() for name, _ in columns):
        raise ValueError("save_ply: the scene contains NaN or Inf")
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    PlyData([PlyElement.describe(data, "vertex")], text=False, byte_order="<").write(str(tmp))
    os.replace(tmp, path)
    return path


def load_ply(path: str | Path, *, dtype: torch.dtype = torch.float32) -> dict[str, torch.Tensor]:
    """Read a 3DGS PLY file into the dict :func:`save_ply` takes ("shN" only with higher bands).

    Raises:
        PlyFormatError: a property is missing or the number of ``f_rest_*`` is not 3 (K - 1).
    """
    try:
        vertex = PlyData.read(str(path))["vertex"]
    except Exception as exc:  # plyfile raises several error types for malformed files
        raise PlyFormatError(f"{path}: not a readable PLY file with a vertex element ({exc})") from exc
    names = set(vertex.data.dtype.names)
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [f"scale_{i}" for i in range(3)]
    required += [f"rot_{i}" for i in range(4)]
    missing = [name for name in required if name not in names]
    if missing:
        raise PlyFormatError(f"{path}: not a 3DGS scene, missing properties {missing}")

    def column(*keys: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.asarray(vertex[k], dtype=np.float64) for k in keys], axis=-1)).to(dtype)

    rest = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n.rsplit("_", 1)[1]))
    if len(rest) % 3:
        raise PlyFormatError(f"{path}: {len(rest)} f_rest_* properties is not a multiple of 3")
    out = {
        "means": column("x", "y", "z"),
        "scales": column("scale_0", "scale_1", "scale_2"),
        "quats": column("rot_0", "rot_1", "rot_2", "rot_3"),
        "opacities": column("opacity")[:, 0],
        "sh0": column("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :],
    }
    if rest:
        n, k = len(vertex.data), len(rest) // 3
        out["shN"] = column(*rest).reshape(n, 3, k).transpose(1, 2).contiguous()
    return out
