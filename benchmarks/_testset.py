"""A pick-and-place test set nobody tuned on: five episodes from the simulator
(shared/tools/sim/gen_pick_place.py) with other cameras, object layouts, a can, and recording
noise with camera latency. Generated once into ``$MANISPLAT_TESTSET`` (default
``~/.cache/manisplat/testset``; about 40 s per episode on 2 cores) with the python of
``$MANISPLAT_SIMENV`` (a venv with mujoco 4.0.0: shared/tools/sim/README.md)."""

from __future__ import annotations

import os
import re
import subprocess
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from benchmarks._harness import BenchContext, MissingBenchmarkData

COMMON = ["--width", "320", "--height", "240", "--fps", "16", "--frames", "120", "--png-optimize"]
EPISODES: dict[str, list[str]] = {
    "left_cam_seed1": ["--seed", "1", "--cam-pos", "0.05", "0.50", "0.55", "--cam-target", "0.30", "0.02", "0.02"],
    "front_cam_seed2": ["--seed", "2", "--cam-pos", "0.85", "-0.25", "0.50", "--cam-target", "0.28", "0.02", "0.02"],
    "high_cam_seed3": ["--seed", "3", "--cam-pos", "0.20", "-0.55", "0.80", "--cam-target", "0.30", "0.05", "0.0"],
    "can_seed4": ["--seed", "4", "--object", "can"],
    "noisy_latency_seed5": ["--seed", "5", "--record-noise", "--cam-latency", "0.01",
                            "--cam-pos", "-0.05", "-0.50", "0.60", "--cam-target", "0.30", "0.0", "0.0"],
}


def test_set(ctx: BenchContext) -> list[Path]:
    """The episodes (made where missing); raises MissingBenchmarkData without a simulator."""
    root = Path(os.environ.get("MANISPLAT_TESTSET", Path.home() / ".cache" / "manisplat" / "testset"))
    return simulated_episodes(ctx, root, {name: [*COMMON, *args] for name, args in EPISODES.items()})


def simulated_episodes(ctx: BenchContext, root: Path, episodes: dict[str, list[str]], workers: int = 1) -> list[Path]:
    """``root/NAME`` for each of ``episodes`` (name -> gen_pick_place.py's arguments), generated
    where missing with the python of ``$MANISPLAT_SIMENV``, ``workers`` at once; raises
    MissingBenchmarkData without a simulator."""
    missing = [name for name in episodes if not (root / name / "episode.json").is_file()]
    if missing:
        simenv = os.environ.get("MANISPLAT_SIMENV")
        if not simenv:
            raise MissingBenchmarkData(f"episodes {missing} missing under {root}: set MANISPLAT_SIMENV to a mujoco "
                                       "venv's python to generate them")
        tools = ctx.require_shared("tools", "sim")

        def generate(name: str) -> None:
            cmd = [simenv, "gen_pick_place.py", "--out", str(root / name), *episodes[name]]
            proc = subprocess.run(cmd, cwd=tools, capture_output=True, text=True,
                                  env={**os.environ, "MUJOCO_GL": "osmesa", "OMP_NUM_THREADS": "1"})
            if proc.returncode != 0:
                raise MissingBenchmarkData(f"gen_pick_place.py failed for {name}: {proc.stderr[-800:]}")

        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(generate, missing))
    return [root / name for name in episodes]


def key_light(ctx: BenchContext) -> np.ndarray:
    """The direction [3] towards the simulator's shadow-casting light (base frame, unit), read from
    its scene (shared/tools/sim/pick_place_scene.xml): the truth a learned light is scored against.
    Read with a pattern, not an XML parser: the scene's comments hold "--", which MuJoCo accepts."""
    scene = (ctx.require_shared("tools", "sim") / "pick_place_scene.xml").read_text()
    lights = [tag for tag in re.findall(r"<light\b[^>]*>", scene) if 'castshadow="true"' in tag]
    if len(lights) != 1:
        raise ValueError(f"pick_place_scene.xml: expected one shadow-casting light, found {len(lights)}")
    towards = -np.array([float(x) for x in re.search(r'\bdir="([^"]+)"', lights[0]).group(1).split()])
    return towards / np.linalg.norm(towards)
