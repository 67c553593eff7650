"""PIPELINE.toml: which episodes, where the outputs go, and each stage's settings (``EXAMPLE``)."""

from __future__ import annotations

import glob
from dataclasses import dataclass
from pathlib import Path
from typing import Any

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11
    import tomli as tomllib

EXPORT_FORMATS = ("lerobot", "act-hdf5")
DEVICES = ("cpu", "cuda", "auto")

EXAMPLE = """\
episodes = ["recordings/*/"]          # globs or folders, relative to the TOML's folder
out = "batch_out"                      # shared by every machine of the cluster

[reconstruct]
iters = 3000
device = "cpu"                         # "cuda": the task asks Ray for `gpus` GPUs
cpus = 2                               # CPUs a reconstruction task asks Ray for
gpus = 1                               # with device "cuda"; a fraction lets tasks share a GPU

[augment]
n = 20
seed = 0

[export]
format = "lerobot"                     # or "act-hdf5"
task = "pick the box and place it on the mat"   # default: each episode's own

[retries]
max = 2                                # a crashed task or dead worker is retried this often
"""
"""A complete PIPELINE.toml, every key with its meaning (the help of ``manisplat-batch run`` prints it)."""


class BatchConfigError(ValueError):
    """PIPELINE.toml is unreadable or names something wrong (the key and the problem named)."""


@dataclass(frozen=True)
class BatchConfig:
    """A batch: episode folders (resolved), the output folder and the stages' settings."""

    episodes: tuple[Path, ...]
    out: Path
    iters: int = 1000
    device: str = "cpu"
    reconstruct_cpus: float = 1.0
    gpus_per_task: float = 1.0
    n: int = 10
    seed: int = 0
    export_format: str = "lerobot"
    task: str | None = None
    max_retries: int = 2

    @property
    def reconstruct_gpus(self) -> float:
        """GPUs a reconstruction task asks Ray for: ``gpus_per_task`` on CUDA, none otherwise."""
        return self.gpus_per_task if self.device == "cuda" else 0.0


def _get(table: dict[str, Any], key: str, kind: type | tuple[type, ...], default: Any, where: str) -> Any:
    value = table.get(key, default)
    if value is not None and (not isinstance(value, kind) or isinstance(value, bool)):
        name = "a number" if isinstance(kind, tuple) else kind.__name__
        raise BatchConfigError(f"{where}{key}: expected {name}, got {value!r}")
    return value


def _episodes(patterns: list[str], base: Path) -> tuple[Path, ...]:
    found: list[Path] = []
    for pattern in patterns:
        full = pattern if Path(pattern).is_absolute() else str(base / pattern)
        matches = sorted(Path(p) for p in glob.glob(full) if Path(p).is_dir())
        if not matches:
            raise BatchConfigError(f"episodes: {pattern!r} matches nothing (relative to {base})")
        found += [m for m in matches if m not in found]
    names = [p.name for p in found]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise BatchConfigError(f"episodes: several folders named {duplicates}; outputs are named after the "
                               "episode folder, so names must be unique")
    return tuple(p.resolve() for p in found)


def load_config(path: str | Path) -> BatchConfig:
    """Read ``PIPELINE.toml``; relative paths in it are relative to its folder.

    Raises:
        BatchConfigError: unreadable TOML, a missing or mistyped key, a glob matching nothing.
    """
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise BatchConfigError(f"{path}: {exc}") from exc
    base = path.resolve().parent
    patterns = raw.get("episodes")
    if not isinstance(patterns, list) or not patterns or not all(isinstance(p, str) for p in patterns):
        raise BatchConfigError(f"{path}: episodes: expected a list of folders or globs")
    out = _get(raw, "out", str, None, "")
    if out is None:
        raise BatchConfigError(f"{path}: out: the output folder is required")
    recon, aug, export, retries = (raw.get(k, {}) for k in ("reconstruct", "augment", "export", "retries"))
    config = BatchConfig(
        episodes=_episodes(patterns, base), out=(base / out).resolve(),
        iters=_get(recon, "iters", int, 1000, "reconstruct."), device=_get(recon, "device", str, "cpu", "reconstruct."),
        reconstruct_cpus=float(_get(recon, "cpus", (int, float), 1, "reconstruct.")),
        gpus_per_task=float(_get(recon, "gpus", (int, float), 1, "reconstruct.")),
        n=_get(aug, "n", int, 10, "augment."), seed=_get(aug, "seed", int, 0, "augment."),
        export_format=_get(export, "format", str, "lerobot", "export."), task=_get(export, "task", str, None, "export."),
        max_retries=_get(retries, "max", int, 2, "retries."))
    if (config.iters < 1 or config.n < 1 or config.max_retries < 0 or config.reconstruct_cpus <= 0
            or not 0 < config.gpus_per_task <= 1 and config.gpus_per_task != int(config.gpus_per_task)):
        raise BatchConfigError(f"{path}: reconstruct.iters and augment.n must be >= 1, retries.max >= 0, "
                               "reconstruct.cpus > 0, reconstruct.gpus a fraction in (0, 1] or a whole number")
    if config.device not in DEVICES:
        raise BatchConfigError(f"{path}: reconstruct.device must be one of {DEVICES}; got {config.device!r}")
    if config.export_format not in EXPORT_FORMATS:
        raise BatchConfigError(f"{path}: export.format must be one of {EXPORT_FORMATS}; got {config.export_format!r}")
    return config
