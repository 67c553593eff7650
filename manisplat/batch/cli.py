"""manisplat-batch: many episodes through validate -> reconstruct -> augment -> one dataset, on Ray.

Only argparse and light modules are imported until the arguments are accepted.
"""

from __future__ import annotations

import argparse
import importlib.util
import textwrap
import logging
import sys
from pathlib import Path

from manisplat.batch.config import EXAMPLE
from manisplat.cli_args import add_version, positive
from manisplat.exit_codes import ExitCode, exit_status_help
from manisplat.threads import THREADS_HELP, use_threads

EPILOG = """\
PIPELINE.toml (paths relative to its folder), for example:

""" + textwrap.indent(EXAMPLE, "  ") + """
Each stage of each episode is a Ray task with its resources; `ray.init()` starts a local cluster
(nothing to set up on one machine) and --address joins an existing one, whose machines must all see
PIPELINE.toml's episode and output paths at the same place (a shared filesystem). Outputs:
OUT/validate/<ep>.json, OUT/recon/<ep>/, OUT/aug/<ep>/, OUT/dataset/, OUT/errors/, OUT/batch.json.
Each is written under a hidden .partial- name and renamed when complete: a killed task never leaves
something that looks done, and running the same command again does only what is missing. A task
whose process crashes or dies is retried (retries.max), then reported; the other episodes go on.
Without Ray installed, the same pipeline runs one task after another in this process
(pip install 'manisplat[distributed]' for Ray).

""" + exit_status_help({
    ExitCode.OK: "every stage complete",
    ExitCode.FAILED: "a stage failed (see the table and OUT/errors/)",
    ExitCode.BAD_INPUT: "bad arguments; a PIPELINE.toml that is wrong (named) or asks for more CPUs or GPUs than any\n"
                        "node of the local Ray cluster has; `status` of a folder that holds no batch",
    ExitCode.INTERRUPTED: "interrupted (finished outputs stay, partial ones never look complete)",
})


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="manisplat-batch", epilog=EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                description="Reconstruct, augment and export many episodes, on a Ray cluster or "
                                            "one after another.")
    sub = p.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run (or finish) a batch", epilog=EPILOG,
                         formatter_class=argparse.RawDescriptionHelpFormatter,
                         description="Run every stage of PIPELINE.toml that is not complete yet.")
    run.add_argument("pipeline", type=Path, metavar="PIPELINE.toml",
                     help="which episodes, where the outputs go and each stage's settings (example below)")
    run.add_argument("--address", help="join this Ray cluster (default: start a local one)")
    run.add_argument("--workers", type=positive(int), metavar="N",
                     help="CPUs of the local Ray cluster (default: all of this machine's)")
    run.add_argument("--sequential", action="store_true",
                     help="run the tasks one after another in this process, without Ray (default when Ray is "
                          "not installed)")
    run.add_argument("--threads", type=positive(int), metavar="N",
                     help=THREADS_HELP + " when the tasks run here, one after another; on Ray each task uses as many "
                                         "as the CPUs it is given")
    run.add_argument("-q", "--quiet", action="store_true", help="no progress bar, warnings only")
    status = sub.add_parser("status", help="the state of a batch, read from its output folder",
                            description="Per episode and stage: complete, running (a partial output with its "
                                        "process id), failed (OUT/errors/) or pending.")
    status.add_argument("out", type=Path, metavar="OUT", help="the batch's output folder")
    return add_version(p)


def table(rows: list) -> str:
    """The summary table: episode, stage, status, seconds, metrics."""
    lines = [f"{'episode':24s} {'stage':12s} {'status':9s} {'time':>8s}  metrics"]
    for r in rows:
        metrics = ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in r.metrics.items())
        seconds = f"{r.seconds:7.1f}s" if r.seconds else ""
        lines.append(f"{r.episode:24s} {r.stage:12s} {r.status:9s} {seconds:>8s}  {metrics}")
    return "\n".join(lines)


def _run(args: argparse.Namespace) -> int:
    from manisplat.batch.config import BatchConfigError, load_config
    from manisplat.batch.runner import LocalExecutor, RayExecutor, run_batch, unfit_reconstruction

    try:
        config = load_config(args.pipeline)
    except BatchConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return ExitCode.BAD_INPUT
    has_ray = importlib.util.find_spec("ray") is not None
    if args.address and (args.sequential or not has_ray):
        print("error: --address needs Ray (pip install 'manisplat[distributed]') and no --sequential", file=sys.stderr)
        return ExitCode.BAD_INPUT
    if args.sequential or not has_ray:
        if not has_ray:
            print("Ray is not installed: running the tasks one after another here "
                  "(pip install 'manisplat[distributed]' to run them in parallel)", file=sys.stderr)
        use_threads(args.threads)
        executor = LocalExecutor()
    else:
        executor = RayExecutor(args.address, config.max_retries, num_cpus=args.workers)
        if problem := unfit_reconstruction(config, executor.nodes()):
            if args.address is None:  # a local cluster does not grow: its tasks would wait forever
                executor.shutdown()
                print(f"error: {problem}: its reconstructions would never start; lower it or give "
                      "--workers more CPUs", file=sys.stderr)
                return ExitCode.BAD_INPUT
            print(f"warning: {problem}: its reconstructions wait until such a node joins", file=sys.stderr)
    print(f"{len(config.episodes)} episodes -> {config.out} on {executor.name}", file=sys.stderr)
    try:
        results = run_batch(config, executor, progress=not args.quiet and sys.stderr.isatty())
    except KeyboardInterrupt:
        print("\ninterrupted: finished outputs stay; run the same command again to do the rest", file=sys.stderr)
        return ExitCode.INTERRUPTED
    finally:
        executor.shutdown()
    print(table(results))
    failed = [r for r in results if r.status in ("failed", "blocked")]
    if failed:
        print(f"{sum(r.status == 'failed' for r in failed)} stage(s) failed; errors in {config.out / 'errors'}",
              file=sys.stderr)
    return ExitCode.FAILED if failed else ExitCode.OK


def _status(args: argparse.Namespace) -> int:
    from manisplat.batch.runner import batch_status

    try:
        rows = batch_status(args.out)
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return ExitCode.BAD_INPUT
    print(table(rows))
    return ExitCode.OK


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING if getattr(args, "quiet", False) else logging.INFO,
                        format="%(message)s")
    return _run(args) if args.command == "run" else _status(args)


if __name__ == "__main__":
    sys.exit(main())
