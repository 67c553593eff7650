"""Rendering helpers that are not the Gaussian rasterizer: a flat-shaded mesh painter, labelled sheets."""
