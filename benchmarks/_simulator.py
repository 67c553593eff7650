"""The simulator's tools (``shared/tools/sim``: ``execute_episode.py``, ``execute_bimanual.py``, ...)
run from benchmarks in the simulator's venv, a few at a time, each writing its JSON report
through a ``.part`` file: a report that exists is a finished job, so a stopped run resumes where
it was."""

from __future__ import annotations

import os
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

from benchmarks._harness import shared_dir


@dataclass(frozen=True)
class SimJob:
    """``script`` run with ``args``, its JSON report to ``report`` (``--json``)."""

    script: str
    args: tuple[str, ...]
    report: Path

    @property
    def part(self) -> Path:
        return self.report.with_name(self.report.name + ".part")


def sim_tools() -> Path:
    """``shared/tools/sim``, where the tools run."""
    return shared_dir() / "tools" / "sim"


def sim_env() -> dict[str, str]:
    """The environment the tools run in: this one, with ``MUJOCO_GL=osmesa`` unless it is set
    (``egl`` where a GPU driver or Mesa's EGL is installed)."""
    return {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "osmesa")}


def run_sim_jobs(simenv: Path, jobs: Iterable[SimJob], *, workers: int = 2, ok_codes: tuple[int, ...] = (0,),
                 tools: Path | None = None) -> None:
    """Run every job whose report does not exist yet, ``workers`` at a time (MuJoCo on the
    machine's cores), with ``MUJOCO_GL=osmesa`` unless set. A tool that exits with a code outside
    ``ok_codes`` (``execute_bimanual.py``: 2 when the task's own checks fail, which its report says)
    stops the run with a RuntimeError naming it; the jobs still running are killed."""
    env = sim_env()
    cwd = tools or sim_tools()
    running: list[tuple[SimJob, subprocess.Popen]] = []

    def finish(job: SimJob, proc: subprocess.Popen) -> None:
        code = proc.wait()
        if code not in ok_codes or not job.part.exists():
            raise RuntimeError(f"{job.script} {' '.join(job.args)} exited {code}"
                               + ("" if job.part.exists() else f" without writing {job.part}"))
        job.part.rename(job.report)

    try:
        for job in jobs:
            if job.report.exists():
                continue
            if len(running) >= workers:
                finish(*running.pop(0))
            job.report.parent.mkdir(parents=True, exist_ok=True)
            running.append((job, subprocess.Popen([str(simenv), job.script, *job.args, "--json", str(job.part)],
                                                  cwd=cwd, env=env, stdout=subprocess.DEVNULL)))
        while running:
            finish(*running.pop(0))
    finally:
        for _, proc in running:
            proc.kill()
            proc.wait()
