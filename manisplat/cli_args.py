"""argparse types shared by the command-line tools: malformed numbers get a message naming them;
and option values shown as their flags read them."""

from __future__ import annotations

import argparse
import math
from typing import Any, Callable


def shown_value(value: Any, unset: str = "unset") -> str:
    """An option's value as its flag reads it: a switch as on / off, numbers as ``%g``, an option
    not given (None) as ``unset`` (or the word the flag takes for it)."""
    if value is None:
        return unset
    if isinstance(value, bool):
        return "on" if value else "off"
    return f"{value:g}" if isinstance(value, (int, float)) else str(value)


def numbers(count: tuple[int, ...]) -> Callable[[str], list[float]]:
    """An argparse type: comma-separated numbers, as many as one of ``count``."""
    def parse(text: str) -> list[float]:
        try:
            values = [float(v) for v in text.split(",")] if text else []
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected comma-separated numbers; got {text!r}") from None
        if len(values) not in count:
            raise argparse.ArgumentTypeError(f"expected {' or '.join(map(str, count))} numbers; got {len(values)}")
        return values

    return parse


def positive(kind: type = float) -> Callable[[str], Any]:
    """An argparse type: one finite number of ``kind`` (float or int) above 0."""
    return _checked(kind, lambda v: v > 0, "must be > 0")


def non_negative(kind: type = float) -> Callable[[str], Any]:
    """An argparse type: one finite number of ``kind`` (float or int) at or above 0."""
    return _checked(kind, lambda v: v >= 0, "must be >= 0")


def finite(kind: type = float) -> Callable[[str], Any]:
    """An argparse type: one finite number of ``kind`` (float or int), any sign."""
    return _checked(kind, lambda v: True, "must be a finite number")


def _checked(kind: type, accept: Callable[[Any], bool], requirement: str) -> Callable[[str], Any]:
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}; "
                                             f"got {text!r}") from None
        if not (math.isfinite(value) and accept(value)):
            raise argparse.ArgumentTypeError(f"{requirement}; got {text}")
        return value

    return parse


def bounded(low: float, high: float = math.inf, kind: type = float) -> Callable[[str], Any]:
    """An argparse type: one finite number of ``kind`` (float or int) from ``low`` to ``high``, both included."""
    requirement = f"must be >= {low:g}" if high == math.inf else f"must be in {low:g}..{high:g}"
    return _checked(kind, lambda v: low <= v <= high, requirement)


def open_fraction() -> Callable[[str], float]:
    """An argparse type: a number between 0 and 1, both excluded."""
    return _checked(float, lambda v: 0.0 < v < 1.0, "must be between 0 and 1, both excluded")


def open_fraction_or(words: tuple[str, ...]) -> Callable[[str], float | str]:
    """An argparse type: one of ``words``, or a number between 0 and 1, both excluded."""
    parse_fraction = open_fraction()

    def parse(text: str) -> float | str:
        if text in words:
            return text
        try:
            return parse_fraction(text)
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(f"expected {', '.join(words)} or a number between 0 and 1, both "
                                             f"excluded; got {text!r}") from None

    return parse


def finite_numbers(count: tuple[int, ...]) -> Callable[[str], list[float]]:
    """An argparse type: comma-separated finite numbers (no NaN or infinity), as many as one of ``count``."""
    parse_numbers = numbers(count)

    def parse(text: str) -> list[float]:
        values = parse_numbers(text)
        if not all(math.isfinite(v) for v in values):
            raise argparse.ArgumentTypeError(f"every number must be finite; got {text!r}")
        return values

    return parse


def pinhole_intrinsics() -> Callable[[str], list[float]]:
    """An argparse type: ``fx,fy,cx,cy`` in pixels, four finite numbers with fx and fy above 0."""
    parse_numbers = finite_numbers((4,))

    def parse(text: str) -> list[float]:
        values = parse_numbers(text)
        if not (values[0] > 0 and values[1] > 0):
            raise argparse.ArgumentTypeError(f"fx and fy must be > 0; got {text!r}")
        return values

    return parse


def add_version(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """``--version``: prints ``PROG VERSION`` (manisplat's) and exits 0."""
    from manisplat import __version__

    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    return parser
