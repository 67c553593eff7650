"""The numeric CSV files (``frames.csv``, ``joints.csv``): a row-by-row scan that keeps every
problem, and the row formatter the writer uses (floats round-trip float64 exactly)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np


@dataclass(frozen=True)
class CsvRow:
    """One data line of a CSV file.

    Attributes:
        line: 1-based line number in the file (the header is line 1).
        text: the line as written, without its line break.
        values: one number per column, or None when the line does not parse.
        problem: why the line does not parse (None when it does).
    """

    line: int
    text: str
    values: tuple[float, ...] | None
    problem: str | None


@dataclass(frozen=True)
class CsvScan:
    """What a CSV file holds.

    Attributes:
        columns: the header's column names.
        header_problem: why the header is wrong (missing required columns, duplicates), or None.
        rows: every data line, parsed or not, in file order.
        ends_with_newline: False when the last line has no line break (a write cut short).
    """

    columns: tuple[str, ...]
    header_problem: str | None
    rows: list[CsvRow]
    ends_with_newline: bool

    def parsed(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lines (N,) int64, values (N, C) float64)`` of the rows that parsed."""
        good = [r for r in self.rows if r.values is not None]
        lines = np.array([r.line for r in good], dtype=np.int64)
        values = np.array([r.values for r in good], dtype=np.float64).reshape(len(good), len(self.columns))
        return lines, values

    @property
    def torn_tail(self) -> bool:
        """The last line is cut short: no line break at its end, or it does not parse."""
        return bool(self.rows) and (not self.ends_with_newline or self.rows[-1].values is None)


def header_problem(columns: Sequence[str], required: Sequence[str]) -> str | None:
    """Why ``columns`` is not a valid header for ``required`` leading columns, or None."""
    if tuple(columns[: len(required)]) != tuple(required):
        return f"header must start with {','.join(required)}; got {','.join(columns)}"
    repeated = sorted({c for c in columns if list(columns).count(c) > 1})
    if repeated:
        return f"header repeats the column(s) {', '.join(repeated)}"
    return None


def parse_row(text: str, columns: Sequence[str],
              int_columns: Sequence[str] = ()) -> tuple[tuple[float, ...] | None, str | None]:
    """``(values, None)`` for a well-formed line, ``(None, problem)`` otherwise.

    Every field must be a finite number; fields of ``int_columns`` must be integers.
    """
    fields = text.split(",")
    if len(fields) != len(columns):
        return None, f"has {len(fields)} fields, the header has {len(columns)}"
    values = []
    for name, field in zip(columns, fields):
        field = field.strip()
        try:
            value = float(int(field)) if name in int_columns else float(field)
        except ValueError:
            kind = "an integer" if name in int_columns else "a number"
            return None, f"column {name!r}: cannot parse {field!r} as {kind}"
        if not math.isfinite(value):
            return None, f"column {name!r} is {field} (must be finite)"
        values.append(value)
    return tuple(values), None


def scan_csv(path: Path, required: Sequence[str], int_columns: Sequence[str] = ()) -> CsvScan:
    """Parse ``path`` line by line, keeping every problem instead of stopping at the first.

    Raises FileNotFoundError when it is missing; an empty or non-UTF-8 file gives a
    ``header_problem`` and no rows.
    """
    data = Path(path).read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        return CsvScan((), f"not UTF-8 text: {exc}", [], True)
    if not text:
        return CsvScan((), "empty file (no header)", [], True)
    lines = text.split("\n")
    ends_with_newline = lines[-1] == ""
    if ends_with_newline:
        lines.pop()
    columns = tuple(c.strip() for c in lines[0].rstrip("\r").split(","))
    rows = []
    for number, line in enumerate(lines[1:], start=2):
        line = line.rstrip("\r")
        if not line.strip():
            rows.append(CsvRow(number, line, None, "empty line"))
            continue
        values, problem = parse_row(line, columns, int_columns)
        rows.append(CsvRow(number, line, values, problem))
    return CsvScan(columns, header_problem(columns, required), rows, ends_with_newline)


def format_row(values: Sequence[float | int]) -> str:
    """One CSV line (with its line break): integers as such, floats in the shortest form that
    reads back as the same float64 (``repr``)."""
    return ",".join(str(v) if isinstance(v, (int, np.integer)) else repr(float(v)) for v in values) + "\n"
