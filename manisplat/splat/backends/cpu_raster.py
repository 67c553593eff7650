"""The C++/OpenMP backend: projection and compositing, forward and hand-written backward (``csrc/``).

Built on first use with ``torch.utils.cpp_extension`` and cached (``$TORCH_EXTENSIONS_DIR``, by
default ``~/.cache/torch_extensions/py3X_cpu``) under a content key (:func:`extension_key`): the
bytes of the sources, the flags, torch's version and C++ ABI, Python's ABI, the machine and the
compiler. The sources are copied into the build directory and built from there, so checkouts
with the same sources share one build wherever they are, an edit or an upgrade builds anew, and
nothing stale is loaded. AVX2/FMA code is generated when torch reports the CPU supports it.
Threads follow ``torch.set_num_threads``.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import logging
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType

import torch

from manisplat.splat.backends.tiles import tile_rects
from manisplat.splat.projection import Projection

log = logging.getLogger(__name__)
CSRC = Path(__file__).resolve().parent.parent / "csrc"
SOURCE_NAMES = ("rasterize_cpu.cpp", "project_cpu.cpp")
HEADER_NAMES = ("splat_cpu.h",)
LDFLAGS = ("-fopenmp",)
_extension: ModuleType | None = None


class BackendUnavailable(RuntimeError):
    """A rasterizer backend cannot run here (no compiler, no GPU, gsplat missing, ...)."""


def _flags() -> list[str]:
    flags = ["-O3", "-fopenmp", "-std=c++17"]
    if torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512"):
        flags += ["-mavx2", "-mfma"]
    return flags


def _compiler() -> str:
    """The compiler torch will call (``$CXX`` or ``c++``), as a resolved path, or raise."""
    compiler = os.environ.get("CXX", "c++")
    path = shutil.which(compiler)
    if path is None:
        raise BackendUnavailable(
            f"the 'cpu' rasterizer needs a C++ compiler ({compiler!r} not found; install g++ or set CXX), "
            "or pass backend='torch' for the slow pure-PyTorch one"
        )
    return os.path.realpath(path)


def _compiler_identity(path: str) -> str:
    """The compiler's path and the first line of ``--version`` (a compiler upgrade builds anew)."""
    try:
        out = subprocess.run([path, "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        out = ""
    return f"{path} {out.splitlines()[0] if out else ''}".strip()


def extension_key(csrc: Path = CSRC, flags: list[str] | None = None, compiler: str | None = None) -> str:
    """The extension's module name: ``manisplat_raster_cpu_`` + 20 hex digits of a SHA-256 over
    the source and header bytes (by file name; not their directory), the compile and link flags,
    torch's version and C++ ABI, Python's ABI tag, the machine and the compiler's identity.

    Identical sources give the same name wherever the checkout is; any difference gives another.
    """
    return _name(_key_description(Path(csrc), _flags() if flags is None else flags,
                                  _compiler_identity(_compiler()) if compiler is None else compiler))


def _name(desc: dict) -> str:
    return "manisplat_raster_cpu_" + hashlib.sha256(json.dumps(desc, sort_keys=True).encode()).hexdigest()[:20]


def _key_description(csrc: Path, flags: list[str], compiler: str) -> dict:
    return {
        "sources": {n: hashlib.sha256((csrc / n).read_bytes()).hexdigest() for n in SOURCE_NAMES + HEADER_NAMES},
        "cflags": list(flags),
        "ldflags": list(LDFLAGS),
        "torch": torch.__version__,
        "cxx11_abi": bool(torch.compiled_with_cxx11_abi()),
        "python": f"{sys.implementation.cache_tag}{getattr(sys, 'abiflags', '')}",
        "machine": f"{sys.platform}-{platform.machine()}",
        "compiler": compiler,
    }


def extensions_root() -> Path:
    """Where torch keeps built extensions: ``$TORCH_EXTENSIONS_DIR``, else torch's default."""
    root = os.environ.get("TORCH_EXTENSIONS_DIR")
    if root:
        return Path(root)
    from torch.utils import cpp_extension

    tag = f"py{sys.version_info.major}{sys.version_info.minor}{getattr(sys, 'abiflags', '')}_cpu"
    return Path(cpp_extension.get_default_build_root()) / tag


def build_directory(name: str) -> Path:
    """The build directory of extension ``name``: its sources (``src/``), build files and library."""
    return extensions_root() / name


def _library(build_dir: Path, name: str) -> Path:
    return build_dir / f"{name}{'.pyd' if sys.platform == 'win32' else '.so'}"


def _done_marker(build_dir: Path, name: str) -> Path:
    """Written (atomically) once ``name`` was built and loaded: its library is complete."""
    return build_dir / f"{name}.done"


def _copy_sources(csrc: Path, build_dir: Path, desc: dict) -> Path:
    """``build_dir/src``: the sources, copied once; atomic (a temporary directory renamed), so
    concurrent first builds all see either nothing or every file."""
    src = build_dir / "src"
    if src.is_dir():
        return src
    tmp = Path(tempfile.mkdtemp(prefix=".src-", dir=build_dir))
    try:
        for n in SOURCE_NAMES + HEADER_NAMES:
            shutil.copyfile(csrc / n, tmp / n)
        (tmp / "key.json").write_text(json.dumps(desc, indent=1, sort_keys=True) + "\n")
        os.chmod(tmp, 0o755)  # mkdtemp's 0o700 would hide the sources from a cache shared by users
        os.rename(tmp, src)
    except OSError:
        if not src.is_dir():  # not just another process winning the rename
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return src


def _import(name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot import {path}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _notice(msg: str, *args) -> None:
    """An INFO log record on a line of its own, also while a tqdm progress bar is on screen."""
    console = any(
        type(h) is logging.StreamHandler and h.stream in (sys.stdout, sys.stderr)
        for h in logging.getLogger().handlers
    )
    if not console:
        log.info(msg, *args)
        return
    from tqdm.contrib.logging import logging_redirect_tqdm

    with logging_redirect_tqdm():
        log.info(msg, *args)


def _load(csrc: Path = CSRC) -> ModuleType:
    """Load the extension built from the sources in ``csrc``, building it first if no checkout
    with the same key (:func:`extension_key`) has."""
    compiler = _compiler()
    flags = _flags()
    desc = _key_description(Path(csrc), flags, _compiler_identity(compiler))
    name = _name(desc)
    build_dir = build_directory(name)
    library = _library(build_dir, name)
    if _done_marker(build_dir, name).exists() and library.exists():
        try:  # built: no ninja, whatever paths this checkout's torch headers have
            return _import(name, library)
        except ImportError as exc:
            log.warning("the cached C++ rasterizer %s did not load (%s); building it again", library, exc)
    from torch.utils import cpp_extension

    _notice("building the C++ rasterizer in %s (once for these sources; about a minute)", build_dir)
    start = time.monotonic()
    try:
        build_dir.mkdir(parents=True, exist_ok=True)
        src = _copy_sources(Path(csrc), build_dir, desc)
        module = cpp_extension.load(
            name=name, sources=[str(src / n) for n in SOURCE_NAMES], extra_include_paths=[str(src)],
            extra_cflags=flags, extra_ldflags=list(LDFLAGS), build_directory=str(build_dir), verbose=False,
        )
    except Exception as exc:  # compiler and ninja errors come in several types
        raise BackendUnavailable(
            f"building the 'cpu' rasterizer failed ({exc}); fix the toolchain or pass backend='torch'"
        ) from exc
    marker = _done_marker(build_dir, name)
    tmp = marker.with_name(f".{marker.name}.{os.getpid()}")
    tmp.write_text(f"{library.name}\n")
    os.replace(tmp, marker)
    _notice("the C++ rasterizer is ready (%.0f s)", time.monotonic() - start)
    return module


def load_extension() -> ModuleType:
    """The compiled extension, building it once if needed (see :func:`extension_key`).

    Raises:
        BackendUnavailable: no C++ compiler or the build failed; the message says how to fix it
            or to choose ``backend="torch"`` explicitly.
    """
    global _extension
    if _extension is None:
        _extension = _load(CSRC)
    return _extension


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, radii, rects, order, width, height, tile_size):
        ext = load_extension()
        tensors = [t.contiguous() for t in (means2d, conics, opacities, colors)]
        image, alpha, final_T, last, offsets, lists = ext.forward(
            *tensors, radii.contiguous(), rects.contiguous(), order.contiguous(), width, height, tile_size
        )
        ctx.save_for_backward(*tensors, radii, offsets, lists, final_T, last)
        ctx.size = (width, height, tile_size)
        return image, alpha

    @staticmethod
    def backward(ctx, grad_image, grad_alpha):
        means2d, conics, opacities, colors, radii, offsets, lists, final_T, last = ctx.saved_tensors
        width, height, tile_size = ctx.size
        g_means, g_conics, g_opac, g_colors = load_extension().backward(
            means2d, conics, opacities, colors, radii.contiguous(), offsets, lists, final_T, last,
            grad_image.contiguous(), grad_alpha.contiguous(), width, height, tile_size,
        )
        return g_means, g_conics, g_opac, g_colors, None, None, None, None, None, None


def composite(means2d, conics, opacities, colors, depths, radii, width, height, tile_size=16):
    """Image [H, W, D] and alpha [H, W]; see :mod:`manisplat.splat.backends` for the rules."""
    if means2d.device.type != "cpu":
        raise BackendUnavailable("the 'cpu' backend takes CPU tensors")
    dtype = colors.dtype
    rects = tile_rects(means2d, radii, width, height, tile_size)
    order = load_extension().depth_order(depths.detach().contiguous())  # torch.argsort(stable=True), radix
    return _Composite.apply(
        means2d.to(dtype), conics.to(dtype), opacities.to(dtype), colors, radii.to(torch.int32), rects, order,
        width, height, tile_size,
    )


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, viewmat, K, opacities, width, height, near, far, eps2d):
        ext = load_extension()
        inputs = [t.contiguous() for t in (means, quats, scales, viewmat, K)]
        means2d, conics, depths, radii = ext.project_forward(
            *inputs[:3], opacities.detach().contiguous(), *inputs[3:], width, height, near, far, eps2d
        )
        ctx.save_for_backward(*inputs, radii)
        ctx.args = (width, height, eps2d)
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, radii

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, _):
        means, quats, scales, viewmat, K, radii = ctx.saved_tensors
        width, height, eps2d = ctx.args
        g_means, g_quats, g_scales, g_view = load_extension().project_backward(
            means, quats, scales, viewmat, K, width, height, eps2d, radii,
            g_means2d.contiguous(), g_conics.contiguous(), g_depths.contiguous(),
        )
        return g_means, g_quats, g_scales, g_view, None, None, None, None, None, None, None


def project(means, quats, scales, opacities, viewmats, Ks, width, height, *, near_plane=0.01, far_plane=1e10,
            eps2d=0.3) -> Projection:
    """:func:`manisplat.splat.projection.project_gaussians` in C++ (same conventions and results)."""
    if means.device.type != "cpu":
        raise BackendUnavailable("the 'cpu' backend takes CPU tensors")
    dtype = means.dtype
    parts = [
        _Project.apply(means, quats.to(dtype), scales.to(dtype), viewmats[c].to(dtype), Ks[c].to(dtype),
                       opacities.to(dtype), width, height, float(near_plane), float(far_plane), float(eps2d))
        for c in range(viewmats.shape[0])
    ]
    means2d, conics, depths, radii = (torch.stack(x) for x in zip(*parts))
    return Projection(means2d, conics, depths, radii, opacities.to(dtype)[None].expand(viewmats.shape[0], -1))
