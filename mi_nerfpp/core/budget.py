"""Sizing: what a training run, a render or a capture may take, against Dr.Jit's arrays and
this machine's memory. The one home of every size limit and memory estimate.

Two limits bound every array: Dr.Jit's arrays hold at most :data:`MAX_ARRAY_ENTRIES`
(2^32 - 1) entries, and all of them together must fit in memory. A refusal names the option
and the largest value that fits, before Dr.Jit sees it (instead of Dr.Jit's
``jit_var_counter`` message or the kernel's out-of-memory kill).

A training run is described by a :class:`Sizing` (each volume's grid levels, planes and sparse
levels, the colour MLP, rays per step, samples per ray, the occupancy grids), which the training
layer makes from its options (:meth:`~mi_nerfpp.training.config.TrainConfig.sizing`), and sized
once, by :func:`plan` (``plan(config.sizing(), Machine.here())``), which returns a
:class:`Plan`: the entries of its arrays, the bytes they take, the first limit the sizes exceed
with the largest value of that size that fits, and the bytes left for the images (what the
automatic downscale spends, :class:`~mi_nerfpp.data.dataset.AutoDownscale`).
Its one memory model:

- the process with Mitsuba, Dr.Jit, LLVM and the step's kernels: :data:`BASE_BYTES`;
- each parameter (float32) :data:`PARAMETER_COPIES` times (value, gradient, Adam's two
  moments) plus once per Dr.Jit thread (the gradients of large grids are summed in one copy
  per thread);
- each occupancy cell :data:`OCCUPANCY_BYTES_PER_CELL`;
- :data:`TRAIN_BYTES_PER_SAMPLE` per field sample of a step (``batch_rays x samples per ray``),
  in proportion to the colour MLP's hidden units (``--color-width x --color-layers``) beyond
  :data:`MEASURED_COLOR_UNITS`, those of the measured runs.

The options must fit in this machine's physical memory; the images get
:data:`USABLE_FRACTION` of the memory available when the run starts, less the rest of the run.
The constants were measured with the peak resident memory of small runs on the CPU
(``llvm_ad_rgb``; ``benchmarks/photo_set_memory.py``: 1,106 / 1,173 / 1,348 MiB peak at 1,024 /
4,096 / 16,384 rays per step with the default model, 17.0 M parameters, 48 samples per ray) and
rounded up; the measurements are noted at each constant.

The ``nerfpp`` integrator renders ``chunk_rays`` rays at a time, and :func:`check_chunk_sizes`
refuses per-chunk arrays beyond :data:`MAX_CHUNK_ENTRIES`; a capture's images are sized with
:data:`CAPTURE_BYTES_PER_PIXEL`. No option is known here by name: a refusal names the option
through the words the :class:`Sizing` carries for each size (:attr:`Sizing.flags`).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, replace

import drjit as dr

from mi_nerfpp.core.arrays import llvm_backend
from mi_nerfpp.core.encodings import S_RATIO, plane_shapes, sparse_s, sparse_shape
from mi_nerfpp.core.occupancy import grid_shape

# Dr.Jit 1.x: "jit_var_counter(): tried to create an array with N entries, which exceeds the
# limit of 2^32 == 4294967296 entries".
MAX_ARRAY_ENTRIES = 2 ** 32 - 1

MIB = 1 << 20
GIB = 1 << 30
# The process with Mitsuba, Dr.Jit, LLVM and a training step's compiled kernels.
BASE_BYTES = 680 * MIB
# Copies of each parameter while training: value, gradient, Adam's two moments (plus one per
# Dr.Jit thread, :func:`parameter_bytes`).
PARAMETER_COPIES = 4
# One field sample of a training step (rays per step x samples per ray): the forward pass,
# the AD graph and the gradients. Measured ~160 B (batches of 4k-65k rays, 48-160 samples), and
# 350 B with the process's growth included (benchmarks/photo_set_memory.py, 1,024-16,384 rays
# of 48 samples).
TRAIN_BYTES_PER_SAMPLE = 350
# The colour MLP's hidden units (width x layers) of the runs TRAIN_BYTES_PER_SAMPLE was measured
# with (the default 32 x 1); a wider or deeper MLP holds its activations and their gradients for
# every sample of a step (the (width, samples) tensors of tensor mode), so a sample takes
# proportionally more.
MEASURED_COLOR_UNITS = 32
# One field sample of a render (the integrator's chunk of rays x samples per ray, no AD).
# Measured ~40 B (16k rays, 2k samples per ray).
RENDER_BYTES_PER_SAMPLE = 64
# One cell of an occupancy grid (its density, the refresh's copy). Measured ~4 B.
OCCUPANCY_BYTES_PER_CELL = 16
# One pixel of a synthetic capture while it is written (the 8-bit image kept until its split
# is written, its float copy, the render and the ground-truth layers of the view).
CAPTURE_BYTES_PER_PIXEL = 64
# A camera of a video's path (measured 641 B per camera with tracemalloc over 20,000 orbit
# cameras); a video also holds every frame's 8-bit RGB pixels while it is assembled.
VIDEO_CAMERA_BYTES = 1024
# Of the memory available when a run starts, the share planned for.
USABLE_FRACTION = 0.8
# Rays per chunk of a primal render: the ``nerfpp`` integrator's default ``chunk_rays``, with
# which evaluations, previews and videos render a trained model.
RENDER_CHUNK_RAYS = 1 << 15
# Largest number of entries of one per-sample array in a chunk of rays (``chunk_rays`` times
# the samples per ray of a volume, the path segments or the catcher directions): a volume's
# samples take about 200 bytes each, so a chunk stays below about 7 GB, and far below Dr.Jit's
# 2^32 entries per array.
MAX_CHUNK_ENTRIES = 1 << 25


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
# parameters and, before training, sample counts whose renders it would refuse (:func:`plan`).

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
    :data:`MAX_CHUNK_ENTRIES` (``sampling``: a dict or :class:`~mi_nerfpp.core.render.Sampling`;
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


# ----------------------------------------------------------------------------- the machine

@dataclass(frozen=True)
class Machine:
    """What a plan is made against: physical ``memory`` (bytes; what the options must fit
    in), the memory ``available`` when the run starts (what the images share) and Dr.Jit's
    worker ``threads`` (each holds a copy of the large grids' gradients on the CPU; none on
    CUDA, where a step's gradients are not expanded per thread). On CUDA the arrays live in
    the GPU's memory, which is not read: the plan is made against the host's."""
    memory: int
    available: int
    threads: int

    @classmethod
    def here(cls) -> Machine:
        """This machine, now."""
        return cls(memory_bytes(), available_bytes(), dr.thread_count() if llvm_backend() else 0)


# ----------------------------------------------------------------------------- a run's sizes
# A run's sizes come from the training layer as a Sizing (``TrainConfig.sizing()``, where its
# options are resolved into them once); a refusal names an option only through Sizing.flags.


@dataclass(frozen=True)
class VolumeSizes:
    """One volume of a run as it sizes arrays: its ``domain`` (``'ball'`` or
    ``'inverted_sphere'``), the ``kind`` of its field and, for a grid field, the resolutions of its
    dense ``levels``, its ``planes`` and its ``sparse`` levels, and (in the inverted sphere) its
    ``s_ratios``, one per level (an MLP field has none of these). ``levels_by``, ``planes_by``,
    ``sparse_by``: the size that sets its levels, planes and sparse levels (a key of
    :attr:`Sizing.flags`; volumes that share it are sized together)."""
    domain: str
    kind: str
    levels: tuple = ()
    planes: tuple = ()
    sparse: tuple = ()
    s_ratios: tuple = ()
    levels_by: str = ''
    planes_by: str = ''
    sparse_by: str = ''


@dataclass(frozen=True)
class Sizing:
    """What sizes a training run's arrays: its ``volumes`` (the foreground first), the grid
    fields' ``grid_channels`` and colour MLP (``color_width`` x ``color_layers``, its inputs'
    ``dir_octaves`` and ``appearance_dims``), ``batch_rays`` per step, ``samples_per_ray``
    (field samples per training ray: coarse and fine, every volume), the ``render_sampling``
    of the model's renders (a :class:`~mi_nerfpp.core.render.Sampling`), the occupancy grids
    (``occupancy``: whether there are any, ``occupancy_res``) and ``sparse_entries`` (the most
    entries of one sparse level).

    ``flags``: for each size a refusal may name (the scalar fields here and each volume's
    ``levels_by``, ``planes_by``), the command-line words that set it (``'--batch-rays
    1024'``); ``defaults``: the default values of ``grid_channels`` and ``batch_rays``, which a
    refusal blames before the others when they are raised above them."""
    volumes: tuple
    grid_channels: int
    color_width: int
    color_layers: int
    dir_octaves: int
    appearance_dims: int
    batch_rays: int
    samples_per_ray: int
    render_sampling: object
    occupancy: bool
    occupancy_res: int
    sparse_entries: int
    flags: dict = field(default_factory=dict, repr=False, compare=False)
    defaults: dict = field(default_factory=dict, repr=False, compare=False)

    def volume(self, domain) -> VolumeSizes | None:
        """The volume over ``domain``; None when the run has none there."""
        return next((v for v in self.volumes if v.domain == domain), None)

    def with_size(self, name: str, value: int) -> Sizing:
        """A copy with size ``name`` at ``value``: a scalar size, or the finest level of the
        levels or planes that ``name`` sets (in every volume it sets them; the other levels
        kept)."""
        if name in _SCALAR_SIZES:
            return replace(self, **{name: value})

        def finest_at(levels):
            i = levels.index(max(levels))
            return levels[:i] + (value,) + levels[i + 1:]
        return replace(self, volumes=tuple(
            replace(v, **{part: finest_at(getattr(v, part))
                          for part, by in _parts(v) if by == name and getattr(v, part)})
            for v in self.volumes))

    def size(self, name: str) -> int:
        """The value of size ``name``: a scalar size, or the finest level of the levels or
        planes that ``name`` sets."""
        if name in _SCALAR_SIZES:
            return getattr(self, name)
        sets = [max(getattr(v, part)) for v in self.volumes
                for part, by in _parts(v) if by == name and getattr(v, part)]
        if not sets:
            raise ValueError(f"no size '{name}' in this run")
        return sets[0]

    def sets_levels(self, name: str) -> bool:
        """Whether size ``name`` sets grid levels or planes (a resolution) of some volume."""
        return any(name in (v.levels_by, v.planes_by, v.sparse_by) for v in self.volumes)

    def sparse_step(self, name: str) -> int:
        """The step of the resolutions of the sparse levels that size ``name`` sets (their
        bricks are the occupancy cells: multiples of the cells along Y); 1 for another size."""
        steps = [grid_shape(v.domain, self.occupancy_res)[1] for v in self.volumes
                 if v.sparse_by == name and v.sparse]
        return steps[0] if steps else 1

    def color_parameters(self) -> int:
        """Weights of the colour MLPs of the grid fields (:class:`~.fields.GridField`: the
        features, the encoded direction and the appearance code in, ``color_layers`` hidden
        layers, RGB out)."""
        total = 0
        for v in self.volumes:
            if v.kind == 'grid':
                n_in = ((len(v.levels) + len(v.planes) + len(v.sparse))
                        * (self.grid_channels - 1)
                        + 3 * (1 + 2 * self.dir_octaves) + self.appearance_dims)
                w = self.color_width
                total += (n_in + 1) * w + (self.color_layers - 1) * (w + 1) * w + (w + 1) * 3
        return total

    def color_units(self) -> int:
        """Hidden units of the colour MLPs (width x layers); none without a grid field."""
        grid = any(v.kind == 'grid' for v in self.volumes)
        return self.color_width * self.color_layers if grid else 0


def _parts(v: VolumeSizes):
    """``(part, the size that sets it)`` of a volume's resolutions."""
    return (('levels', v.levels_by), ('planes', v.planes_by), ('sparse', v.sparse_by))


# The sizes that are one number of the run (the others are volumes' levels and planes).
_SCALAR_SIZES = ('batch_rays', 'samples_per_ray', 'grid_channels', 'color_width',
                 'occupancy_res', 'sparse_entries')


def _per_level(values, n):
    values = (values,) if isinstance(values, (int, float)) else tuple(values)
    return values * n if len(values) == 1 else values


def grid_level_entries(sizing: Sizing, domain) -> list[int]:
    """Entries of each feature-grid level of one volume (:class:`~.fields.GridField`'s
    shapes): ``R³`` cells in the ball, ``max(⌊q·R⌋, 4) × R × 2R`` in the inverted sphere, times
    ``grid_channels``; empty for a volume without a grid field."""
    v, channels = sizing.volume(domain), sizing.grid_channels
    if v is None:
        return []
    if domain == 'ball':
        return [r ** 3 * channels for r in v.levels]
    ratios = _per_level(v.s_ratios, len(v.levels))
    return [max(int(r * q), 4) * r * 2 * r * channels for r, q in zip(v.levels, ratios)]


def grid_plane_entries(sizing: Sizing, domain, largest: bool = False) -> list[int]:
    """Entries of each plane level of one volume's grid field (its three planes,
    :func:`~mi_nerfpp.core.encodings.plane_shapes`), times ``grid_channels``; ``largest``: of its
    largest plane only (one array)."""
    v = sizing.volume(domain)
    if v is None:
        return []
    combine = max if largest else sum
    return [combine(h * w for _, (h, w) in plane_shapes(domain, r)) * sizing.grid_channels
            for r in v.planes]


# The sparse foreground level a run chooses unless told (``--grid-sparse``): twice the finest
# dense level's resolution, where its cells span at least SPARSE_PIXELS training pixels at the
# scene's centre (finer cells than that the images cannot teach). Measured on gt_plaza at
# 512x384 (a pixel ~0.0018 of the unit ball there), after 10 minutes alone: 27.21 against
# 26.80 dB with a sparse level of 256 in both volumes, the foreground's error down 0.8 dB and
# the background's up 0.25 dB (benchmarks/results/error_split_plaza512_*.json), so the
# background gets no finer level unless told (``--bg-grid-sparse``; its finest dense level goes
# into bricks with the foreground's, mi_nerfpp.training.choices.background_in_bricks).
SPARSE_FACTOR = 2
SPARSE_PIXELS = 2


def sparse_resolution(footprint: float, finest: int, occupancy_res: int) -> int | None:
    """The resolution of the sparse foreground level for a capture whose training pixels are
    ``footprint`` wide at the scene's centre (in the unit ball's units): ``SPARSE_FACTOR`` times
    the ``finest`` dense level, rounded up to a multiple of ``occupancy_res`` (its bricks are
    the occupancy cells), when its cells (``2/R``) span at least :data:`SPARSE_PIXELS` pixels;
    None when they would not."""
    r = SPARSE_FACTOR * int(finest)
    r = -(-r // occupancy_res) * occupancy_res
    return r if spans_pixels(r, footprint) else None


def spans_pixels(resolution: int, footprint: float) -> bool:
    """Whether a cell of a foreground level of ``resolution`` (``2/R`` of the unit ball) spans
    at least :data:`SPARSE_PIXELS` training pixels ``footprint`` wide: the rule for storing a
    level in bricks (:func:`sparse_resolution`,
    :func:`mi_nerfpp.training.choices.choose_sparse_level`)."""
    return 2.0 / resolution >= SPARSE_PIXELS * footprint


def sparse_brick_shapes(sizing: Sizing, domain) -> list[tuple]:
    """Texels (Z, Y, X) of one brick of each sparse level of one volume: the level's texels
    over the occupancy cells (:class:`~.bricks.BrickGrid`; in the inverted sphere along s as
    :func:`~.encodings.sparse_s` has them)."""
    v = sizing.volume(domain)
    if v is None or not v.sparse:
        return []
    blocks = grid_shape(domain, sizing.occupancy_res)
    s = None
    if domain == 'inverted_sphere':
        s = sparse_s(v.sparse, (v.s_ratios or (S_RATIO,))[-1], blocks)
    return [tuple(n // b for n, b in zip(sparse_shape(domain, r, blocks, s), blocks))
            for r in v.sparse]


def sparse_level_sizes(sizing: Sizing, domain) -> list[int]:
    """Entries of each sparse level of one volume's grid field with every brick allocated
    (what ``--sparse-at 0`` allocates at the first step); empty without sparse levels."""
    cells = math.prod(grid_shape(domain, sizing.occupancy_res))
    return [cells * max(math.prod(brick) * sizing.grid_channels, 1)
            for brick in sparse_brick_shapes(sizing, domain)]


def sparse_level_entries(sizing: Sizing, domain) -> list[int]:
    """Entries of each sparse level of one volume's grid field at most
    (:class:`~.bricks.BrickGrid`): its bricks up to ``sparse_entries`` (one brick at least),
    or all of them when fewer; empty without a grid field or sparse levels."""
    limit, out = sizing.sparse_entries, []
    for brick, full in zip(sparse_brick_shapes(sizing, domain), sparse_level_sizes(sizing, domain)):
        per_brick = max(math.prod(brick) * sizing.grid_channels, 1)
        out.append(min(full, max(limit // per_brick, 1) * per_brick))
    return out


def occupancy_cells(sizing: Sizing) -> list[int]:
    """Cells of each volume's occupancy grid (:class:`~.occupancy.OccupancyGrid`)."""
    if not sizing.occupancy:
        return []
    return [math.prod(grid_shape(v.domain, sizing.occupancy_res)) for v in sizing.volumes]


def _grid_parts(s: Sizing) -> dict:
    """Entries of the grids by the size that sets them: ``{size: entries}``."""
    return _sum_into({}, [(v.levels_by, sum(grid_level_entries(s, v.domain)))
                          for v in s.volumes]
                     + [(v.planes_by, sum(grid_plane_entries(s, v.domain)))
                        for v in s.volumes]
                     + [('sparse_entries', sum(sum(sparse_level_entries(s, v.domain))
                                               for v in s.volumes))])


def _sum_into(parts: dict, items) -> dict:
    """``parts`` with each ``(size, entries)`` of ``items`` added to its size's entries."""
    for size, entries in items:
        parts[size] = parts.get(size, 0) + entries
    return parts


def _entries(s: Sizing) -> dict:
    return {'grids': sum(_grid_parts(s).values()) + s.color_parameters(),
            'occupancy': sum(occupancy_cells(s)),
            'samples': s.batch_rays * s.samples_per_ray}


def _bytes(entries: dict, threads: int, color_units: int = 0) -> dict:
    """Bytes of a run's parts from its entries; ``color_units``: the colour MLP's hidden units
    (:meth:`Sizing.color_units`), which scale a step's bytes per sample."""
    per_sample = TRAIN_BYTES_PER_SAMPLE * max(1.0, color_units / MEASURED_COLOR_UNITS)
    return {'process': BASE_BYTES,
            'grids': 4 * (PARAMETER_COPIES + threads) * entries['grids'],
            'occupancy': OCCUPANCY_BYTES_PER_CELL * entries['occupancy'],
            'step': int(per_sample * entries['samples'])}


def _exceeded(s: Sizing, machine: Machine):
    """The first limit the sizes ``s`` exceed on ``machine``, as ``(size, what)``, or None
    when they fit."""
    budget = machine.memory
    array = 'more than one Dr.Jit array holds (2^32 - 1 entries)'
    # A render of the model (evaluation, previews, videos) takes its samples per ray for a
    # chunk of the integrator's rays at a time, whatever --batch-rays.
    chunk = RENDER_CHUNK_RAYS
    spr = s.samples_per_ray
    if not fits(spr, chunk, chunk * RENDER_BYTES_PER_SAMPLE, budget):
        return 'samples_per_ray', (f'renders of the model take {spr:,} samples per ray for '
                                   f'{chunk:,} rays at a time, more than Dr.Jit\'s arrays '
                                   f'(2^32 - 1 entries) and {memory_text(budget)} of memory '
                                   f'hold')
    raised_channels = s.grid_channels > s.defaults.get('grid_channels', s.grid_channels)
    for v in s.volumes:
        behind = 'background ' if v.domain != 'ball' else ''
        for r, n in zip(v.levels, grid_level_entries(s, v.domain)):
            if n > MAX_ARRAY_ENTRIES:
                return (v.levels_by if not raised_channels else 'grid_channels',
                        f'a {behind}level of resolution {r} has {n:,} entries (--grid-channels '
                        f'{s.grid_channels}), {array}')
    for v in s.volumes:
        behind = 'background ' if v.domain != 'ball' else ''
        for r, n in zip(v.planes, grid_plane_entries(s, v.domain, largest=True)):
            if n > MAX_ARRAY_ENTRIES:
                return (v.planes_by, f'a {behind}plane level of resolution {r} has a plane of '
                                     f'{n:,} entries (--grid-channels {s.grid_channels}), '
                                     f'{array}')
    for v in s.volumes:
        # A level keeps one brick however large (issue 63: a resolution of 65,536 made one
        # brick of 1024^3 texels, gigabytes, while the plan counted --sparse-entries).
        behind = 'background ' if v.domain != 'ball' else ''
        for r, brick in zip(v.sparse, sparse_brick_shapes(s, v.domain)):
            n = math.prod(brick) * s.grid_channels
            if n > s.sparse_entries:
                return (v.sparse_by, f'one brick of a {behind}sparse level of resolution {r:,} '
                                     f'(an occupancy cell) holds {"x".join(map(str, brick))} '
                                     f'texels, {n:,} entries (--grid-channels '
                                     f'{s.grid_channels}), more than '
                                     f'{s.flags.get("sparse_entries", "--sparse-entries")} '
                                     f'lets a sparse level hold')
        for n in sparse_level_entries(s, v.domain):
            if n > MAX_ARRAY_ENTRIES:
                return 'sparse_entries', f'a sparse level of {n:,} entries is {array}'
    for cells in occupancy_cells(s):
        if cells > MAX_ARRAY_ENTRIES:
            return 'occupancy_res', f'a grid of {cells:,} cells is {array}'
    if s.batch_rays * spr > MAX_ARRAY_ENTRIES:
        return 'batch_rays', (f'{s.batch_rays:,} rays x {spr} samples per ray are '
                              f'{s.batch_rays * spr:,} field samples per step, {array}')
    if s.color_units():
        # The colour MLP in a training step: a (width, samples) tensor per layer, and its
        # weights (width x width between hidden layers).
        rows = s.color_width * s.batch_rays * spr
        weights = s.color_width * s.color_width if s.color_layers > 1 else 0
        if max(rows, weights) > MAX_ARRAY_ENTRIES:
            return 'color_width', (f'a colour MLP of width {s.color_width:,} holds arrays of '
                                   f'{max(rows, weights):,} entries (its width x the '
                                   f'{s.batch_rays * spr:,} field samples of a step), {array}')
    need = _bytes(_entries(s), machine.threads, s.color_units())
    if sum(need.values()) <= budget:
        return None
    what = (f'a run takes about {memory_text(sum(need.values()))} (process '
            f'{memory_text(need["process"])}, grids and MLPs {memory_text(need["grids"])}, occupancy '
            f'{memory_text(need["occupancy"])}, training step {memory_text(need["step"])}), '
            f'more than this machine\'s {memory_text(budget)}')
    grown = {k: v for k, v in need.items() if k != 'process'}
    heaviest = max(grown, key=grown.get)
    if heaviest == 'step' and s.color_units() > MEASURED_COLOR_UNITS * s.color_layers:
        return 'color_width', what
    if heaviest == 'grids':
        if raised_channels:
            return 'grid_channels', what
        parts = _grid_parts(s)
        parts['color_width'] = s.color_parameters()
        return max(parts, key=parts.get), what
    if heaviest == 'occupancy':
        return 'occupancy_res', what
    raised_batch = s.batch_rays > s.defaults.get('batch_rays', s.batch_rays)
    return ('batch_rays' if raised_batch else 'samples_per_ray'), what


def largest_that_fits(sizing: Sizing, size: str, machine: Machine) -> int:
    """The largest value of ``size`` (a scalar size of :class:`Sizing` - ``batch_rays``,
    ``samples_per_ray``, ``grid_channels``, ``color_width``, ``occupancy_res``,
    ``sparse_entries`` -, or what a volume's ``levels_by`` / ``planes_by`` names: the finest
    level's resolution, the others kept) with which the run fits on ``machine``; 0 when none
    does."""
    high = sizing.size(size)
    low = 2 if size == 'grid_channels' or sizing.sets_levels(size) else (
        4 if size == 'occupancy_res' else 1)

    def ok(value):
        return _exceeded(sizing.with_size(size, value), machine) is None

    if not ok(low):
        return 0
    while ok(high):                                  # fits: look above
        if high >= MAX_ARRAY_ENTRIES:
            return high
        low, high = high, min(2 * high, MAX_ARRAY_ENTRIES)
    while low < high:                                # the largest value that fits, by bisection
        mid = (low + high + 1) // 2
        low, high = (mid, high) if ok(mid) else (low, mid - 1)
    return low - low % sizing.sparse_step(size)      # sparse levels: multiples of the cells


@dataclass(frozen=True)
class Plan:
    """What a training run takes on a machine (:func:`plan`).

    ``sizing``: what it was made for; ``entries``: the run's ``grids`` (parameters),
    ``occupancy`` cells and field ``samples`` per step; ``bytes``: what the ``process``, the
    ``grids`` (with gradients, moments and the threads' gradient copies), the ``occupancy``
    grids and a training ``step`` take; ``exceeded``: ``(size, what)`` of the first limit the
    sizes exceed, or None, and ``largest``: the largest value of that size that fits;
    ``images``: the bytes left for the images (:data:`USABLE_FRACTION` of the memory
    available, less ``total``)."""
    machine: Machine
    entries: dict
    bytes: dict
    exceeded: tuple | None = None
    largest: int | None = None
    chunk_error: str | None = field(default=None, repr=False)
    sizing: Sizing | None = field(default=None, repr=False)

    @property
    def total(self) -> int:
        """Bytes of the run without its images."""
        return sum(self.bytes.values())

    @property
    def images(self) -> int:
        """Bytes left for the images (:func:`images_budget`)."""
        return images_budget(self.total, self.machine.available)

    def describe(self) -> str:
        """One line for the run's log: entries, bytes and what is left for the images."""
        return (f'plan: {self.entries["grids"] / 1e6:.1f} M grid entries, '
                f'{self.entries["samples"]:,} field samples per step; about '
                f'{memory_text(self.total)} of {memory_text(self.machine.memory)} '
                f'({memory_text(self.machine.available)} available, '
                f'{self.machine.threads} threads), {memory_text(self.images)} left for images')


def plan(sizing: Sizing, machine: Machine | None = None) -> Plan:
    """Size a training run (``sizing``: its :class:`Sizing`,
    :meth:`~mi_nerfpp.training.config.TrainConfig.sizing`) on ``machine`` (default:
    :meth:`Machine.here`), once: see :class:`Plan`. Raise with :func:`check` to refuse sizes
    that do not fit."""
    machine = machine or Machine.here()
    entries = _entries(sizing)
    chunk_error = None
    try:
        check_chunk_sizes(RENDER_CHUNK_RAYS, sizing.render_sampling, 1, 1)
    except ValueError:
        r = sizing.render_sampling
        per_volume = max(r.fg_samples, r.bg_samples) + r.fine_samples
        chunk_error = (
            f'{sizing.flags["samples_per_ray"]} are too many: renders of the model take '
            f'{per_volume:,} samples per ray of a volume (coarse and fine) for '
            f'{RENDER_CHUNK_RAYS:,} rays at a time, more than the nerfpp integrator\'s '
            f'{MAX_CHUNK_ENTRIES:,} entries per array; at most '
            f'{MAX_CHUNK_ENTRIES // RENDER_CHUNK_RAYS:,} samples per ray of a volume fit')
    exceeded = _exceeded(sizing, machine)
    best = None if exceeded is None else largest_that_fits(sizing, exceeded[0], machine)
    return Plan(machine, entries, _bytes(entries, machine.threads, sizing.color_units()),
                exceeded, best, chunk_error, sizing)


def check(run_plan: Plan):
    """Refuse, before any work, a ``run_plan`` whose sizes Dr.Jit's arrays cannot hold or
    that do not fit in memory: a ValueError naming the option (its :attr:`Sizing.flags`) and
    the largest value that fits. Renders the integrator would refuse come first (a run must
    not train and then fail to evaluate)."""
    if run_plan.chunk_error:
        raise ValueError(run_plan.chunk_error)
    if run_plan.exceeded is None:
        return
    size, what = run_plan.exceeded
    best, s = run_plan.largest, run_plan.sizing
    if size == 'samples_per_ray':
        raise ValueError(f'{s.flags[size]} are too many: {what}; at most {best:,} samples per '
                         f'ray (coarse and fine, every volume) fit with '
                         f'{s.flags["batch_rays"]}')
    largest_text = (f'the finest level fits at resolution {best:,} at most'
                    if s.sets_levels(size) else f'at most {best:,} fits')
    if best == 0:
        largest_text = 'not even the smallest value fits: lower the other options'
    raise ValueError(f'{s.flags[size]} is too large: {what}; {largest_text}')


def images_budget(run_bytes: int = BASE_BYTES, available: int | None = None) -> int:
    """Bytes left for a run's images: :data:`USABLE_FRACTION` of ``available`` (default: what
    :func:`available_bytes` finds now) less the rest of the run, ``run_bytes`` (default: the
    process alone); never below 0."""
    available = available_bytes() if available is None else available
    return max(int(USABLE_FRACTION * available) - run_bytes, 0)


def video_frames_limit(width: int, height: int, available: int | None = None) -> int:
    """The most frames of ``width`` x ``height`` pixels a video can take: its cameras
    (:data:`VIDEO_CAMERA_BYTES`) and, while the video is assembled, every frame's 8-bit RGB
    pixels are held in memory, within :func:`images_budget` (of ``available`` bytes, default
    what is available now)."""
    return largest(1, width * height * 3 + VIDEO_CAMERA_BYTES,
                   images_budget(available=available))
