"""Reconstruction on a device: ms per training iteration, its time split, and host-device syncs.

``python -m benchmarks.bench_reconstruct_device EPISODE --device cuda --iters 1000 --out r.json``
builds the reconstruction of EPISODE (load, plan, initialise, align: the CLI's setup), trains
``--iters`` iterations on ``--device`` and reports the training wall time and ms per iteration
(plain training, as ``manisplat-reconstruct`` runs it), then ``--profile-iters`` more iterations
with every phase timed separately (each phase waits for the device before and after it, so the
split adds up to a slower iteration than the plain one; the exposure refit that ends a training
run is left out): object poses, composition (with the shadow map, also timed alone), the main
rasterization, the loss, backward, densification and the optimizer step.
Eager runs count the tensor operations of ``--op-iters`` more iterations (each a kernel launch on
a GPU: what bounds a small scene's iteration there; the same count on the CPU).
On CUDA it also counts the host-device synchronisations of ``--sync-iters`` iterations
(``torch.cuda.set_sync_debug_mode``), by source line. The held-out PSNR and pose error of the
trained reconstruction are computed as ``metrics.json`` computes them.

Through the harness (``python -m benchmarks reconstruct_device``) it runs the built-in sample
on the CPU with the harness's thread counts.
"""

from __future__ import annotations

import argparse
import collections
import platform
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

from benchmarks._harness import print_and_write_json
from benchmarks.bench_rasterizer_cpu import check_revision
from manisplat.cli_args import non_negative

if TYPE_CHECKING:
    import torch

THREADED = True


