"""The C++ rasterizer's compositing on a real training iteration's inputs, against an earlier build.

``python -m benchmarks.bench_rasterizer_cpu EPISODE --warm-iters 500 --baseline 7de011e --out r.json``
builds the reconstruction of EPISODE as ``manisplat-reconstruct`` does, trains ``--warm-iters``
iterations on the CPU (so the Gaussians are densified as in a real run), then records the
compositing calls of one more iteration: the camera image (RGB and one alpha channel per scene
group) and the shadow map's light pass (one channel): depth sort, forward and backward (a
revision without the C++ depth sort is timed with ``torch.argsort``, as it sorted). Each call is then
timed with this checkout's build and with the build of the ``--baseline`` git revision's
``manisplat/splat/csrc`` (built into the same cache), alternating the two so that load on the
machine hits both alike, at 1 and 2 threads; medians and minima over ``--reps`` calls, and the
largest difference between the two builds' outputs.

Through the harness (``python -m benchmarks rasterizer_cpu``) it times this checkout's build
alone on the built-in sample (a baseline needs a git revision: use the command above).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import subprocess
import tempfile
import time
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

from benchmarks._harness import print_and_write_json

if TYPE_CHECKING:
    import torch

THREADED = False  # it sets 1 and 2 threads itself

REPO = Path(__file__).resolve().parent.parent
CSRC_IN_REPO = "manisplat/splat/csrc"


def baseline_sources(revision: str, into: Path) -> Path:
    """The rasterizer's C++ sources at git ``revision``, written into ``into``; raises with the
    git error when the revision or the files are not there."""
    from manisplat.splat.backends import cpu_raster

    into.mkdir(parents=True, exist_ok=True)
    for name in cpu_raster.SOURCE_NAMES + cpu_raster.HEADER_NAMES:
        done = subprocess.run(["git", "-C", str(REPO), "show", f"{revision}:{CSRC_IN_REPO}/{name}"],
                              capture_output=True)
        if done.returncode != 0:
            raise RuntimeError(f"git show {revision}:{CSRC_IN_REPO}/{name} failed: {done.stderr.decode().strip()}")
        (into / name).write_bytes(done.stdout)
    return into


class _TorchDepthOrder:
    """A build from before the C++ depth sort, with the sort its revision did in Python."""

    def __init__(self, extension: ModuleType) -> None:
        self._extension = extension

    def __getattr__(self, name: str):
        return getattr(self._extension, name)

    @staticmethod
    def depth_order(depths: torch.Tensor) -> torch.Tensor:
        import torch

        return torch.argsort(depths, stable=True)


def current_revision() -> str | None:
    """HEAD's short hash, with "+uncommitted" when the rasterizer's sources differ from HEAD's (the
    build timed as current is the working tree's)."""
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    if not head.stdout.strip():
        return None
    changed = subprocess.run(["git", "-C", str(REPO), "diff", "--quiet", "HEAD", "--", CSRC_IN_REPO])
    return head.stdout.strip() + ("+uncommitted" if changed.returncode else "")


def build_of(revision: str):
    """The C++ extension built from git ``revision``'s sources (built once into torch's cache,
    keyed by the sources as ever); a revision from before the C++ depth sort gets
    ``torch.argsort`` for it, as it sorted."""
    from manisplat.splat.backends import cpu_raster

    with tempfile.TemporaryDirectory() as tmp:
        extension = cpu_raster._load(baseline_sources(revision, Path(tmp)))
    return extension if hasattr(extension, "depth_order") else _TorchDepthOrder(extension)


def check_revision(parser: argparse.ArgumentParser, revision: str | None) -> None:
    """Exit through ``parser`` (status 2) unless ``revision`` names a commit of this repository."""
    if revision is None:
        return
    done = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--verify", "--quiet", f"{revision}^{{commit}}"],
                          capture_output=True)
    if done.returncode != 0:
        parser.error(f"{revision!r} is not a commit of {REPO} (git rev-parse)")


def record_calls(episode: Path, warm_iters: int, threads: int) -> tuple[list[tuple[str, list]], int]:
    """The compositing calls (``("forward" | "backward", arguments)``) of the training iteration
    after ``warm_iters`` iterations, and the number of Gaussians then."""
    import torch

    from benchmarks.bench_reconstruct_device import build_reconstruction
    from manisplat.reconstruct.config import TrainConfig
    from manisplat.splat.backends import cpu_raster

    torch.set_num_threads(threads)
    rec, _, _ = build_reconstruction(episode, TrainConfig(iters=warm_iters, device="cpu"))
    rec.train(progress=False)
    extension = cpu_raster.load_extension()
    calls: list[tuple[str, list]] = []

    class Recording:
        def __getattr__(self, name: str):
            return getattr(extension, name)

        def forward(self, *args):
            calls.append(("forward", [a.clone() if torch.is_tensor(a) else a for a in args]))
            return extension.forward(*args)

        def backward(self, *args):
            calls.append(("backward", [a.clone() if torch.is_tensor(a) else a for a in args]))
            return extension.backward(*args)

        def depth_order(self, depths):
            calls.append(("depth_order", [depths.clone()]))
            return extension.depth_order(depths)

    load = cpu_raster.load_extension
    cpu_raster.load_extension = Recording
    rec.config.iters = rec.step + 1
    rec.refit_exposure = lambda: None  # the end of training's exposure refit is not an iteration
    try:
        rec.train(progress=False)
    finally:
        cpu_raster.load_extension = load
    gaussians = sum(len(n.gaussians) for n in rec.graph.nodes())
    # the iteration's own calls end with its last backward (the evaluation at the end of
    # training renders more frames)
    last_backward = max(i for i, (kind, _) in enumerate(calls) if kind == "backward")
    return calls[: last_backward + 1], gaussians


