"""Importers: convert episodes recorded in other formats into ManiSplat episodes (each imported on
first use, so one format's libraries load only when it is used)."""

from __future__ import annotations

from manisplat._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "act_hdf5": ("import_act_hdf5",),
    "cobot_magic": ("import_cobot_magic", "load_calibration"),
    "lerobot": ("import_lerobot",),
})
