"""Importers: convert episodes recorded in other formats into ManiSplat episodes."""

from manisplat.episode.importers.act_hdf5 import import_act_hdf5

__all__ = ["import_act_hdf5"]
