"""Exporters: write ManiSplat episodes in the formats policy learners read."""

from manisplat.episode.exporters.act_hdf5 import export_act_hdf5

__all__ = ["export_act_hdf5"]
