"""The rule every command that writes a results folder follows: ``--out`` is new or empty, unless
the user said what to do with what is there."""

from __future__ import annotations

from pathlib import Path


def check_output_folder(out: Path, *, allowed: bool, refusal: str, error: type[Exception] = ValueError) -> bool:
    """Whether ``out`` holds anything; raises ``error`` when it exists and is not a folder, or holds
    something and ``allowed`` (e.g. ``--overwrite``) is False, with ``refusal`` (what to pass
    instead) after "--out OUT is not empty"."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise error(f"--out {out} exists and is not a folder")
    in_use = out.is_dir() and any(out.iterdir())
    if in_use and not allowed:
        raise error(f"--out {out} is not empty{refusal}")
    return in_use


def new_or_empty_folder(out: str | Path) -> Path:
    """``out`` as a Path when it does not exist or is an empty folder, else a ValueError naming it
    (for tools with no ``--overwrite``, such as the examples: they never write into their inputs)."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"{out} is not a new or empty folder; choose one that is (nothing already there is touched)")
    return out
