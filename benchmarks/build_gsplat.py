"""Build gsplat's CUDA extension once, as the prebuilt module ``gsplat.csrc`` that gsplat imports
before it falls back to its own JIT build, so that a later run on a machine of the same image
(a lent GPU machine starts bare) carries the built file instead of building again.

``python -m benchmarks.build_gsplat OUT.so`` compiles the installed gsplat's CUDA sources with
its JIT flags (-O3, fast math; ``TORCH_CUDA_ARCH_LIST`` chooses the GPUs, e.g. 9.0 for Hopper),
writes the module to OUT.so and installs it into the gsplat package; ``--install FILE.so`` only
installs a file built earlier.
"""

from __future__ import annotations

import argparse
import glob
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def gsplat_package() -> Path:
    import importlib.util

    spec = importlib.util.find_spec("gsplat")
    if spec is None or spec.origin is None:
        raise SystemExit("gsplat is not installed")
    return Path(spec.origin).parent


def build(out: Path) -> float:
    """Compile gsplat's CUDA sources into the module ``csrc`` at ``out``; returns seconds taken."""
    from torch.utils.cpp_extension import load

    cuda = gsplat_package() / "cuda"
    sources = sorted(glob.glob(str(cuda / "csrc" / "*.cu")) + glob.glob(str(cuda / "csrc" / "*.cpp"))) + [str(cuda / "ext.cpp")]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as build_dir:
        load(name="csrc", sources=sources, extra_cflags=["-O3", "-Wno-attributes"],
             extra_cuda_cflags=["-O3", "-use_fast_math"],
             extra_include_paths=[str(cuda / "include"), str(cuda / "csrc" / "third_party" / "glm")],
             build_directory=build_dir, verbose=False)
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(Path(build_dir) / "csrc.so", out)
    return time.perf_counter() - t0


def install(built: Path) -> None:
    shutil.copyfile(built, gsplat_package() / "csrc.so")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.build_gsplat", description=__doc__.splitlines()[0])
    p.add_argument("file", type=Path, help="the module file to write (or, with --install, to install)")
    p.add_argument("--install", action="store_true", help="install FILE, built earlier, without building")
    args = p.parse_args(argv)
    if not args.install:
        print(f"gsplat CUDA extension built in {build(args.file):.1f} s: {args.file}")
    install(args.file)
    # checked in a new process: this one has the module loaded under the build's own name
    check = "from gsplat.cuda._backend import _C; print('gsplat imports its prebuilt module:', _C.__file__)"
    return subprocess.run([sys.executable, "-c", check]).returncode


if __name__ == "__main__":
    raise SystemExit(main())
