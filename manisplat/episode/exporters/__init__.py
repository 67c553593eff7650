"""Exporters: write ManiSplat episodes in the formats policy learners read (each imported on first use,
so one format's libraries load only when it is used)."""

from __future__ import annotations

from manisplat._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "act_hdf5": ("export_act_hdf5",),
    "lerobot": ("export_lerobot",),
})
