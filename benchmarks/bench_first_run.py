"""What a newcomer's first command costs: disk, the rasterizer's one-time build, and the time of the
README's first command after the install.

``python -m benchmarks first_run [--out benchmarks/results_first_run/first_run.json]`` makes a new
virtual environment, installs as the README says (``pip install torch==2.13.0``, then ``pip install
-e .``; then the test extras ``.[dev]``) and measures each environment's size on disk; then, with an
empty extension cache, runs ``manisplat-episode sample demo_episode && manisplat-reconstruct
demo_episode --out demo_twin --iters 1000`` twice in a new folder: the first run builds the C++
rasterizer (the build's own notice gives its seconds), the second finds it built. Needs PyPI (or a
pip configuration that serves the same packages) and a few minutes; nothing outside a temporary
folder is written except the JSON.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks._harness import BENCH_DIR, REPO_DIR, print_and_write_json

OWN_OPTIONS = True
FIRST_COMMAND = ("manisplat-episode sample demo_episode && "
                 "manisplat-reconstruct demo_episode --out demo_twin --iters 1000")


def _size_gb(path: Path) -> float:
    """Bytes on disk under ``path`` (``du``), in GB (1e9)."""
    out = subprocess.run(["du", "-sk", str(path)], check=True, capture_output=True, text=True).stdout
    return round(int(out.split()[0]) * 1024 / 1e9, 2)


def _timed(command: list[str] | str, **kwargs) -> tuple[float, str]:
    """Seconds ``command`` took and its combined output; raises when it fails."""
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, **kwargs)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{command} failed ({done.returncode}):\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    return round(seconds, 1), done.stdout + done.stderr


def _first_command(venv: Path, work: Path, extensions: Path) -> dict:
    """The first command's time in a new folder, and the build's seconds when it built the rasterizer."""
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    env = {**os.environ, "PATH": f"{venv / 'bin'}{os.pathsep}{os.environ['PATH']}",
           "TORCH_EXTENSIONS_DIR": str(extensions), "VIRTUAL_ENV": str(venv)}
    seconds, log = _timed(["bash", "-c", FIRST_COMMAND], cwd=work, env=env)
    built = re.search(r"the C\+\+ rasterizer is ready \((\d+) s\)", log)
    summary = re.search(r"done in (\d+) s", log)
    return {"wall_s": seconds, "build_s": int(built.group(1)) if built else None,
            "reconstruct_reported_s": int(summary.group(1)) if summary else None}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks first_run", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=BENCH_DIR / "results_first_run" / "first_run.json",
                        help="JSON to write (default: %(default)s)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="manisplat_first_run_") as tmp:
        tmp = Path(tmp)
        venv = tmp / "venv"
        pip = [str(venv / "bin" / "python"), "-m", "pip", "install", "-q"]
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
        torch_s, _ = _timed([*pip, "torch==2.13.0"])
        base_s, _ = _timed([*pip, "-e", str(REPO_DIR)])
        base_gb = _size_gb(venv)
        dev_s, _ = _timed([*pip, "-e", f"{REPO_DIR}[dev]"])
        dev_gb = _size_gb(venv)
        extensions = tmp / "extensions"
        first = _first_command(venv, tmp / "run1", extensions)
        second = _first_command(venv, tmp / "run2", extensions)
    result = {
        "benchmark": "first_run", "machine": platform.machine(), "cpus": os.cpu_count(),
        "python": platform.python_version(), "command": FIRST_COMMAND,
        "install_s": {"torch": torch_s, "base": base_s, "dev_extras": dev_s},
        "venv_gb": {"base": base_gb, "with_dev_extras": dev_gb},
        "first_command": {"with_build": first, "built_already": second},
    }
    print_and_write_json(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
