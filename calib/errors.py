"""Errors of the calibration package: every failure names what is missing or degenerate."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


class CalibrationError(ValueError):
    """Calibration input or result is unusable (the message says why and what to do)."""


class NotEnoughDataError(CalibrationError):
    """Too few usable views, detections or corners to solve."""


class DegenerateMotionError(CalibrationError):
    """The robot motion does not determine the unknowns (e.g. every rotation about one axis)."""


class InputError(CalibrationError):
    """An input file is missing, unreadable or does not fit (board file, intrinsics, sizes)."""


def read_json(path: Path, what: str) -> Any:
    """The JSON in ``path``; a missing or unreadable file raises :class:`InputError` naming it as ``what``."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: {what} not found") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: cannot read {what}: {exc}") from None
