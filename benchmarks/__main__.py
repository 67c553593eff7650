"""python -m benchmarks [list | NAME... | all] [--threads 1,2] [--quick] [--out DIR]"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from benchmarks._harness import BENCH_DIR, MissingBenchmarkData, list_benchmarks, run_benchmark


def main(argv: list[str] | None = None) -> int:
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


if __name__ == "__main__":
    sys.exit(main())
