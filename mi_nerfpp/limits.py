"""How large the arrays of a run, a render or a capture may be, checked before Dr.Jit sees them.

Two limits bound every array: Dr.Jit's arrays hold at most :data:`MAX_ARRAY_ENTRIES`
(2^32 - 1) entries, and all of them together must fit in this machine's memory
(:func:`memory_bytes`). The options that size arrays (rays per step, samples per ray, grid and
occupancy resolutions, image and film sizes) are checked against both where they are read
(:mod:`mi_nerfpp.config`, :mod:`mi_nerfpp.synth`), and a refusal names the option and the
largest value that fits (:func:`largest`), instead of Dr.Jit's ``jit_var_counter`` message or
the kernel's out-of-memory kill.

Memory is estimated from bytes per entry, measured with the peak resident memory of small
runs on the CPU (``llvm_ad_rgb``) and rounded up; the measurements are noted at each
constant. This module imports nothing of the package (every other module may use it).
"""
from __future__ import annotations

import os

# Dr.Jit 1.x: "jit_var_counter(): tried to create an array with N entries, which exceeds the
# limit of 2^32 == 4294967296 entries".
MAX_ARRAY_ENTRIES = 2 ** 32 - 1

# One field sample of a training step (rays per step x samples per ray): the forward pass,
# the AD graph and the gradients. Measured ~160 B (batches of 4k-65k rays, 48-160 samples), and
# 350 B with the process's growth included (benchmarks/photo_set_memory.py, 1,024-16,384 rays
# of 48 samples; :mod:`mi_nerfpp.memory`, which plans the automatic downscale with it).
TRAIN_BYTES_PER_SAMPLE = 350
# One field sample of a render (the integrator's chunk of rays x samples per ray, no AD).
# Measured ~40 B (16k rays, 2k samples per ray).
RENDER_BYTES_PER_SAMPLE = 64
# One entry of a feature grid while training: the value, its gradient, Adam's two moments,
# the checkpoint's copy. Measured ~45 B (grids of 2 M and 17 M entries).
GRID_BYTES_PER_ENTRY = 64
# One cell of an occupancy grid (its density, the refresh's copy). Measured ~4 B.
OCCUPANCY_BYTES_PER_CELL = 16
# One pixel of a synthetic capture while it is written (the 8-bit image kept until its split
# is written, its float copy, the render and the ground-truth layers of the view).
CAPTURE_BYTES_PER_PIXEL = 64
# Rays per chunk of a primal render: the ``nerfpp`` integrator's default ``chunk_rays``, with
# which evaluations, previews and videos render a trained model.
RENDER_CHUNK_RAYS = 1 << 15

# Largest number of entries of one per-sample array in a chunk of rays (``chunk_rays`` times
# the samples per ray of a volume, the path segments or the catcher directions): a volume's
# samples take about 200 bytes each, so a chunk stays below about 7 GB, and far below Dr.Jit's
# 2^32 entries per array.
MAX_CHUNK_ENTRIES = 1 << 25

GIB = 1 << 30


def memory_bytes() -> int:
    """This machine's physical memory in bytes (what every estimate must fit in)."""
    try:
        return os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES')
    except (ValueError, OSError, AttributeError):      # not POSIX: assume 16 GiB
        return 16 * GIB


def memory_text(nbytes: int | None = None) -> str:
    """``'23 GiB'``: memory as the messages show it (this machine's by default)."""
    nbytes = memory_bytes() if nbytes is None else nbytes
    return f'{nbytes / GIB:.0f} GiB' if nbytes >= GIB else f'{nbytes / (1 << 20):.0f} MiB'


def largest(entries_per_unit: float, bytes_per_unit: float, budget: float | None = None,
            max_entries: int = MAX_ARRAY_ENTRIES) -> int:
    """The largest whole number of units whose largest array (``entries_per_unit`` entries
    each) stays within Dr.Jit's limit and whose memory (``bytes_per_unit`` each) fits in
    ``budget`` bytes (this machine's memory by default); 0 when not even one does."""
    budget = memory_bytes() if budget is None else budget
    by_entries = max_entries // max(int(entries_per_unit), 1)
    by_memory = int(max(budget, 0) // max(bytes_per_unit, 1e-9))
    return max(min(by_entries, by_memory), 0)


def fits(units: float, entries_per_unit: float, bytes_per_unit: float,
         budget: float | None = None) -> bool:
    """Whether ``units`` units (see :func:`largest`) fit."""
    return units <= largest(entries_per_unit, bytes_per_unit, budget)


# ----------------------------------------------------------------------------- render chunks
# The ``nerfpp`` integrator renders ``chunk_rays`` rays at a time; the same rule refuses its XML
# parameters and, before training, sample counts whose renders it would refuse
# (:meth:`mi_nerfpp.config.TrainConfig.check_render_chunks`).

def _largest(name, per_ray, chunk_rays, extra=0, also=''):
    """The refusal of ``name`` when ``chunk_rays`` rays of ``per_ray`` entries are too many."""
    fits = MAX_CHUNK_ENTRIES // chunk_rays - extra
    what = f' (with {also})' if also else ''
    if fits < 1:
        return ValueError(
            f"nerfpp: parameter 'chunk_rays' is {chunk_rays}: a chunk of that many rays cannot "
            f"hold {name}{what} within {MAX_CHUNK_ENTRIES} entries per array; the largest "
            f"chunk_rays that fits is {MAX_CHUNK_ENTRIES // max(per_ray, 1)}")
    return ValueError(
        f"nerfpp: parameter '{name}' is {per_ray - extra}: {chunk_rays} rays per chunk "
        f"(chunk_rays) would hold {chunk_rays * per_ray:.3g} entries per array, more than "
        f"{MAX_CHUNK_ENTRIES} (memory, Dr.Jit's 2^32-entry arrays); the largest {name} that "
        f"fits{what} is {fits}")


def check_chunk_sizes(chunk_rays, sampling, max_depth, catcher_samples):
    """Refuse sample counts, path depth and catcher directions whose per-chunk arrays exceed
    :data:`MAX_CHUNK_ENTRIES` (``sampling``: a dict or :class:`~mi_nerfpp.render.Sampling`;
    None counts are not checked). Each count is first checked alone (the others at their
    least), so the message names the one that is out of range."""
    get = sampling.get if isinstance(sampling, dict) else (lambda k: getattr(sampling, k))
    fine = get('fine_samples')
    if fine is not None and chunk_rays * (1 + fine) > MAX_CHUNK_ENTRIES:
        raise _largest('fine_samples', 1 + fine, chunk_rays, 1, 'one coarse sample')
    fine = fine or 0
    for name in ('fg_samples', 'bg_samples'):
        n = get(name)
        if n is not None and chunk_rays * (n + fine) > MAX_CHUNK_ENTRIES:
            raise _largest(name, n + fine, chunk_rays, fine, f'fine_samples={fine}')
    for name, n in (('max_depth', max_depth), ('catcher_samples', catcher_samples)):
        if chunk_rays * n > MAX_CHUNK_ENTRIES:
            raise _largest(name, n, chunk_rays)
