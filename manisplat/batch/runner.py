"""The batch driver: every episode through validate -> reconstruct -> augment, then one export.

Each stage of each episode is a task. On Ray (:class:`RayExecutor`) tasks declare their resources
(a reconstruction ``num_gpus=1`` on CUDA, ``num_cpus`` otherwise) and Ray retries a task whose
process crashed or died up to ``retries.max`` times; the driver submits an episode's next stage when
the previous one finishes, so one command fills a workstation or a cluster. Without Ray
(:class:`LocalExecutor`) the same tasks run one after another in this process. A stage that still
fails is reported with its error in ``OUT/errors/`` and the episode's later stages are skipped;
the other episodes go on.
"""

from __future__ import annotations

import json
import logging
import time
import traceback
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable

from tqdm import tqdm

from manisplat.batch.config import BatchConfig
from manisplat.batch.stages import (EXPORT, STAGES, StageResult, augment_stage, augmented_episodes, export_stage,
                                    reconstruct_stage, validate_stage)
from manisplat.episode.fsio import atomic_write_bytes

log = logging.getLogger(__name__)

STAGE_FUNCTIONS: dict[str, Callable[[BatchConfig, Path], StageResult]] = {
    "validate": validate_stage, "reconstruct": reconstruct_stage, "augment": augment_stage}
SUMMARY_FILE = "batch.json"


class LocalExecutor:
    """Runs each task in this process when it is submitted (no Ray)."""

    name = "sequential (in-process)"

    def __init__(self) -> None:
        self._done: list[tuple[int, Any, BaseException | None]] = []
        self._next = 0

    def submit(self, fn: Callable[..., Any], *args: Any, cpus: float = 1.0, gpus: float = 0.0) -> int:
        handle, self._next = self._next, self._next + 1
        try:
            self._done.append((handle, fn(*args), None))
        except Exception as exc:  # noqa: BLE001 - reported per task, like a Ray task's error
            self._done.append((handle, None, exc))
        return handle

    def wait(self) -> tuple[int, Any, BaseException | None]:
        return self._done.pop(0)

    def shutdown(self) -> None:
        pass


class RayExecutor:
    """Tasks on a Ray cluster: local (``ray.init()``) or joined (``address``)."""

    def __init__(self, address: str | None, max_retries: int, num_cpus: int | None = None) -> None:
        import ray

        self._ray = ray
        self._started = not ray.is_initialized()
        if self._started:
            ray.init(address=address, num_cpus=num_cpus if address is None else None, include_dashboard=False,
                     logging_level=logging.ERROR, log_to_driver=False)
        self._remote = ray.remote(_call)
        self._retries = max_retries
        self._pending: dict[Any, Any] = {}
        resources = ray.cluster_resources()
        self.name = f"Ray ({resources.get('CPU', 0):g} CPUs, {resources.get('GPU', 0):g} GPUs)"

    def submit(self, fn: Callable[..., Any], *args: Any, cpus: float = 1.0, gpus: float = 0.0) -> Any:
        ref = self._remote.options(num_cpus=cpus, num_gpus=gpus, max_retries=self._retries,
                                   retry_exceptions=True).remote(fn, *args)
        self._pending[ref] = ref
        return ref

    def wait(self) -> tuple[Any, Any, BaseException | None]:
        (ref,), _ = self._ray.wait(list(self._pending), num_returns=1)
        del self._pending[ref]
        try:
            return ref, self._ray.get(ref), None
        except Exception as exc:  # noqa: BLE001 - a task's error or a worker that died once too often
            return ref, None, getattr(exc, "cause", None) or exc

    def nodes(self) -> list[tuple[float, float]]:
        """(CPUs, GPUs) of each alive node of the cluster."""
        return [(node["Resources"].get("CPU", 0.0), node["Resources"].get("GPU", 0.0))
                for node in self._ray.nodes() if node.get("Alive")]

    def shutdown(self) -> None:
        if self._started:
            self._ray.shutdown()


def unfit_reconstruction(config: BatchConfig, nodes: list[tuple[float, float]]) -> str | None:
    """Why none of the cluster's ``nodes`` ((CPUs, GPUs) each, :meth:`RayExecutor.nodes`) could run
    the reconstruction tasks ``config`` asks for (Ray would keep them waiting), or None when one could."""
    cpus, gpus = config.reconstruct_cpus, config.reconstruct_gpus
    if any(c >= cpus and g >= gpus for c, g in nodes):
        return None
    most_cpus, most_gpus = (max(column, default=0.0) for column in zip(*nodes)) if nodes else (0.0, 0.0)
    if cpus > most_cpus:
        return f"reconstruct.cpus = {cpus:g}, but the largest node of the Ray cluster has {most_cpus:g} CPUs"
    if gpus > most_gpus:
        return (f"reconstruct.gpus = {gpus:g} (device cuda), but the largest node of the Ray cluster has "
                f"{most_gpus:g} GPUs")
    return f"reconstruct.cpus = {cpus:g} and reconstruct.gpus = {gpus:g}: no node of the Ray cluster has both"