def describe(calls: list[tuple[str, list]], i: int) -> dict:
    """What call ``i`` is: its pass (a depth sort belongs to the forward after it), size, channels."""
    kind, args = calls[i]
    if kind == "depth_order":
        following = next(j for j in range(i + 1, len(calls)) if calls[j][0] == "forward")
        return {**describe(calls, following), "call": kind}
    means2d, colors = args[0], args[3]
    width, height = (args[7], args[8]) if kind == "forward" else (args[11], args[12])
    channels = colors.shape[1]
    return {"pass": "shadow map (light)" if channels == 1 else "camera image", "call": kind,
            "gaussians": int(means2d.shape[0]), "size": f"{width}x{height}", "channels": int(channels)}


def compare(calls: list[tuple[str, list]], builds: dict, reps: int) -> list[dict]:
    """Rows of median / min ms per call and build, at 1 and 2 threads (builds alternated)."""
    import torch

    rows = []
    for threads in (1, 2):
        torch.set_num_threads(threads)
        for i, (kind, args) in enumerate(calls):
            functions = {name: getattr(ext, kind) for name, ext in builds.items()}
            outputs = {name: fn(*args) for name, fn in functions.items()}  # warm-up
            outputs = {name: out if isinstance(out, (list, tuple)) else [out] for name, out in outputs.items()}
            times: dict[str, list[float]] = {name: [] for name in builds}
            for _ in range(reps):
                for name, fn in functions.items():
                    t0 = time.perf_counter()
                    fn(*args)
                    times[name].append(time.perf_counter() - t0)
            first, *others = outputs.values()
            diff = max((float((a.double() - b.double()).abs().max()) for other in others for a, b in zip(first, other)
                        if a.numel()), default=0.0)
            row = {**describe(calls, i), "threads": threads}
            for name, ts in times.items():
                row[f"{name}_ms_median"] = round(statistics.median(ts) * 1e3, 2)
                row[f"{name}_ms_min"] = round(min(ts) * 1e3, 2)
            if len(builds) == 2:
                a, b = (row[f"{name}_ms_median"] for name in builds)
                row["speedup_median"] = round(b / a, 2)
            row["max_abs_output_difference"] = diff
            rows.append(row)
    return rows


def measure(episode: Path, *, warm_iters: int, baseline: str | None, reps: int) -> dict:
    import torch

    from manisplat.splat.backends import cpu_raster

    calls, gaussians = record_calls(episode, warm_iters, threads=2)
    builds = {"current": cpu_raster.load_extension()}
    if baseline:
        builds[f"baseline_{baseline}"] = build_of(baseline)
    return {
        "episode": str(episode), "warm_iters": warm_iters, "gaussians_after_warm_up": gaussians,
        "current": current_revision(), "baseline": baseline, "reps": reps,
        "rows": compare(calls, builds, reps),
        "torch": torch.__version__, "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "platform": platform.platform(), "processor": platform.processor() or platform.machine(),
    }


def run(ctx) -> list[dict]:
    """Harness entry: the built-in sample, this build alone (no baseline: that needs a revision)."""
    from manisplat.episode.synthetic import write_sample_episode

    with tempfile.TemporaryDirectory() as tmp:
        episode = write_sample_episode(Path(tmp) / "sample")
        result = measure(episode, warm_iters=20 if ctx.quick else 300, baseline=None, reps=5 if ctx.quick else 21)
    return result["rows"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_rasterizer_cpu", description=__doc__.splitlines()[0])
    p.add_argument("episode", type=Path)
    p.add_argument("--warm-iters", type=int, default=500, help="training iterations before the recorded one")
    p.add_argument("--baseline", help="git revision whose rasterizer sources to compare with (e.g. 7de011e)")
    p.add_argument("--reps", type=int, default=21)
    p.add_argument("--out", type=Path, help="write the result as JSON here")
    args = p.parse_args(argv)
    check_revision(p, args.baseline)
    print_and_write_json(measure(args.episode, warm_iters=args.warm_iters, baseline=args.baseline, reps=args.reps),
                         args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
