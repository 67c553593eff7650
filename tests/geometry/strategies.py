"""Hypothesis strategies for geometry tests: unit axes, angles with the hard cases, transforms."""

from __future__ import annotations

import math

import torch
from hypothesis import strategies as st

SPECIAL_ANGLES = [0.0, 1e-12, 1e-8, 1e-4, math.pi / 2, math.pi - 1e-6, math.pi - 1e-9, math.pi]

angles = st.one_of(st.sampled_from(SPECIAL_ANGLES), st.floats(0.0, math.pi, allow_nan=False))


@st.composite
def unit_axes(draw) -> torch.Tensor:
    """A unit 3-vector (float64), never degenerate."""
    v = draw(st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=3, max_size=3).filter(
        lambda v: math.sqrt(sum(x * x for x in v)) > 1e-3
    ))
    t = torch.tensor(v, dtype=torch.float64)
    return t / t.norm()


@st.composite
def rotation_vectors(draw) -> torch.Tensor:
    """An axis-angle vector (float64) whose angle includes 0, 1e-12, pi - 1e-9 and pi."""
    return draw(unit_axes()) * draw(angles)


@st.composite
def transforms(draw) -> torch.Tensor:
    """A random rigid transform [4, 4] (float64) with translation in [-2, 2] m."""
    from manisplat.geometry import make_transform, so3_exp

    t = torch.tensor(draw(st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3)), dtype=torch.float64)
    return make_transform(so3_exp(draw(rotation_vectors())), t)
