"""Where the time of a training step or a render goes: Dr.Jit kernels grouped by stage.

The code marks its stages (``with stage('field'):``); outside a :class:`KernelProfile` a stage
costs one global lookup. Inside one, every kernel that Dr.Jit launches while a stage is
innermost is attributed to it (Dr.Jit's kernel history, read at each stage boundary). Dr.Jit
evaluates lazily, so a kernel belongs to the stage that evaluates it: the stages evaluate
their outputs before they end. The reverse pass is one stage whose kernels are told apart by
kind: the kernels that scatter-add gradients (into the feature grids above all), memsets of
gradient buffers, block reductions (sums of per-thread gradient copies, per-ray sums), matrix
products (the MLPs in tensor mode) and the rest.

Used by ``benchmarks/profile.py``; run steps without ``drjit.freeze`` to see stages (a frozen
step replays its kernels in one call, with no Python in between).
"""
from __future__ import annotations

import contextlib
import re
import time
from collections import defaultdict

import drjit as dr

_active = None


@contextlib.contextmanager
def stage(name):
    """Attribute the kernels launched inside to stage ``name`` (when a profile is active)."""
    profile = _active
    if profile is None:
        yield
        return
    profile._enter(name)
    try:
        yield
    finally:
        profile._leave()


def settle(*values):
    """Evaluate ``values`` now when a profile is active (so that their kernels count in the stage
    that computes them, not in a later one that happens to need them); nothing otherwise."""
    if _active is not None:
        dr.eval(*values)


# A whole-array read or write in a kernel's LLVM IR: a vector load or store (masked or not) of
# one array element per lane; gathers, scatters and atomics (``@llvm.masked.gather`` ...) are not.
_STREAMED = re.compile(r'(?:= load|store) <\d+ x (\w+)>|@llvm\.masked\.(?:load|store)\.v\d+(\w+?)\(')
# Bytes of an element of each LLVM type.
_TYPE_BYTES = {'i1': 1, 'i8': 1, 'i16': 2, 'half': 2, 'f16': 2, 'i32': 4, 'float': 4, 'f32': 4,
               'i64': 8, 'double': 8, 'f64': 8, 'ptr': 8, 'p0': 8}


def _ir_text(kernel) -> str:
    ir = kernel.get('ir')
    return ir.getvalue() if hasattr(ir, 'getvalue') else str(ir or '')


def streamed_bytes(ir: str) -> int:
    """Bytes a kernel reads and writes whole per element, from its LLVM IR (:data:`_STREAMED`):
    each vector load or store of the code counted once (a loop's body once, whatever its
    iterations)."""
    return sum(_TYPE_BYTES.get(a or b, 4) for a, b in _STREAMED.findall(ir))


def kernel_kind(kernel):
    """What a kernel of Dr.Jit's history does, from its type and its code."""
    kind = str(kernel.get('type', '')).rsplit('.', 1)[-1]
    if kind == 'BatchedGemm':
        return 'matrix products'
    if kind == 'Memset':
        return 'memset'
    if kind in ('BlockReduce', 'BlockPrefixReduce', 'Reduce'):
        return 'block reductions'
    if kind == 'JIT':
        text = _ir_text(kernel)
        if 'reduce_add' in text or 'atomicrmw' in text:
            return 'gradient scatter'
        return 'kernels'
    return kind.lower() or 'other'


class KernelProfile:
    """Collects the kernels of the code run inside ``with KernelProfile() as p:`` by stage."""

    def __init__(self):
        self.stack = ['(outside stages)']
        self.records = []            # (stage path, kind, milliseconds)
        self.work = []               # per record: (elements, IR operations, bytes streamed each)
        self.python = defaultdict(float)
        self._t = None

    def _flush(self):
        path = ' / '.join(self.stack[1:]) or self.stack[0]
        for k in dr.kernel_history():
            self.records.append((path, kernel_kind(k), float(k.get('execution_time', 0.0))))
            self.work.append((int(k.get('size') or 0), int(k.get('operation_count') or 0),
                              streamed_bytes(_ir_text(k))))
        now = time.perf_counter()
        if self._t is not None:
            self.python[path] += now - self._t
        self._t = now

    def _enter(self, name):
        self._flush()
        self.stack.append(name)

    def _leave(self):
        dr.sync_thread()
        self._flush()
        self.stack.pop()

    def __enter__(self):
        global _active
        dr.sync_thread()
        self._flag = dr.flag(dr.JitFlag.KernelHistory)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history_clear()
        self._t = time.perf_counter()
        _active = self
        return self

    def __exit__(self, *exc):
        global _active
        dr.sync_thread()
        self._flush()
        _active = None
        dr.set_flag(dr.JitFlag.KernelHistory, self._flag)
        return False

    def launches(self):
        return len(self.records)

    def by_stage(self):
        """``{stage: {kind: (milliseconds, launches)}}`` over everything recorded."""
        out = defaultdict(lambda: defaultdict(lambda: [0.0, 0]))
        for path, kind, ms in self.records:
            entry = out[path][kind]
            entry[0] += ms
            entry[1] += 1
        return {s: {k: tuple(v) for k, v in kinds.items()} for s, kinds in out.items()}

    def by_stage_work(self):
        """``{(stage, kind): [milliseconds, launches, operations, bytes]}``: Dr.Jit's IR
        operations (per element times elements; integer and address arithmetic included) and
        the bytes of the arrays a kernel reads and writes whole (:func:`streamed_bytes` times
        elements; what gathers and scatters touch is not counted), an estimate of the
        arithmetic and a lower bound of the streaming traffic of each stage. A memset or a
        reduction counts 4 bytes per element and no operations; the kernels that are not
        Dr.Jit's generated code (matrix products, copies) are not estimated (None)."""
        out = defaultdict(lambda: [0.0, 0, 0, 0])
        for (path, kind, ms), (size, ops, streamed) in zip(self.records, self.work):
            entry = out[(path, kind)]
            entry[0] += ms
            entry[1] += 1
            if entry[2] is None:
                continue
            if kind in ('memset', 'block reductions'):
                entry[3] += 4 * size
            elif kind in ('kernels', 'gradient scatter'):
                entry[2] += size * ops
                entry[3] += size * streamed
            else:
                entry[2] = entry[3] = None
        return dict(out)
