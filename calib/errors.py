"""Errors of the calibration package: every failure names what is missing or degenerate."""

from __future__ import annotations


class CalibrationError(ValueError):
    """Calibration input or result is unusable (the message says why and what to do)."""


class NotEnoughDataError(CalibrationError):
    """Too few usable views, detections or corners to solve."""


class DegenerateMotionError(CalibrationError):
    """The robot motion does not determine the unknowns (e.g. every rotation about one axis)."""


class InputError(CalibrationError):
    """An input file is missing, unreadable or does not fit (board file, intrinsics, sizes)."""
