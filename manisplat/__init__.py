"""ManiSplat: one demonstration in, a Gaussian-splatting twin and new demonstrations out."""

from manisplat.threads import sleep_when_idle

sleep_when_idle()  # before torch loads OpenMP (manisplat.threads)

__version__ = "0.1.0"
