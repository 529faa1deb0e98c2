"""Dr.Jit arrays from NumPy that own their memory, and which backend they live on.

Converting a NumPy array to a Dr.Jit array may map the NumPy buffer instead of copying it
(when it is suitably aligned); releasing such an array later needs a host callback, which a
frozen function (:func:`drjit.freeze`, the training step of :mod:`.train`) cannot record:
Dr.Jit 1.5 then aborts the process ("enqueue_host_func(): this function cannot be
recorded"). Everything that a training step may replace - parameters, optimizer state,
occupancy grids, the ray bank - is therefore created through :func:`owned`.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


def llvm_backend() -> bool:
    """Whether the selected variant runs on Dr.Jit's LLVM backend (the CPU, ``llvm_ad_rgb``)
    rather than CUDA: the settings measured on the CPU (Dr.Jit's thread count, scatter
    expansion, packed networks) apply there only."""
    return dr.backend_v(mi.Float) == dr.JitBackend.LLVM


def owned(values, tp=None):
    """A copy of ``values`` (NumPy array or anything ``tp`` converts) in memory Dr.Jit
    allocated: a ``TensorXf`` of its shape by default, or ``tp`` (e.g. ``mi.Float``)."""
    if tp is None:
        a = np.ascontiguousarray(values, dtype=np.float32)
        return mi.TensorXf(owned(a.ravel(), mi.Float), a.shape)
    src = tp(values)
    # A scatter into a new array: Dr.Jit folds ``x + 0``, ``dr.copy(x)`` and a gather at
    # ``arange`` back into ``x`` itself, which would keep the NumPy buffer.
    out = dr.empty(tp, dr.width(src))
    dr.scatter(out, src, dr.arange(mi.UInt32, dr.width(src)))
    dr.eval(out)
    dr.sync_thread()      # kernels run asynchronously: the copy is done before NumPy moves on
    return out