def _call(fn: Callable[..., Any], *args: Any) -> Any:
    return fn(*args)


def _error_file(config: BatchConfig, episode: str, stage: str) -> Path:
    return config.out / "errors" / f"{episode}.{stage}.txt"


def _report_failure(config: BatchConfig, episode: str, stage: str, error: BaseException) -> StageResult:
    """Log the failure, keep its traceback in ``OUT/errors/<episode>.<stage>.txt``, return its row."""
    log.error("%s: %s failed: %s", episode, stage, _describe(error))
    path = _error_file(config, episode, stage)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(traceback.format_exception(type(error), error, error.__traceback__)))
    return StageResult(episode, stage, "failed", metrics={"error": _describe(error)})


def _describe(exc: BaseException) -> str:
    text = "".join(traceback.format_exception_only(type(exc), exc)).strip()
    return text.splitlines()[-1] if text else type(exc).__name__


def run_batch(config: BatchConfig, executor: Any, *, progress: bool = False) -> list[StageResult]:
    """Run every stage not yet complete; returns one result per stage and episode, plus the export.

    Results' ``status``: "done" (ran now), "skipped" (complete before), "failed" (its error in
    ``OUT/errors/<episode>.<stage>.txt``), "blocked" (an earlier stage of the episode failed).
    ``OUT/batch.json`` records the configuration and these rows.
    """
    config.out.mkdir(parents=True, exist_ok=True)
    results: list[StageResult] = []
    tasks: dict[Any, tuple[Path, str]] = {}
    counts = {stage: 0 for stage in (*STAGES, EXPORT)}
    total = len(config.episodes) * len(STAGES) + 1
    started = time.perf_counter()

    def submit(episode: Path, stage: str) -> None:
        cpus = config.reconstruct_cpus if stage == "reconstruct" else 1.0
        gpus = config.reconstruct_gpus if stage == "reconstruct" else 0.0
        tasks[executor.submit(STAGE_FUNCTIONS[stage], config, episode, cpus=cpus, gpus=gpus)] = (episode, stage)

    with tqdm(total=total, desc="batch", unit="task", disable=not progress) as bar:
        for episode in config.episodes:
            submit(episode, STAGES[0])
        while tasks:
            handle, result, error = executor.wait()
            episode, stage = tasks.pop(handle)
            error_path = _error_file(config, episode.name, stage)
            bar.update(1)
            if error is None:
                results.append(result)
                counts[stage] += 1
                error_path.unlink(missing_ok=True)
                following = STAGES.index(stage) + 1
                if following < len(STAGES):
                    submit(episode, STAGES[following])
            else:
                results.append(_report_failure(config, episode.name, stage, error))
                for later in STAGES[STAGES.index(stage) + 1:]:
                    results.append(StageResult(episode.name, later, "blocked"))
                    bar.update(1)
            bar.set_postfix({s: counts[s] for s in STAGES})
        finished = [e for e in config.episodes if any(r.episode == e.name and r.stage == "augment"
                                                      and r.status in ("done", "skipped") for r in results)]
        if finished:
            sources = [p for e in finished for p in (e, *augmented_episodes(config, e.name))]
            executor.submit(export_stage, config, sources)
            _, result, error = executor.wait()
            results.append(result if error is None else _report_failure(config, "(all)", EXPORT, error))
        else:
            results.append(StageResult("(all)", EXPORT, "blocked"))
        bar.update(1)
    summary = {"config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(config).items()
                          if k != "episodes"}, "episodes": [str(e) for e in config.episodes],
               "executor": executor.name, "wall_s": time.perf_counter() - started,
               "results": [asdict(r) for r in results]}
    atomic_write_bytes(config.out / SUMMARY_FILE, (json.dumps(summary, indent=1, default=str) + "\n").encode())
    return results


def batch_status(out: Path, episodes: list[str] | None = None) -> list[StageResult]:
    """The state of a batch read from its output folder: per episode and stage "complete", "failed",
    "running" (a ``.partial`` output with a pid file) or "pending"."""
    from manisplat.batch.stages import stage_output

    summary_path = out / SUMMARY_FILE
    if episodes is None:
        if not summary_path.is_file():
            raise FileNotFoundError(f"{out}: no {SUMMARY_FILE}; not a batch output folder (or no run has finished)")
        episodes = [Path(e).name for e in json.loads(summary_path.read_text())["episodes"]]
    config = BatchConfig(episodes=(), out=out)
    rows = []
    for name in [*episodes, "(all)"]:
        for stage in (STAGES if name != "(all)" else (EXPORT,)):
            final = stage_output(config, stage, name)
            complete = {"validate": final.is_file(), "reconstruct": (final / "twin.json").is_file(),
                        "augment": (final / "augment_report.json").is_file(),
                        EXPORT: any((final / p).is_file() for p in ("meta/info.json", "augmentation.json"))}[stage]
            running = final.with_name(f".partial-{final.name}.pid").is_file()
            failed = _error_file(config, name, stage).is_file()
            status = "complete" if complete else "failed" if failed else "running" if running else "pending"
            rows.append(StageResult(name, stage, status))
    return rows
