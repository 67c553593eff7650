"""manisplat-batch throughput on this machine: episodes per hour with 1 and 2 Ray workers (and the
in-process sequential runner), small budget, with each stage's mean time for a cluster estimate.

Episodes: 4 built-in samples (64 frames, 160x120, seeds 0-3); reconstruct ``--iters 200`` on the CPU,
augment ``--n 3``, export one LeRobot dataset. Each run starts from an empty output folder and a
fresh local Ray cluster of 1 or 2 CPUs (each task asks for 1 CPU; Ray gives its workers
OMP_NUM_THREADS=1). The sequential runner uses torch's own threads (2 here).
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks._harness import BenchContext, MissingBenchmarkData

THREADED = False
EPISODES, ITERS, N = 4, 200, 3


def _pipeline(root: Path, count: int, iters: int, n: int) -> Path:
    text = (f'episodes = ["episodes/*"]\nout = "out"\n[reconstruct]\niters = {iters}\n[augment]\nn = {n}\n'
            f'seed = 0\n[export]\ntask = "pick the box and place it on the mat"\n')
    (root / "pipeline.toml").write_text(text)
    return root / "pipeline.toml"


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    try:
        import ray
    except ModuleNotFoundError as exc:
        raise MissingBenchmarkData("needs Ray (pip install 'manisplat[distributed]')") from exc
    from manisplat.batch.config import load_config
    from manisplat.batch.runner import LocalExecutor, RayExecutor, run_batch
    from manisplat.episode.synthetic import write_sample_episode

    count, iters, n = (2, 20, 1) if ctx.quick else (EPISODES, ITERS, N)
    rows = []
    with tempfile.TemporaryDirectory() as tmp_name:
        episodes = Path(tmp_name) / "episodes"
        for seed in range(count):
            write_sample_episode(episodes / f"sample{seed}", seed=seed)
        for runner in ("sequential", "ray 1 worker", "ray 2 workers"):
            root = Path(tmp_name) / runner.replace(" ", "_")
            root.mkdir()
            (root / "episodes").symlink_to(episodes)
            config = load_config(_pipeline(root, count, iters, n))
            if runner == "sequential":
                executor = LocalExecutor()
            else:
                ray.init(num_cpus=int(runner.split()[1]), include_dashboard=False, log_to_driver=False)
                executor = RayExecutor(None, config.max_retries)
            start = time.perf_counter()
            try:
                results = run_batch(config, executor)
            finally:
                if runner != "sequential":
                    ray.shutdown()
            wall = time.perf_counter() - start
            failed = [r for r in results if r.status != "done"]
            by_stage = {stage: statistics.mean(r.seconds for r in results if r.stage == stage)
                        for stage in ("validate", "reconstruct", "augment", "export")}
            written = sum(r.metrics.get("written", 0) for r in results if r.stage == "augment")
            rows.append({"runner": runner, "episodes": count, "not_done": len(failed), "wall_s": wall,
                         "episodes_per_hour": 3600 * count / wall, "demonstrations_written": written,
                         **{f"{stage}_s_mean": s for stage, s in by_stage.items()}})
    ctx.notes.append(f"{count} sample episodes (64 frames 160x120), reconstruct --iters {iters} on the CPU, "
                     f"augment --n {n}, one LeRobot export; stage times are per task, in its worker")
    return rows
