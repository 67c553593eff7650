"""The joint and gripper units of an imported dataset, as the user declares them (``--units JOINT,GRIPPER``).

PiPER's LeRobot plugins store state and action under the same key names in different units:
radians and metres, degrees and millimetres, or values normalised to +-100 by a calibration the
dataset does not carry. Nothing in a dataset says which, so a multi-arm import needs them declared;
:func:`unit_problems` refuses values that cannot be in the declared units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from manisplat.episode.format import EpisodeFormatError

JOINT_UNITS = {"rad": 1.0, "deg": math.pi / 180.0}
"""Joint unit -> radians per unit."""
GRIPPER_UNITS = {"m": 1.0, "mm": 0.001}
"""Gripper unit -> metres per unit."""
NORMALISED = ("norm100", "normalized", "normalised")
MAX_RAD = 2.0 * math.pi
"""No joint of an arm ManiSplat knows turns past one revolution: larger values are not radians."""
MAX_GAP_M = 0.2
"""No gripper ManiSplat knows opens 20 cm: larger values are not metres."""
HELP = ("--units JOINT,GRIPPER: rad,m (what ManiSplat exports, lerobot-robot-piper's SI mode), deg,mm, deg,m or "
        "rad,mm")


@dataclass(frozen=True)
class Units:
    """Declared units of a dataset's 7 values per arm (6 joints, gripper).

    Attributes:
        joint: ``rad`` or ``deg``.
        gripper: ``m`` or ``mm``.
    """

    joint: str
    gripper: str

    def scale(self) -> np.ndarray:
        """(7,) float64 factors to radians (6 joints) and metres (gripper); exactly 1.0 for ``rad,m``."""
        return np.array([JOINT_UNITS[self.joint]] * 6 + [GRIPPER_UNITS[self.gripper]])

    def __str__(self) -> str:
        return f"{self.joint},{self.gripper}"


def parse_units(text: str) -> Units:
    """``"rad,m"`` -> :class:`Units`; raises :class:`ValueError` naming the accepted forms (and why
    values normalised to +-100 cannot be read)."""
    if text.strip().lower() in NORMALISED:
        raise ValueError(f"{text!r}: values normalised to +-100 depend on the per-joint ranges of the calibration "
                         "that recorded them, which a LeRobot dataset does not store; convert them to degrees or "
                         "radians with that calibration first")
    parts = [p.strip().lower() for p in text.split(",")]
    if len(parts) != 2 or parts[0] not in JOINT_UNITS or parts[1] not in GRIPPER_UNITS:
        raise ValueError(f"{text!r}: expected {HELP}")
    return Units(*parts)


def unit_problems(values: np.ndarray, units: Units, what: str) -> list[str]:
    """Why ``values`` (T, 7) [6 joints, gripper] of one arm, as stored, cannot be in ``units``."""
    problems = []
    joints, gripper = np.abs(values[:, :6]), values[:, 6]
    if units.joint == "rad" and joints.size and joints.max() > MAX_RAD:
        problems.append(f"{what}: joints up to {joints.max():.4g} are not radians (more than a revolution); "
                        "degrees? (--units deg,...)")
    if units.gripper == "m" and gripper.size and gripper.max() > MAX_GAP_M:
        problems.append(f"{what}: gripper values up to {gripper.max():.4g} are not metres (a {gripper.max():.4g} m "
                        "opening); millimetres? (--units ...,mm)")
    return problems


def describe_ranges(values: np.ndarray, what: str) -> str:
    """``what: joints -95.2..120.1, gripper 0..70`` of (T, 7) stored values, for a refusal that asks for units."""
    return (f"{what}: joints {values[:, :6].min():.4g}..{values[:, :6].max():.4g}, "
            f"gripper {values[:, 6].min():.4g}..{values[:, 6].max():.4g}")


def require_units(units: Units | None, ranges: list[str], where: str) -> Units:
    """``units``, or :class:`EpisodeFormatError` saying that they must be declared, with the stored
    value ranges (``ranges``, from :func:`describe_ranges`) to help tell them."""
    if units is not None:
        return units
    raise EpisodeFormatError(f"{where}: the joint and gripper units are not declared, and a LeRobot dataset does "
                             f"not say them (PiPER plugins write radians/metres, degrees/millimetres or values "
                             f"normalised to +-100 under the same names); stored values: {'; '.join(ranges)}; "
                             f"give {HELP}")
