"""The GPU measurements of issue 35, as one run on a lent CUDA machine (``benchmarks/device_run.sh``).

``python -m benchmarks.device_run --data DIR --out OUT [--steps ...] [--budget-s S]`` runs the
named steps in order and rewrites ``OUT/device.json`` after each one, so a run stopped at its time
limit still returns what it measured. ``DIR`` holds ``data/sim_pick_place_small`` and the robot
description it points to (``robots/``), as ``../shared`` does. Steps:

- ``tests``: the CUDA tests (``pytest -m cuda``-free: the files that hold them), pass/fail counts.
- ``iteration``: the built-in sample and sim_pick_place_small trained eagerly and compiled: ms
  per iteration over the run (compilation included) and after it, the phases' split, host-device
  syncs, held-out PSNR and pose error.
- ``cpu``: the same episodes on this machine's CPU with all its threads and with 2, for
  ``--cpu-iters`` iterations (the GPU runs record how long their first as many took).
- ``long``: sim_pick_place_small for ``--long-iters`` (the paper's 30 000 by default) compiled:
  wall time, the time the held-out PSNR first reaches 30 dB, the final metrics.
- ``hires``: the same at 640x480 (sim_pick_place_small upscaled 2x: the pixel count of a
  640x480 recording; its quality is that of a 320x240 one).
Steps that need what a machine lacks say so in the JSON and are skipped.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.bench_reconstruct_device import measure

STEPS = ("tests", "iteration", "cpu", "long", "hires")
VARIANTS = {"eager": "off", "compiled": "on"}
PROGRESS_EVERY = 2500  # iterations between the long runs' partial records
CUDA_TESTS = ["tests/reconstruct/test_device.py", "tests/splat/test_gsplat_backend.py", "-k", "cuda or gsplat"]


class Run:
    """The results so far, written to ``out/device.json`` after every step."""

    def __init__(self, out: Path, budget_s: float) -> None:
        self.out, self.budget_s, self.t0 = out, budget_s, time.perf_counter()
        self.results: dict = {"machine": _machine(), "steps": {}}
        out.mkdir(parents=True, exist_ok=True)  # steps write their logs beside device.json

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def record(self, step: str, value) -> None:
        self.results["steps"][step] = value
        self.results["elapsed_s"] = round(self.elapsed(), 1)
        (self.out / "device.json").write_text(json.dumps(self.results, indent=1, default=str) + "\n")
        print(f"[{self.elapsed():6.0f} s] {step}: {json.dumps(value, default=str)[:400]}", flush=True)


def _machine() -> dict:
    import torch

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {"node": platform.node(), "cpus": os.cpu_count(), "python": platform.python_version(),
            "torch": torch.__version__, "cuda": torch.version.cuda, "gpu": gpu}


def _train(run: Run, name: str, episode: Path, **kwargs) -> dict:
    """One ``measure`` run, recorded under ``name`` (an error is recorded, not raised)."""
    import torch

    torch._dynamo.reset()  # each variant compiles afresh (another mode, no stale cache entries)
    t0 = time.perf_counter()
    try:
        result = measure(episode, **kwargs)
    except Exception as exc:  # a failed variant must not lose the others' figures
        result = {"error": f"{type(exc).__name__}: {exc}"}
    result["wall_s"] = round(time.perf_counter() - t0, 1)
    from torch._dynamo.utils import counters

    result["dynamo"] = {"graphs": counters["stats"]["unique_graphs"], "breaks": sum(counters["graph_break"].values()),
                        "recompiles": sum(counters["recompiles"].values())}
    counters.clear()
    run.record(name, result)
    return result


def step_tests(run: Run, args) -> None:
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *CUDA_TESTS],
                          capture_output=True, text=True)
    (run.out / "tests_log.txt").write_text(proc.stdout + proc.stderr)  # the failures' reasons
    tail = proc.stdout.strip().splitlines()[-15:]
    run.record("tests", {"returncode": proc.returncode, "summary": tail, "s": round(time.perf_counter() - t0, 1)})


def step_iteration(run: Run, args) -> None:
    from manisplat.episode.synthetic import write_sample_episode

    sample = write_sample_episode(args.work / "sample")
    episodes = {"sample": (sample, args.sample_iters), "pp": (args.pp, args.pp_iters)}
    for label in args.episodes.split(","):
        episode, iters = episodes[label]
        for variant in args.variants.split(","):
            first = _FirstIterations(args.cpu_iters)
            result = _train(run, f"iteration/{label}/{variant}", episode, device="cuda", iters=iters,
                            compile=VARIANTS[variant], steady_iters=args.steady_iters, profile_iters=args.profile_iters,
                            sync_iters=10, threads=os.cpu_count(), callback=first)
            result[f"s_first_{args.cpu_iters}_iters"] = first.seconds
            run.record(f"iteration/{label}/{variant}", result)


class _FirstIterations:
    """A training callback: the seconds the first ``n`` iterations took (to compare with a CPU run
    of ``n`` iterations)."""

    def __init__(self, n: int) -> None:
        self.n, self.seconds = n, None

    def __call__(self, rec, seconds: float) -> None:
        if rec.step == self.n:
            self.seconds = round(seconds, 2)


def step_cpu(run: Run, args) -> None:
    from manisplat.episode.synthetic import write_sample_episode

    sample = write_sample_episode(args.work / "sample_cpu")
    episodes = {"sample": sample, "pp": args.pp}
    for label in args.cpu_episodes.split(","):
        for threads in (os.cpu_count(), 2):
            _train(run, f"cpu/{label}/{threads}_threads", episodes[label], device="cpu", iters=args.cpu_iters,
                   compile="off", steady_iters=0, profile_iters=0, sync_iters=0, threads=threads)


def _long_run(run: Run, name: str, episode: Path, iters: int, setting: str) -> None:
    """A full-budget run: the wall time at which the held-out PSNR (3 frames, every 250
    iterations) first reaches 30 dB, and the curve."""
    curve: list[tuple[int, float, float]] = []

    def track(rec, seconds: float) -> None:
        if rec.step % rec.config.eval_every == 0:
            curve.append((rec.step, round(seconds, 2), round(rec.held_out_psnr, 3)))
        if rec.step % PROGRESS_EVERY == 0:  # a run stopped at the call's limit keeps its curve so far
            gaussians = sum(len(n.gaussians) for n in rec.graph.nodes())
            run.record(f"{name}/progress", {"iteration": rec.step, "s": round(seconds, 1), "gaussians": gaussians,
                                            "psnr_curve": curve})

    result = _train(run, name, episode, device="cuda", iters=iters, compile=setting, steady_iters=0,
                    profile_iters=0, sync_iters=0, threads=os.cpu_count(), callback=track)
    reached = next(((step, s) for step, s, psnr in curve if psnr >= 30.0), None)
    result["psnr_curve"] = curve
    result["to_30_db"] = None if reached is None else {"iteration": reached[0], "s": reached[1]}
    run.record(name, result)


def step_long(run: Run, args) -> None:
    _long_run(run, "long/pp", args.pp, args.long_iters, args.long_compile)


def step_hires(run: Run, args) -> None:
    hires = upscaled_copy(args.pp, args.work / "pp_640x480", 2)
    _long_run(run, "hires/pp_640x480", hires, args.hires_iters, args.long_compile)


def upscaled_copy(src: Path, dst: Path, factor: int) -> Path:
    """A copy of the v1 episode ``src`` with its images ``factor`` times larger (colour bilinear,
    depth and masks nearest) and its intrinsics scaled to match (pixel centres kept)."""
    import cv2

    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("rgb", "depth", "masks"))
    for folder, interpolation in (("rgb", cv2.INTER_LINEAR), ("depth", cv2.INTER_NEAREST), ("masks", cv2.INTER_NEAREST)):
        if not (src / folder).is_dir():
            continue
        (dst / folder).mkdir()
        for path in sorted((src / folder).iterdir()):
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            big = cv2.resize(image, None, fx=factor, fy=factor, interpolation=interpolation)
            cv2.imwrite(str(dst / folder / path.name), big)
    meta = json.loads((src / "episode.json").read_text())
    camera = meta["camera"]
    camera["width"], camera["height"] = camera["width"] * factor, camera["height"] * factor
    K = camera["K"]
    K[0][0], K[1][1] = K[0][0] * factor, K[1][1] * factor
    K[0][2], K[1][2] = (K[0][2] + 0.5) * factor - 0.5, (K[1][2] + 0.5) * factor - 0.5
    description = meta["robot"].get("description")
    if description and not description.startswith("builtin:") and not Path(description).is_absolute():
        meta["robot"]["description"] = str((src / description).resolve())
    (dst / "episode.json").write_text(json.dumps(meta, indent=1))
    return dst


def save_compile_cache(out: Path) -> None:
    """Torch's compiled artefacts of this process (Inductor / Triton), for the next run to load."""
    import torch

    artifacts = torch.compiler.save_cache_artifacts()
    if artifacts is not None:
        (out / "compile_cache.bin").write_bytes(artifacts[0])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.device_run", description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, required=True, help="folder with data/sim_pick_place_small and robots/")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--steps", default=",".join(STEPS))
    p.add_argument("--budget-s", type=float, default=420.0, help="start no step after this many seconds")
    p.add_argument("--episodes", default="sample,pp", help="the iteration step's episodes (sample, pp)")
    p.add_argument("--variants", default=",".join(VARIANTS), help="the iteration step's variants")
    p.add_argument("--cpu-episodes", default="sample,pp", help="the cpu step's episodes (sample, pp)")
    p.add_argument("--sample-iters", type=int, default=700)
    p.add_argument("--pp-iters", type=int, default=700)
    p.add_argument("--steady-iters", type=int, default=100)
    p.add_argument("--profile-iters", type=int, default=30)
    p.add_argument("--cpu-iters", type=int, default=300,
                   help="iterations of each CPU run (the GPU runs also say how long their first as many took)")
    p.add_argument("--long-iters", type=int, default=30_000)
    p.add_argument("--hires-iters", type=int, default=30_000)
    p.add_argument("--long-compile", default="on", choices=tuple(VARIANTS.values()))
    p.add_argument("--compile-cache", type=Path, help="load torch's compiled artefacts saved by an earlier run")
    args = p.parse_args(argv)
    steps = args.steps.split(",")
    unknown = sorted(set(steps) - set(STEPS))
    if unknown:
        p.error(f"unknown steps {unknown}; choose from {', '.join(STEPS)}")
    args.pp = args.data / "data" / "sim_pick_place_small"
    args.work = Path(tempfile.mkdtemp(prefix="device_run_"))
    import torch

    if args.compile_cache and args.compile_cache.exists():
        torch.compiler.load_cache_artifacts(args.compile_cache.read_bytes())
    run = Run(args.out, args.budget_s)
    for step in steps:
        if run.elapsed() > args.budget_s:
            run.record(step, {"skipped": f"the budget of {args.budget_s:.0f} s was spent"})
            continue
        globals()[f"step_{step}"](run, args)
        save_compile_cache(args.out)  # after every step: a call stopped at its limit keeps it
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
