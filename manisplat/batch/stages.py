"""The batch's stages for one episode (validate, reconstruct, augment) and the final export.

Each stage is a plain function that runs in any process (a Ray worker or the driver). It writes
under a hidden ``.partial-<name>`` and renames the result to its final name only when complete, so
a killed task never leaves anything that looks done; a stage whose final output exists is done.
While it runs, ``.partial-<name>.pid`` beside the partial output names the process doing it.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from manisplat.batch.config import BatchConfig

STAGES = ("validate", "reconstruct", "augment")
EXPORT = "export"


class StageError(RuntimeError):
    """A stage ran and failed (what failed named); the batch goes on with the other episodes."""


@dataclass
class StageResult:
    """What one stage did: ``status`` "done" (ran now) or "skipped" (already complete), its wall
    time in seconds, and a few figures to show (``metrics``)."""

    episode: str
    stage: str
    status: str
    seconds: float = 0.0
    metrics: dict[str, Any] = field(default_factory=dict)


def stage_output(config: BatchConfig, stage: str, episode: str) -> Path:
    """The final output of ``stage`` for ``episode`` (the dataset for the export)."""
    return {"validate": config.out / "validate" / f"{episode}.json", "reconstruct": config.out / "recon" / episode,
            "augment": config.out / "aug" / episode, EXPORT: config.out / "dataset"}[stage]


def _partial(final: Path) -> Path:
    return final.with_name(f".partial-{final.name}")


class _Claim:
    """The partial output of a stage: cleared of a killed attempt's debris, marked with this pid."""

    def __init__(self, final: Path) -> None:
        self.final, self.partial = final, _partial(final)
        self.pid_file = self.partial.with_name(self.partial.name + ".pid")

    def __enter__(self) -> Path:
        self.final.parent.mkdir(parents=True, exist_ok=True)
        if self.partial.is_dir():
            shutil.rmtree(self.partial)
        self.partial.unlink(missing_ok=True)
        written = self.pid_file.with_name(self.pid_file.name + ".tmp")
        written.write_text(str(os.getpid()))
        os.replace(written, self.pid_file)  # whoever sees the pid file reads a whole pid
        return self.partial

    def __exit__(self, exc_type: Any, *_: Any) -> None:
        if exc_type is None:
            old = None
            if self.final.is_dir():  # a redone stage (the export): the earlier output goes once this one is in
                old = self.final.with_name(f".old-{self.final.name}")
                shutil.rmtree(old, ignore_errors=True)
                os.replace(self.final, old)
            os.replace(self.partial, self.final)
            if old is not None:
                shutil.rmtree(old)
        self.pid_file.unlink(missing_ok=True)


@contextlib.contextmanager
def _logged(config: BatchConfig, episode: str, stage: str):
    """What a stage's command prints goes to ``OUT/logs/<episode>.<stage>.log``, not the batch's console."""
    path = config.out / "logs" / f"{episode}.{stage}.log"
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as log_file, contextlib.redirect_stdout(log_file):
        yield


def _json(path: Path) -> dict[str, Any]:
    return json.loads(path.read_text())


def validate_stage(config: BatchConfig, episode: Path) -> StageResult:
    """Decode and check every file of the episode; an invalid episode fails here, named."""
    from manisplat.episode.validation import validate

    final, start = stage_output(config, "validate", episode.name), time.perf_counter()
    if final.is_file():
        record = _json(final)
        if not record["ok"]:
            raise StageError(f"{episode}: invalid episode (validated before): {record['report']}")
        return StageResult(episode.name, "validate", "skipped", metrics={"frames": record["frames"]})
    report = validate(episode)
    if not report.ok:
        raise StageError(f"{episode}: invalid episode: {report}")
    with _Claim(final) as partial:
        frames = report.frame_rows
        partial.write_text(json.dumps({"ok": True, "frames": frames, "report": str(report)}))
    return StageResult(episode.name, "validate", "done", time.perf_counter() - start, {"frames": frames})


def reconstruct_stage(config: BatchConfig, episode: Path) -> StageResult:
    """``manisplat-reconstruct EPISODE --iters N --device D`` into the batch's ``recon/<name>/``."""
    from manisplat.reconstruct.cli import main as reconstruct

    final, start = stage_output(config, "reconstruct", episode.name), time.perf_counter()
    if not (final / "twin.json").is_file():
        with _Claim(final) as partial, _logged(config, episode.name, "reconstruct"):
            code = reconstruct([str(episode), "--out", str(partial), "--iters", str(config.iters),
                                "--device", config.device, "-q"])
            if code != 0:
                raise StageError(f"{episode}: manisplat-reconstruct exited with {code}")
        status = "done"
    else:
        status = "skipped"
    metrics = _json(final / "metrics.json")
    psnr = metrics.get("psnr", {})
    return StageResult(episode.name, "reconstruct", status, time.perf_counter() - start,
                       {"psnr_full_db": psnr.get("full") if isinstance(psnr, dict) else psnr})


def augment_stage(config: BatchConfig, episode: Path) -> StageResult:
    """``manisplat-augment recon/<name> --n N --seed S`` into ``aug/<name>/``; fails if none is valid."""
    from manisplat.augment.cli import main as augment

    recon, final = stage_output(config, "reconstruct", episode.name), stage_output(config, "augment", episode.name)
    start = time.perf_counter()
    if not (final / "augment_report.json").is_file():
        with _Claim(final) as partial, _logged(config, episode.name, "augment"):
            code = augment([str(recon), "--n", str(config.n), "--out", str(partial), "--seed", str(config.seed), "-q"])
            report = partial / "augment_report.json"
            if code not in (0, 1) or not report.is_file() or _json(report)["written"] == 0:
                raise StageError(f"{episode.name}: manisplat-augment wrote no demonstration (exit {code})")
        status = "done"
    else:
        status = "skipped"
    report = _json(final / "augment_report.json")
    return StageResult(episode.name, "augment", status, time.perf_counter() - start,
                       {"written": report["written"], "validity": round(report["validity_rate"], 3)})


def augmented_episodes(config: BatchConfig, episode: str) -> list[Path]:
    """The augmented episodes written for ``episode``, in order."""
    return sorted((stage_output(config, "augment", episode)).glob("episode_*"))


def export_stage(config: BatchConfig, episodes: list[Path]) -> StageResult:
    """One dataset of ``episodes`` (the sources and their augmented episodes); redone when the set changed."""
    final, start = stage_output(config, EXPORT, ""), time.perf_counter()
    wanted = [str(p.resolve()) for p in episodes]
    record = final / ("meta/augmentation.json" if config.export_format == "lerobot" else "augmentation.json")
    if record.is_file():
        entries = _json(record).get("episodes" if config.export_format == "lerobot" else "files", [])
        if [e["episode"] for e in entries] == wanted:
            return StageResult("(all)", EXPORT, "skipped", metrics={"episodes": len(wanted)})
    if config.export_format == "lerobot":
        from manisplat.episode.exporters.lerobot import export_lerobot

        result = export_lerobot(episodes, final, task=config.task, overwrite=True)
        frames = result.frames
    else:
        from manisplat.episode.exporters.act_hdf5 import export_act_hdf5

        with _Claim(final) as partial:
            frames = sum(e["frames"] for e in export_act_hdf5(episodes, partial))
    return StageResult("(all)", EXPORT, "done", time.perf_counter() - start,
                       {"episodes": len(episodes), "frames": frames})
