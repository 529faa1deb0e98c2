"""What a training run holds in memory, against what the machine has: the estimate behind the
automatic downscale (:class:`~mi_nerfpp.data.dataset.AutoDownscale`, announced by
:func:`mi_nerfpp.run.prepare`).

A run holds the images of every split as stored (:mod:`mi_nerfpp.data.storage`, the training
images twice: as loaded and in the store its steps gather from) and the working set of a
training step, which does not depend on the images' size (a step draws ``batch_rays`` pixels):

- the process with Mitsuba, Dr.Jit, LLVM and the step's kernels: :data:`BASE_BYTES`;
- the model's parameters (float32), each held :data:`PARAMETER_COPIES` times (value,
  gradient, Adam's two moments) plus once per Dr.Jit thread (in steps of
  :data:`mi_nerfpp.train.EXPAND_MIN_SAMPLES` or more, gradients of large grids are summed in
  one copy per thread; the plan counts them whatever the step);
- :data:`SAMPLE_BYTES` per sample of the batch (``batch_rays x samples per ray``).

The constants were measured with ``benchmarks/photo_set_memory.py`` (20 photos of 120x80,
5 steps, 2 threads): 1,106 / 1,173 / 1,348 MiB peak at 1,024 / 4,096 / 16,384 rays per step
with the default model (17.0 M parameters, 48 samples per ray).

Of the memory available when the run starts (``MemAvailable``, or what the cgroup of the
process leaves, whichever is smaller), :data:`USABLE_FRACTION` is planned for.
"""
from __future__ import annotations

import os

from .limits import TRAIN_BYTES_PER_SAMPLE

MIB = 2 ** 20
BASE_BYTES = 680 * MIB
PARAMETER_COPIES = 4
SAMPLE_BYTES = TRAIN_BYTES_PER_SAMPLE     # one home: mi_nerfpp.limits
USABLE_FRACTION = 0.8


def available_bytes() -> int:
    """Memory available to this process now: the kernel's ``MemAvailable``, bounded by the
    limit of its cgroup (containers), or the free physical pages where neither is known."""
    found = []
    try:
        with open('/proc/meminfo') as f:
            for line in f:
                if line.startswith('MemAvailable:'):
                    found.append(int(line.split()[1]) * 1024)
    except OSError:
        pass
    for limit, usage in (('/sys/fs/cgroup/memory.max', '/sys/fs/cgroup/memory.current'),
                         ('/sys/fs/cgroup/memory/memory.limit_in_bytes',
                          '/sys/fs/cgroup/memory/memory.usage_in_bytes')):
        try:
            with open(limit) as f, open(usage) as g:
                text = f.read().strip()
                if text != 'max' and int(text) < 2 ** 60:
                    found.append(max(int(text) - int(g.read().strip()), 0))
            break
        except (OSError, ValueError):
            continue
    if not found:
        found.append(os.sysconf('SC_AVPHYS_PAGES') * os.sysconf('SC_PAGE_SIZE'))
    return min(found)


def threads() -> int:
    """Dr.Jit's worker threads (one per core unless set otherwise)."""
    import drjit as dr
    return dr.thread_count()


def working_set(parameters: int, batch_rays: int, samples_per_ray: int,
                thread_count: int | None = None) -> int:
    """Bytes of a training step's working set (see the module docstring); ``thread_count``
    default: Dr.Jit's."""
    thread_count = threads() if thread_count is None else thread_count
    return int(BASE_BYTES + 4 * parameters * (PARAMETER_COPIES + thread_count)
               + SAMPLE_BYTES * batch_rays * samples_per_ray)


def model_parameters(config) -> int:
    """Parameters of the model a :class:`~mi_nerfpp.config.TrainConfig` trains, counting
    the feature grids (the colour networks and MLP fields add well under 1 % of a grid
    model; an MLP-only model counts as 0): a foreground level of resolution r holds r³ cells,
    a background level ``max(int(r s), 4) x r x 2r`` (``s``: its ``--bg-s-ratio``), each of
    ``--grid-channels`` floats (:meth:`mi_nerfpp.fields.GridField._grid_shape`)."""
    m = config.model
    total = 0
    volumes = [('ball', m.field)] + ([('inverted_sphere', m.bg_field or m.field)]
                                     if m.kind == 'nerfpp' else [])
    for domain, kind in volumes:
        if kind != 'grid':
            continue
        levels = m.levels(domain)
        ratios = m.bg_s_ratio * len(levels) if len(m.bg_s_ratio) == 1 else m.bg_s_ratio
        for r, s in zip(levels, ratios):
            cells = r ** 3 if domain == 'ball' else max(int(r * s), 4) * r * 2 * r
            total += cells * m.grid_channels
        total += sum(config.grid_planes_entries(domain))
    return total


def training_working_set(config=None) -> int:
    """:func:`working_set` of the training step of a
    :class:`~mi_nerfpp.config.TrainConfig` (default: the default options) on Dr.Jit's
    threads."""
    if config is None:
        from .config import TrainConfig
        config = TrainConfig()
    return working_set(model_parameters(config), config.schedule.batch_rays,
                       config.samples_per_ray)


def image_budget(step_bytes: int | None = None, available: int | None = None) -> int:
    """Bytes left for the images: :data:`USABLE_FRACTION` of ``available`` (default: what
    :func:`available_bytes` finds) less a training step's working set ``step_bytes``
    (default: :func:`training_working_set` of the default options); never below 0."""
    available = available_bytes() if available is None else available
    step_bytes = training_working_set() if step_bytes is None else step_bytes
    return max(int(USABLE_FRACTION * available) - step_bytes, 0)
