"""Jobs beside busy processes: the sample's reconstruction and a twin's rendering, idle and beside 1 and 2 CPU hogs.

``python -m benchmarks.bench_contention [--before REV] [--out FILE]`` times, each in a new process
as a user runs them, ``manisplat-reconstruct SAMPLE --iters 100`` (wall time of the command) and
``Twin.render_frame`` over 20 frames of its twin (seconds after loading), on an idle machine and
beside 1 and 2 hogs of two kinds: "spin", a process that keeps one core busy (a Python loop), and
"torch", another PyTorch job on the CPU with PyTorch's own defaults (a thread per core, small
matrix products in a loop: what a second reconstruction or a training job is to this one). With
``--before REV`` the same for a revision's tree (checked out in a temporary worktree). Goal
(issue 31): each time beside k hogs within 1.5x of the idle time scaled by the job's fair share
of the cores: ``cores / max(cores - k, cores / (k + 1))`` beside one-core hogs (2 cores: 3x beside
one, 4.5x beside two), ``k + 1`` beside hogs that want every core.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager, nullcontext
from pathlib import Path

from benchmarks._harness import REPO_DIR, print_and_write_json

THREADED = False  # each job sets its own threads (the defaults under test)
HOGS = (0, 1, 2)
ITERS, FRAMES = 100, 20
HOG_SCRIPTS = {
    "spin": "while True: pass",
    "torch": "import torch\nx = torch.randn(256, 256)\nwhile True:\n    (x @ x).sin_().sum()",
}

RENDER = """
import sys, time
from manisplat.twin import Twin
twin = Twin.load(sys.argv[1])
twin.render_frame(0)
t0 = time.perf_counter()
for i in range({frames}):
    twin.render_frame(i % twin.n_frames)
print(time.perf_counter() - t0)
"""


@contextmanager
def hogs(kind: str, k: int):
    """``k`` busy processes of ``kind`` (:data:`HOG_SCRIPTS`), for the duration of the block."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMP_", "GOMP_"))}  # their own defaults
    procs = [subprocess.Popen([sys.executable, "-c", HOG_SCRIPTS[kind]], env=env) for _ in range(k)]
    try:
        time.sleep(3.0 if k else 0.0)  # started (torch imported) before the job
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


def _env(tree: Path) -> dict[str, str]:
    """The environment of a job run from ``tree`` (also its working folder, which Python puts
    first on the path): no thread settings of our own (the defaults under test)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMP_", "MKL_", "OPENBLAS_", "GOMP_"))}
    env["PYTHONPATH"] = str(tree)
    return env


def reconstruct_s(tree: Path, episode: Path, out: Path) -> tuple[float, int | None]:
    """(wall seconds of the reconstruction command run from ``tree``, the threads its log says it
    chose, None when it says none)."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "manisplat.reconstruct.cli", str(episode), "--out", str(out),
                           "--iters", str(ITERS), "--overwrite"], env=_env(tree), cwd=tree, check=True,
                           capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    chosen = re.search(r"using (\d+) CPU thread", proc.stderr)
    return seconds, int(chosen.group(1)) if chosen else None


def render_s(tree: Path, twin: Path) -> float:
    """Seconds of rendering FRAMES frames of ``twin`` (after loading it), run from ``tree``."""
    proc = subprocess.run([sys.executable, "-c", RENDER.format(frames=FRAMES), str(twin)], env=_env(tree), cwd=tree,
                          check=True, capture_output=True, text=True)
    return float(proc.stdout.strip().splitlines()[-1])


def settle(limit_s: float = 240.0) -> None:
    """Wait (at most ``limit_s``) until the machine is idle: the 1-minute load average below 0.3."""
    t0 = time.perf_counter()
    while os.getloadavg()[0] > 0.3 and time.perf_counter() - t0 < limit_s:
        time.sleep(5)


def allowed_ratio(kind: str, k: int, cores: int) -> float:
    """1.5x the idle time scaled by the fair share of ``cores`` beside ``k`` hogs of ``kind``."""
    return 1.5 * (cores / max(cores - k, cores / (k + 1)) if kind == "spin" else k + 1)


def measure(tree: Path, label: str, work: Path) -> dict:
    """Both jobs from ``tree``, idle and beside each number of hogs."""
    from manisplat.episode.synthetic import write_sample_episode

    episode = write_sample_episode(work / f"sample_{label}")
    twin = work / f"twin_{label}"
    reconstruct_s(tree, episode, twin)  # the twin to render (and the C++ rasterizer built)
    cores = len(os.sched_getaffinity(0))
    rows = {}
    for kind, k in [("idle", 0)] + [(kind, k) for kind in HOG_SCRIPTS for k in HOGS[1:]]:
        if not k:
            settle()
        with hogs(kind, k) if k else nullcontext():
            seconds, chosen = reconstruct_s(tree, episode, work / f"out_{label}")
            row = {"reconstruct_s": round(seconds, 2), "reconstruct_threads": chosen,
                   "render_ms_per_frame": round(render_s(tree, twin) / FRAMES * 1e3, 1)}
        if k:
            limit = allowed_ratio(kind, k, cores)
            for job in ("reconstruct_s", "render_ms_per_frame"):
                ratio = row[job] / rows["idle"][job]
                row[job.split("_")[0] + "_ratio"] = round(ratio, 2)
                row[job.split("_")[0] + "_within_goal"] = ratio <= limit
            row["goal_ratio"] = round(limit, 2)
        rows["idle" if not k else f"{k} {kind}"] = row
        print(label, kind, k, row, flush=True)
    return {"tree": label, "cores": cores, "by_load": rows}


def run(ctx) -> list[dict]:
    """Harness entry: this checkout's defaults (rows by number of hogs)."""
    with tempfile.TemporaryDirectory(prefix="contention_") as work:
        result = measure(REPO_DIR, "this checkout", Path(work))
    return [{"beside": k, **row} for k, row in result["by_load"].items()]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_contention", description=__doc__.splitlines()[0])
    p.add_argument("--before", metavar="REV", help="also measure the thread defaults of git revision REV")
    p.add_argument("--out", type=Path, help="write the result as JSON here")
    args = p.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="contention_"))
    results = {"iters": ITERS, "frames": FRAMES, "load_average_at_start": os.getloadavg()[0], "runs": []}
    try:
        if args.before:
            tree = work / "before"
            subprocess.run(["git", "-C", str(REPO_DIR), "worktree", "add", "--detach", str(tree), args.before],
                           check=True, capture_output=True)
            for name in ("drivers", "recorder", "calib"):  # installed under manisplat.*: linked for a plain path
                (tree / "manisplat" / name).symlink_to(tree / name)
            commit = subprocess.run(["git", "-C", str(tree), "rev-parse", "--short", "HEAD"], check=True,
                                    capture_output=True, text=True).stdout.strip()
            try:
                results["runs"].append(measure(tree, f"before ({commit})", work))
            finally:
                subprocess.run(["git", "-C", str(REPO_DIR), "worktree", "remove", "--force", str(tree)],
                               capture_output=True)
        results["runs"].append(measure(REPO_DIR, "after (this checkout)", work))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print_and_write_json(results, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
