"""Shared plumbing for benchmarks: discovery, thread control, timing, tables and JSON output."""

from __future__ import annotations

import ast
import datetime as _dt
import importlib
import json
import os
import platform
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

BENCH_DIR = Path(__file__).resolve().parent
REPO_DIR = BENCH_DIR.parent


def shared_dir() -> Path:
    """The project's ``shared/`` folder (``$MANISPLAT_SHARED`` or ``../shared`` beside the repo)."""
    env = os.environ.get("MANISPLAT_SHARED")
    return Path(env) if env else REPO_DIR.parent / "shared"


class MissingBenchmarkData(RuntimeError):
    """A benchmark needs files (e.g. ``shared/data``) that are not on this machine."""


def simulator_python() -> Path:
    """``$MANISPLAT_SIMENV``: the python of a venv with mujoco that runs ``shared/tools/sim``."""
    simenv = os.environ.get("MANISPLAT_SIMENV")
    if not simenv:
        raise MissingBenchmarkData("set MANISPLAT_SIMENV to the python of a venv with mujoco (shared/tools/sim)")
    return Path(simenv)


@dataclass
class BenchContext:
    """What a benchmark's ``run`` receives.

    Attributes:
        threads: torch intra-op threads set for this run.
        quick: smaller sizes, for a smoke run.
        shared: path of the shared data folder (may not exist).
        out_dir: where the benchmark may write extra artefacts (plots).
    """

    threads: int
    quick: bool
    shared: Path
    out_dir: Path
    notes: list[str] = field(default_factory=list)

    def require_shared(self, *parts: str) -> Path:
        path = self.shared.joinpath(*parts)
        if not path.exists():
            raise MissingBenchmarkData(f"{path} not found (set MANISPLAT_SHARED to the shared folder)")
        return path


def print_and_write_json(result: dict, out: Path | None) -> None:
    """Print ``result`` as JSON (numpy floats as floats, other objects as strings) and write it to
    ``out`` as well when given (its folder made)."""
    import numpy as np

    text = json.dumps(result, indent=1, default=lambda x: float(x) if isinstance(x, np.floating) else str(x))
    print(text)
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text + "\n")


def time_call(fn: Callable[[], Any], *, repeat: int = 20, warmup: int = 3, min_time: float = 0.0) -> float:
    """Median wall time of ``fn()`` in seconds over ``repeat`` runs after ``warmup`` runs.

    With ``min_time`` > 0, each measurement loops ``fn`` until it has run that long and divides.
    """
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeat):
        n, start = 0, time.perf_counter()
        while True:
            fn()
            n += 1
            elapsed = time.perf_counter() - start
            if elapsed >= min_time:
                break
        samples.append(elapsed / n)
    return statistics.median(samples)


def list_benchmarks() -> dict[str, str]:
    """Benchmark name -> first docstring line, for every ``bench_*.py`` module (read from its
    source: listing them imports none, nor torch)."""
    found = {}
    for path in sorted(BENCH_DIR.glob("bench_*.py")):
        doc = ast.get_docstring(ast.parse(path.read_text()))
        found[path.stem.removeprefix("bench_")] = doc.strip().splitlines()[0] if doc else ""
    return found


def takes_own_options(name: str) -> bool:
    """Whether benchmark ``name`` declares ``OWN_OPTIONS = True`` (its own ``main(argv)``), read
    from its source so that ``python -m benchmarks NAME --help`` imports nothing heavy."""
    for node in ast.parse((BENCH_DIR / f"bench_{name}.py").read_text()).body:
        names = [t.id for t in node.targets if isinstance(t, ast.Name)] if isinstance(node, ast.Assign) else []
        if "OWN_OPTIONS" in names:
            return isinstance(node.value, ast.Constant) and node.value.value is True
    return False


def machine_info() -> dict[str, Any]:
    import torch

    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
    }


def format_table(rows: list[dict[str, Any]]) -> str:
    """A plain-text table of ``rows`` (columns in first-seen order; floats with 4 significant digits)."""
    if not rows:
        return "(no rows)"
    columns: list[str] = []
    for row in rows:
        columns += [k for k in row if k not in columns]

    def cell(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return "" if v is None else str(v)

    cells = [[cell(r.get(c)) for c in columns] for r in rows]
    widths = [max(len(c), *(len(r[i]) for r in cells)) for i, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths))]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(v.rjust(w) for v, w in zip(r, widths)) for r in cells]
    return "\n".join(lines)


def run_benchmark(name: str, *, threads: list[int], quick: bool, out_dir: Path) -> dict[str, Any]:
    """Run benchmark ``name`` once per thread count; print its table; write ``out_dir/NAME.json``."""
    import torch

    module = importlib.import_module(f"benchmarks.bench_{name}")
    threaded = getattr(module, "THREADED", True)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    notes: list[str] = []
    previous = torch.get_num_threads()
    try:
        for n in threads if threaded else [torch.get_num_threads()]:
            torch.set_num_threads(n)
            ctx = BenchContext(threads=n, quick=quick, shared=shared_dir(), out_dir=out_dir)
            for row in module.run(ctx):
                rows.append({"threads": n, **row} if threaded else row)
            notes += [m for m in ctx.notes if m not in notes]
    finally:
        torch.set_num_threads(previous)
    result = {
        "benchmark": name,
        "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "quick": quick,
        "machine": machine_info(),
        "rows": rows,
        "notes": notes,
    }
    print(f"== {name}: {(module.__doc__ or '').strip().splitlines()[0]}")
    print(format_table(rows))
    for note in notes:
        print(f"note: {note}")
    path = out_dir / f"{name}.json"
    path.write_text(json.dumps(result, indent=1, default=str) + "\n")
    print(f"wrote {path}")
    return result
