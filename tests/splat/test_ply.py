"""PLY in the 3DGS layout: round trip, the property names and order viewers expect, errors."""

from __future__ import annotations

import pytest
import torch
from plyfile import PlyData

from manisplat.splat import PlyFormatError, load_ply, save_ply


def scene(n=5, sh=True):
    g = torch.Generator().manual_seed(0)
    out = {"means": torch.randn(n, 3, generator=g), "scales": torch.randn(n, 3, generator=g),
           "quats": torch.randn(n, 4, generator=g), "opacities": torch.randn(n, generator=g),
           "sh0": torch.randn(n, 1, 3, generator=g)}
    if sh:
        out["shN"] = torch.randn(n, 15, 3, generator=g)
    return out


@pytest.mark.parametrize("sh", [True, False])
def test_round_trip_is_exact_in_float32(tmp_path, sh):
    splats = scene(sh=sh)
    back = load_ply(save_ply(tmp_path / "scene.ply", splats))
    assert set(back) == set(splats)
    for key in splats:
        assert torch.equal(back[key], splats[key].float()), key


def test_layout_matches_3dgs(tmp_path):
    splats = scene(n=2)
    path = save_ply(tmp_path / "scene.ply", splats)
    vertex = PlyData.read(str(path))["vertex"]
    names = list(vertex.data.dtype.names)
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert names[54:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    # channel-major f_rest: f_rest_1 is band 2 of red, f_rest_15 is band 1 of green
    assert float(vertex["f_rest_1"][0]) == float(splats["shN"][0, 1, 0])
    assert float(vertex["f_rest_15"][0]) == float(splats["shN"][0, 0, 1])
    assert PlyData.read(str(path)).byte_order == "<" and not PlyData.read(str(path)).text


def test_errors(tmp_path):
    bad = scene()
    bad["quats"] = bad["quats"][:, :3]
    with pytest.raises(ValueError, match="quats"):
        save_ply(tmp_path / "bad.ply", bad)
    nan = scene()
    nan["means"][0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        save_ply(tmp_path / "nan.ply", nan)
    (tmp_path / "junk.ply").write_bytes(b"not a ply")
    with pytest.raises(PlyFormatError):
        load_ply(tmp_path / "junk.ply")
