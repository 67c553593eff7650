"""Counting the tensor operations code issues: on a GPU each is a kernel launch and a trip
through Python and the dispatcher (about 10-20 us), which bounds a training iteration of a few
hundred thousand Gaussians long before the arithmetic does.

:class:`TensorOpCounter` counts the ATen operations that compute (views, detaches and other
aliasing operations launch nothing and are left out), backward ones included; it measures the
same on the CPU as on a GPU, so launch overhead can be worked on without a GPU.
"""

from __future__ import annotations

import collections

from torch.utils._python_dispatch import TorchDispatchMode

#: ATen operations that only alias their input (no kernel runs)
ALIASING = frozenset({
    "aten.alias", "aten.as_strided", "aten.detach", "aten.diagonal", "aten.expand", "aten.permute", "aten.select",
    "aten.slice", "aten.squeeze", "aten.t", "aten.transpose", "aten.unbind", "aten.unflatten", "aten.unsqueeze",
    "aten.view", "aten._unsafe_view", "aten._reshape_alias", "aten.split", "aten.split_with_sizes", "aten.chunk",
    "aten.lift_fresh", "aten.view_as_real", "aten.view_as_complex", "aten.unfold",
})


class TensorOpCounter(TorchDispatchMode):
    """``with TensorOpCounter() as ops: ...`` then ``ops.counts`` (op name -> calls) and
    ``ops.total``: the computing ATen operations run inside, backward included."""

    def __init__(self) -> None:
        super().__init__()
        self.counts: collections.Counter = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = str(func.overloadpacket)
        if name not in ALIASING:
            self.counts[name] += 1
        return func(*args, **(kwargs or {}))

    @property
    def total(self) -> int:
        return sum(self.counts.values())
