"""python -m benchmarks [list | NAME... | all] [--threads 1,2] [--quick] [--out DIR]

A benchmark with options of its own (``OWN_OPTIONS = True`` and ``main(argv)``, e.g. policy_sim) runs alone:
``python -m benchmarks NAME [its options]``."""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from benchmarks._harness import BENCH_DIR, MissingBenchmarkData, list_benchmarks, run_benchmark, takes_own_options


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    own = _own_main(argv[0]) if argv else None
    if own is not None:
        try:
            return own(argv[1:])
        except MissingBenchmarkData as exc:
            print(f"{argv[0]}: skipped: {exc}", file=sys.stderr)
            return 2
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks",
        description="Run ManiSplat benchmarks: each prints a table and writes NAME.json.",
    )
    parser.add_argument("names", nargs="*", default=["list"], help="benchmark names, 'all', or 'list' (default)")
    parser.add_argument("--threads", default="1,2", help="comma-separated torch thread counts (default 1,2)")
    parser.add_argument("--quick", action="store_true", help="small sizes: a smoke run, not a measurement")
    parser.add_argument("--out", type=Path, default=BENCH_DIR / "results", help="output folder for JSON/plots")
    args = parser.parse_args(argv)

    available = list_benchmarks()
    if args.names == ["list"]:
        for name, summary in available.items():
            print(f"{name:24s} {summary}")
        return 0
    names = list(available) if args.names == ["all"] else args.names
    unknown = [n for n in names if n not in available]
    if unknown:
        parser.error(f"unknown benchmark(s) {unknown}; available: {sorted(available)}")
    threads = [int(t) for t in args.threads.split(",")]
    status = 0
    for name in names:
        try:
            run_benchmark(name, threads=threads, quick=args.quick, out_dir=args.out)
        except MissingBenchmarkData as exc:
            print(f"{name}: skipped: {exc}", file=sys.stderr)
            status = 2
    return status


def _own_main(name: str):
    """The ``main(argv)`` of benchmark ``name`` when it takes options of its own, else None."""
    if name.startswith("-") or not (BENCH_DIR / f"bench_{name}.py").exists() or not takes_own_options(name):
        return None
    return importlib.import_module(f"benchmarks.bench_{name}").main


if __name__ == "__main__":
    sys.exit(main())