def _sync(device: torch.device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def build_reconstruction(episode: Path, config):
    """(Reconstruction, alignments, setup seconds) as the CLI builds them."""
    from manisplat.reconstruct.data import load_episode_data
    from manisplat.reconstruct.pipeline import build
    from manisplat.reconstruct.plan import make_plan

    t0 = time.perf_counter()
    data = load_episode_data(episode)
    rec, alignments = build(data, make_plan(data), config)
    _sync(rec.device)
    return rec, alignments, time.perf_counter() - t0


class PhaseTimer:
    """Wraps functions so that each call is timed alone (device synchronised before and after)."""

    def __init__(self, device: torch.device) -> None:
        self.device, self.totals = device, collections.defaultdict(float)

    def wrap(self, name: str, fn):
        def timed(*args, **kwargs):
            _sync(self.device)
            t0 = time.perf_counter()
            out = fn(*args, **kwargs)
            _sync(self.device)
            self.totals[name] += time.perf_counter() - t0
            return out
        return timed


def profile_split(rec, iters: int) -> dict[str, float]:
    """ms per iteration of each phase over ``iters`` more iterations (see the module docstring)."""
    import torch

    import manisplat.reconstruct.trainer as trainer_module
    import manisplat.scene.render as render_module

    timer = PhaseTimer(rec.device)
    originals = (rec.losses, rec._step_and_densify, rec.object_poses, rec.graph.compose, render_module.rasterization,
                 trainer_module.frame_loss, torch.Tensor.backward)
    rec.losses = timer.wrap("forward (poses + compose + rasterize + loss)", rec.losses)
    rec.object_poses = timer.wrap("object poses (se3_exp)", rec.object_poses)
    rec.graph.compose = timer.wrap("compose (incl. shadow map)", rec.graph.compose)
    render_module.rasterization = timer.wrap("rasterize", render_module.rasterization)
    trainer_module.frame_loss = timer.wrap("loss (exposure, L1, SSIM, mask, pose)", trainer_module.frame_loss)
    torch.Tensor.backward = timer.wrap("backward", torch.Tensor.backward)
    rec.optimizer.step = timer.wrap("optimizer step", rec.optimizer.step)
    rec._step_and_densify = timer.wrap("optimizer step + densify", rec._step_and_densify)
    shadows = rec.graph.shadows
    if shadows is not None:
        shadows._shadow_map = timer.wrap("shadow map (light pass, in compose)", shadows._shadow_map)
    try:
        total = _train_more(rec, iters)
    finally:
        (rec.losses, rec._step_and_densify, rec.object_poses, rec.graph.compose, render_module.rasterization,
         trainer_module.frame_loss, torch.Tensor.backward) = originals
        for name in ("losses", "_step_and_densify", "object_poses"):
            rec.__dict__.pop(name, None)
        rec.optimizer.__dict__.pop("step", None)
        rec.graph.__dict__.pop("compose", None)
        if shadows is not None:
            shadows.__dict__.pop("_shadow_map", None)
    split = {k: round(v / iters * 1e3, 3) for k, v in timer.totals.items()}
    split["iteration (phases timed apart)"] = round(total / iters * 1e3, 3)
    return split


def steady_ms_per_iter(rec, iters: int) -> float:
    """ms per iteration of ``iters`` more plain iterations (after training: compiled code, if
    any, is ready; no densification once past its stop)."""
    return round(_train_more(rec, iters) / iters * 1e3, 3)


def _train_more(rec, iters: int) -> float:
    """Seconds ``iters`` more training iterations take, without the exposure refit that ends a
    training run (it renders every frame: not an iteration)."""
    rec.config.iters = rec.step + iters
    rec.refit_exposure = lambda: None
    _sync(rec.device)
    t0 = time.perf_counter()
    try:
        rec.train(progress=False)
        _sync(rec.device)
    finally:
        rec.__dict__.pop("refit_exposure", None)
    return time.perf_counter() - t0


def count_syncs(rec, iters: int) -> dict[str, int]:
    """CUDA only: host-device synchronisations in ``iters`` more iterations, by source line
    (the file named by its folder and name)."""
    counts: collections.Counter = collections.Counter()
    for site, n in rec.host_syncs(iters).items():
        path, line = site.rsplit(":", 1)
        counts[f"{Path(path).parent.name}/{Path(path).name}:{line}"] += n
    return dict(counts.most_common())


def tensor_ops_per_iter(rec, iters: int) -> dict:
    """Eager runs: the tensor operations (kernel launches on a GPU) of ``iters`` more iterations,
    per iteration: the total and the ten most frequent."""
    ops = rec.tensor_ops(iters)
    return {"total": round(ops.total / iters, 1),
            "most_frequent": {k: round(v / iters, 1) for k, v in ops.counts.most_common(10)}}


def quality(rec, alignments) -> dict:
    """Held-out PSNR/SSIM and pose error, as ``metrics.json`` (written to a temporary folder)."""
    from manisplat.reconstruct.outputs import write_evaluation

    with tempfile.TemporaryDirectory() as tmp:
        metrics = write_evaluation(rec, alignments, Path(tmp), wall_s=0.0)
    return {k: metrics.get(k) for k in ("psnr", "ssim", "pose", "pose_anchored", "pose_baseline")}


def measure(episode: Path, *, device: str, iters: int, profile_iters: int, sync_iters: int, threads: int | None,
            rasterizer_revision: str | None = None, compile: str = "off", steady_iters: int = 0,
            overrides: dict | None = None, callback=None, op_iters: int = 5) -> dict:
    """One training run on ``device`` and its measurements (see the module docstring).

    ``compile``: TrainConfig.compile; ``steady_iters``: iterations timed after training (compiled
    code ready); ``op_iters``: eager runs count the tensor operations of this many more iterations
    (0: not counted); ``overrides``: other TrainConfig fields; ``callback(rec, seconds_since_start)``
    is called after every training iteration."""
    import torch

    from manisplat.reconstruct.config import TrainConfig
    from manisplat.splat.backends import resolve_backend

    if threads:
        torch.set_num_threads(threads)
    if rasterizer_revision:  # a before/after of the rasterizer alone: the rest is this checkout
        from benchmarks.bench_rasterizer_cpu import build_of
        from manisplat.splat.backends import cpu_raster

        cpu_raster._extension = build_of(rasterizer_revision)
    config = TrainConfig(iters=iters, device=device, compile=compile, **(overrides or {}))
    rec, alignments, setup_s = build_reconstruction(episode, config)
    dev = rec.device
    resolve_backend(config.backend, dev)  # a first build of the C++ rasterizer is not training time
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    _sync(dev)
    t0 = time.perf_counter()
    rec.train(progress=False, callback=None if callback is None else lambda r: callback(r, time.perf_counter() - t0))
    _sync(dev)
    train_s = time.perf_counter() - t0
    result = {
        "episode": str(episode), "device": str(dev), "backend": config.backend, "iters": iters,
        "compiled": rec.compiled, "threads": torch.get_num_threads(), "setup_s": round(setup_s, 2),
        "train_s": round(train_s, 2), "ms_per_iter": round(train_s / iters * 1e3, 2),
        "gaussians": sum(len(n.gaussians) for n in rec.graph.nodes()),
        "quality": quality(rec, alignments),
        "rasterizer_revision": rasterizer_revision, "torch": torch.__version__, "machine": platform.node(),
        "gpu": torch.cuda.get_device_name(dev) if dev.type == "cuda" else None,
    }
    if dev.type == "cuda":
        result["peak_gpu_mib"] = round(torch.cuda.max_memory_allocated(dev) / 2 ** 20)
    if steady_iters:
        result["steady_ms_per_iter"] = steady_ms_per_iter(rec, steady_iters)
    if profile_iters:
        result["split_ms"] = profile_split(rec, profile_iters)
    if op_iters and rec.compiled is None:
        result["tensor_ops_per_iter"] = tensor_ops_per_iter(rec, op_iters)
    if sync_iters and dev.type == "cuda":
        result["syncs_in_%d_iters" % sync_iters] = count_syncs(rec, sync_iters)
    return result


def run(ctx) -> list[dict]:
    """Harness entry: the built-in sample on the CPU, ``ctx.threads`` threads."""
    from manisplat.episode.synthetic import write_sample_episode

    with tempfile.TemporaryDirectory() as tmp:
        episode = write_sample_episode(Path(tmp) / "sample")
        iters = 60 if ctx.quick else 300
        row = measure(episode, device="cpu", iters=iters, profile_iters=20 if ctx.quick else 50, sync_iters=0,
                      threads=ctx.threads)
    return [row]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_reconstruct_device", description=__doc__.splitlines()[0])
    p.add_argument("episode", type=Path)
    p.add_argument("--device", default="auto")
    p.add_argument("--iters", type=int, default=1000)
    p.add_argument("--profile-iters", type=int, default=50)
    p.add_argument("--sync-iters", type=int, default=20)
    p.add_argument("--op-iters", type=non_negative(int), default=5, help="eager runs: iterations whose tensor ops are counted (0: none)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    p.add_argument("--compile", default="off", choices=("auto", "on", "off"), help="TrainConfig.compile (default off)")
    p.add_argument("--steady-iters", type=int, default=0, help="iterations timed after training (compiled code ready)")
    p.add_argument("--rasterizer-revision", metavar="REV",
                   help="CPU: train with the C++ rasterizer of git revision REV (the rest is this checkout)")
    p.add_argument("--out", type=Path, help="write the result as JSON here")
    args = p.parse_args(argv)
    check_revision(p, args.rasterizer_revision)
    result = measure(args.episode, device=args.device, iters=args.iters, profile_iters=args.profile_iters,
                     sync_iters=args.sync_iters, threads=args.threads, rasterizer_revision=args.rasterizer_revision,
                     compile=args.compile, steady_iters=args.steady_iters, op_iters=args.op_iters)
    print_and_write_json(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
