"""ManiSplat: one demonstration in, a Gaussian-splatting twin and new demonstrations out."""

__version__ = "0.1.0"
