"""``torch.compile`` for the training iteration's tensor functions, switched on by a context.

Eager PyTorch runs an iteration of the reconstruction as some 800 separate operations (the
placement of every node, the light pass's camera, the shading, the loss and their backward;
:meth:`~manisplat.reconstruct.trainer.Reconstruction.tensor_ops` counts them); on a GPU each is a
kernel launch of a few microseconds of work, so the iteration is bound by launches, not by
arithmetic. The functions that do that work are pure tensor functions of fixed-shape
inputs (shapes change only at densification steps) marked :func:`compilable`: inside
``with compilation("default"):`` they run through ``torch.compile`` (Inductor: fused Triton
kernels on CUDA, vectorised C++ on the CPU, their backward compiled too); outside it they run
eagerly, the same code. Each is compiled for any number of Gaussians on its first call, and again
when a Python setting it reads changes (the shadows' start); compiled code is cached on disk by
PyTorch (``TORCHINDUCTOR_CACHE_DIR``), so a later process on the same machine starts faster.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
from collections.abc import Callable, Iterator
from typing import TypeVar

import torch

F = TypeVar("F", bound=Callable)

#: how each mode compiles: "default", Inductor's fused kernels; "trace", Dynamo and AOTAutograd
#: without generating code (the graphs, guards and backward that compiling sees, in seconds: for
#: tests and for finding a fault). torch.compile's "reduce-overhead" (CUDA graphs) ended the process
#: with a segmentation fault on an H100 with torch 2.11.0 and is not offered.
MODES: dict[str, dict[str, str]] = {"default": {"mode": "default"}, "trace": {"backend": "aot_eager"}}

_MODE: contextvars.ContextVar[str | None] = contextvars.ContextVar("manisplat_compilation", default=None)


@contextlib.contextmanager
def compilation(mode: str | None) -> Iterator[None]:
    """Run :func:`compilable` functions compiled in ``mode`` (one of :data:`MODES`), or eagerly
    (None), inside the block.

    A compiled block treats the sizes of parameters as symbolic, as of other tensors (Gaussians
    are parameters whose number changes at densification; torch.compile's default would compile
    again at every change). Enter it around a loop, not each call: changing Dynamo's settings
    makes the next compiled calls check their cache the slow way (3.4 ms a call measured).
    """
    if mode is not None and mode not in MODES:
        raise ValueError(f"unknown compilation mode {mode!r}; choose one of {', '.join(MODES)}")
    token = _MODE.set(mode)
    try:
        if mode is None:
            yield
        else:
            with torch._dynamo.config.patch(force_parameter_static_shapes=False):
                yield
    finally:
        _MODE.reset(token)


def compilable(fn: F) -> F:
    """``fn`` eagerly, or through ``torch.compile`` inside ``with compilation(mode)`` (compiled on
    first use in each mode). Called while another function is being compiled, it is traced into
    that one."""
    compiled: dict[str, Callable] = {}

    @functools.wraps(fn)
    def dispatch(*args, **kwargs):
        mode = _MODE.get()
        if mode is None or torch.compiler.is_compiling():
            return fn(*args, **kwargs)
        if mode not in compiled:
            compiled[mode] = torch.compile(fn, dynamic=True, **MODES[mode])
        return compiled[mode](*args, **kwargs)

    return dispatch  # type: ignore[return-value]


_CONSTANTS: dict[tuple[int, torch.dtype, torch.device], torch.Tensor] = {}


def constant_tensor(values: tuple, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The tensor of ``values`` (nested tuples of numbers, a module-level constant) on ``device``:
    made once per dtype and device in eager code (a host-to-device copy in every call would wait
    for the GPU), a constant of the graph inside compiled code (which traces no cache)."""
    if torch.compiler.is_compiling():
        return torch.tensor(values, dtype=dtype, device=device)
    key = (id(values), dtype, device)
    if key not in _CONSTANTS:
        _CONSTANTS[key] = torch.tensor(values, dtype=dtype, device=device)
    return _CONSTANTS[key]
