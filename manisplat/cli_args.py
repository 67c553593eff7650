"""argparse types shared by the command-line tools: malformed numbers get a message naming them."""

from __future__ import annotations

import argparse
import math
from typing import Any, Callable


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
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number; got {text!r}") from None
        if not (math.isfinite(value) and value > 0):
            raise argparse.ArgumentTypeError(f"must be > 0; got {text}")
        return value

    return parse
