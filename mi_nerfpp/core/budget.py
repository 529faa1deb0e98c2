"""Sizing: what a training run, a render or a capture may take, against Dr.Jit's arrays and
this machine's memory. The one home of every size limit and memory estimate.

Two limits bound every array: Dr.Jit's arrays hold at most :data:`MAX_ARRAY_ENTRIES`
(2^32 - 1) entries, and all of them together must fit in memory. A refusal names the option
and the largest value that fits, before Dr.Jit sees it (instead of Dr.Jit's
``jit_var_counter`` message or the kernel's out-of-memory kill).

A training run is sized once, by :func:`plan` (``plan(config, Machine.here())``), which
returns a :class:`Plan`: the entries of its arrays, the bytes they take, the first limit the
options exceed with the largest value of that option that fits, and the bytes left for the
images (what the automatic downscale spends, :class:`~mi_nerfpp.data.dataset.AutoDownscale`).
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
:data:`CAPTURE_BYTES_PER_PIXEL`. A config is read through its attributes (no import of the
training layer).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

import drjit as dr

from mi_nerfpp.core.arrays import llvm_backend
from mi_nerfpp.core.encodings import plane_shapes
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


# ----------------------------------------------------------------------------- a run's arrays
# A config is read through its attributes: ``config.model`` (``kind``, ``field``, ``bg_field``,
# ``grid_channels``, ``bg_s_ratio``, ``levels(domain)``, ``planes(domain)``), ``config.sampling``
# (``occupancy``, ``occupancy_res``), ``config.schedule.batch_rays``, ``config.samples_per_ray``
# and ``config.flag(option)`` (the command-line spelling, for messages).

def _has_grid(config, domain) -> bool:
    """Whether the volume of ``domain`` has a grid field."""
    m = config.model
    kind = m.field if domain == 'ball' else m.bg_field
    return kind == 'grid' and (domain == 'ball' or m.kind == 'nerfpp')


def _per_level(values, n):
    values = (values,) if isinstance(values, (int, float)) else tuple(values)
    return values * n if len(values) == 1 else values


def grid_level_entries(config, domain, levels=None, channels=None) -> list[int]:
    """Entries of each feature-grid level of one volume (:class:`~.fields.GridField`'s
    shapes): ``R³`` cells in the ball, ``max(⌊q·R⌋, 4) × R × 2R`` in the inverted sphere, times
    ``--grid-channels``; empty for a volume without a grid field. ``levels``, ``channels``: in
    place of the config's."""
    m = config.model
    if not _has_grid(config, domain):
        return []
    levels = m.levels(domain) if levels is None else levels
    channels = channels or m.grid_channels
    if domain == 'ball':
        return [r ** 3 * channels for r in levels]
    ratios = _per_level(m.bg_s_ratio, len(levels))
    return [max(int(r * q), 4) * r * 2 * r * channels for r, q in zip(levels, ratios)]


def grid_plane_entries(config, domain, planes=None, channels=None,
                       largest: bool = False) -> list[int]:
    """Entries of each plane level of one volume's grid field (its three planes,
    :func:`~mi_nerfpp.core.encodings.plane_shapes`), times ``--grid-channels``; ``largest``: of
    its largest plane only (one array). ``planes``, ``channels``: in place of the config's."""
    m = config.model
    if not _has_grid(config, domain):
        return []
    planes = m.planes(domain) if planes is None else planes
    channels = channels or m.grid_channels
    combine = max if largest else sum
    return [combine(h * w for _, (h, w) in plane_shapes(domain, r)) * channels for r in planes]


# The sparse foreground level a run chooses unless told (``--grid-sparse``): twice the finest
# dense level's resolution, where its cells span at least SPARSE_PIXELS training pixels at the
# scene's centre (finer cells than that the images cannot teach). Measured on gt_plaza at
# 512x384 (a pixel ~0.0018 of the unit ball there), after 10 minutes alone: 27.21 against
# 26.80 dB with a sparse level of 256 in both volumes, the foreground's error down 0.8 dB and
# the background's up 0.25 dB (benchmarks/results/error_split_plaza512_*.json), so the
# background has none unless told (``--bg-grid-sparse``).
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
    return r if 2.0 / r >= SPARSE_PIXELS * footprint else None


def sparse_level_entries(config, domain, limit=None, channels=None) -> list[int]:
    """Entries of each sparse level of one volume's grid field at most
    (:class:`~.bricks.BrickGrid`): its bricks up to ``--sparse-entries`` (``limit``), or all of
    them when fewer; empty without a grid field or sparse levels."""
    m = config.model
    if not _has_grid(config, domain):
        return []
    limit = config.schedule.sparse_entries if limit is None else limit
    channels = channels or m.grid_channels
    if domain == 'ball':
        return [min(limit, r ** 3 * channels) for r in m.sparse(domain)]
    along_s = grid_shape(domain, config.sampling.occupancy_res)[0]
    return [min(limit, along_s * r * 2 * r * channels) for r in m.sparse(domain)]


def occupancy_cells(config, resolution=None) -> list[int]:
    """Cells of each volume's occupancy grid (:class:`~.occupancy.OccupancyGrid`)."""
    if not config.sampling.occupancy:
        return []
    r = config.sampling.occupancy_res if resolution is None else resolution
    return [r ** 3] + ([max(r // 4, 4) * max(r // 2, 4) * r]
                       if config.model.kind == 'nerfpp' else [])


@dataclass(frozen=True)
class Sizes:
    """The values that size a run's arrays: rays per step, samples per ray, each volume's
    grid levels, grid channels and the occupancy resolution."""
    batch_rays: int
    samples_per_ray: int
    grid_levels: tuple
    bg_grid_levels: tuple
    grid_channels: int
    occupancy_res: int
    grid_planes: tuple = ()
    bg_grid_planes: tuple = ()
    sparse_entries: int = 0
    color_width: int = MEASURED_COLOR_UNITS
    color_layers: int = 1

    @classmethod
    def of(cls, config, **values) -> Sizes:
        """The config's sizes, with ``values`` in their place (the background grid follows
        ``grid_levels`` unless it has levels of its own)."""
        m = config.model
        fg = values.get('grid_levels') or m.grid_levels
        bg = values.get('bg_grid_levels') or m.bg_grid_levels or fg
        fg_planes = values.get('grid_planes', m.grid_planes)
        bg_planes = values.get('bg_grid_planes') or m.bg_grid_planes or fg_planes
        return cls(values.get('batch_rays') or config.schedule.batch_rays,
                   values.get('samples_per_ray') or config.samples_per_ray,
                   tuple(fg), tuple(bg), values.get('grid_channels') or m.grid_channels,
                   values.get('occupancy_res') or config.sampling.occupancy_res,
                   tuple(fg_planes), tuple(bg_planes),
                   values.get('sparse_entries') or config.schedule.sparse_entries,
                   values.get('color_width') or m.color_width, m.color_layers)

    def color_parameters(self, config) -> int:
        """Weights of the colour MLPs of the grid fields (:class:`~.fields.GridField`: the
        features and the encoded direction in, ``color_layers`` hidden layers, RGB out)."""
        m, total = config.model, 0
        for domain, levels, planes in (('ball', self.grid_levels, self.grid_planes),
                                       ('inverted_sphere', self.bg_grid_levels,
                                        self.bg_grid_planes)):
            if _has_grid(config, domain):
                n_in = ((len(levels) + len(planes) + len(m.sparse(domain)))
                        * (self.grid_channels - 1)
                        + 3 * (1 + 2 * m.dir_octaves))
                w = self.color_width
                total += (n_in + 1) * w + (self.color_layers - 1) * (w + 1) * w + (w + 1) * 3
        return total

    def color_units(self, config) -> int:
        """Hidden units of the colour MLPs (width x layers); none without a grid field."""
        grid = _has_grid(config, 'ball') or _has_grid(config, 'inverted_sphere')
        return self.color_width * self.color_layers if grid else 0


def _grid_parts(config, sizes: Sizes) -> dict:
    """Entries of the grids by the option that sizes them: ``{option: entries}``."""
    channels = sizes.grid_channels
    return _sum_into({}, [
        ('grid_levels', sum(grid_level_entries(config, 'ball', sizes.grid_levels, channels))),
        (_levels_option(config, 'inverted_sphere'), sum(grid_level_entries(
            config, 'inverted_sphere', sizes.bg_grid_levels, channels))),
        ('grid_planes', sum(grid_plane_entries(config, 'ball', sizes.grid_planes, channels))),
        (_planes_option(config, 'inverted_sphere'), sum(grid_plane_entries(
            config, 'inverted_sphere', sizes.bg_grid_planes, channels))),
        ('sparse_entries', sum(sum(sparse_level_entries(config, d, sizes.sparse_entries,
                                                        channels))
                               for d in ('ball', 'inverted_sphere')))])


def _sum_into(parts: dict, items) -> dict:
    """``parts`` with each ``(option, entries)`` of ``items`` added to its option's entries."""
    for option, entries in items:
        parts[option] = parts.get(option, 0) + entries
    return parts


def _entries(config, sizes: Sizes) -> dict:
    return {'grids': (sum(_grid_parts(config, sizes).values())
                      + sizes.color_parameters(config)),
            'occupancy': sum(occupancy_cells(config, sizes.occupancy_res)),
            'samples': sizes.batch_rays * sizes.samples_per_ray}


def _bytes(entries: dict, threads: int, color_units: int = 0) -> dict:
    """Bytes of a run's parts from its entries; ``color_units``: the colour MLP's hidden units
    (:meth:`Sizes.color_units`), which scale a step's bytes per sample."""
    per_sample = TRAIN_BYTES_PER_SAMPLE * max(1.0, color_units / MEASURED_COLOR_UNITS)
    return {'process': BASE_BYTES,
            'grids': 4 * (PARAMETER_COPIES + threads) * entries['grids'],
            'occupancy': OCCUPANCY_BYTES_PER_CELL * entries['occupancy'],
            'step': int(per_sample * entries['samples'])}


def _levels_option(config, domain):
    """The option that sets the levels of ``domain``'s grid."""
    if domain == 'inverted_sphere' and config.model.bg_grid_levels is not None:
        return 'bg_grid_levels'
    return 'grid_levels'


def _planes_option(config, domain):
    """The option that sets the plane levels of ``domain``'s grid."""
    if domain == 'inverted_sphere' and config.model.bg_grid_planes is not None:
        return 'bg_grid_planes'
    return 'grid_planes'


def _exceeded(config, machine: Machine, **values):
    """The first limit the config (with ``values`` in place of its own, :meth:`Sizes.of`)
    exceeds on ``machine``, as ``(option, what)``, or None when it fits."""
    s = Sizes.of(config, **values)
    budget = machine.memory
    array = 'more than one Dr.Jit array holds (2^32 - 1 entries)'
    # A render of the model (evaluation, previews, videos) takes its samples per ray for a
    # chunk of the integrator's rays at a time, whatever --batch-rays.
    chunk = RENDER_CHUNK_RAYS
    spr = s.samples_per_ray
    if not fits(spr, chunk, chunk * RENDER_BYTES_PER_SAMPLE, budget):
        return 'samples', (f'renders of the model take {spr:,} samples per ray for '
                           f'{chunk:,} rays at a time, more than Dr.Jit\'s arrays (2^32 - 1 '
                           f'entries) and {memory_text(budget)} of memory hold')
    default_channels = type(config.model)().grid_channels
    for domain, levels in (('ball', s.grid_levels), ('inverted_sphere', s.bg_grid_levels)):
        for r, n in zip(levels, grid_level_entries(config, domain, levels, s.grid_channels)):
            if n > MAX_ARRAY_ENTRIES:
                option = (_levels_option(config, domain) if s.grid_channels <= default_channels
                          else 'grid_channels')
                return (option, f'a {"background " if domain != "ball" else ""}level of '
                                f'resolution {r} has {n:,} entries (--grid-channels '
                                f'{s.grid_channels}), {array}')
    for domain, planes in (('ball', s.grid_planes), ('inverted_sphere', s.bg_grid_planes)):
        for r, n in zip(planes, grid_plane_entries(config, domain, planes, s.grid_channels,
                                                   largest=True)):
            if n > MAX_ARRAY_ENTRIES:
                return (_planes_option(config, domain),
                        f'a {"background " if domain != "ball" else ""}plane level of '
                        f'resolution {r} has a plane of {n:,} entries (--grid-channels '
                        f'{s.grid_channels}), {array}')
    for domain in ('ball', 'inverted_sphere'):
        for n in sparse_level_entries(config, domain, s.sparse_entries, s.grid_channels):
            if n > MAX_ARRAY_ENTRIES:
                return 'sparse_entries', f'a sparse level of {n:,} entries is {array}'
    for cells in occupancy_cells(config, s.occupancy_res):
        if cells > MAX_ARRAY_ENTRIES:
            return 'occupancy_res', f'a grid of {cells:,} cells is {array}'
    if s.batch_rays * spr > MAX_ARRAY_ENTRIES:
        return 'batch_rays', (f'{s.batch_rays:,} rays x {spr} samples per ray are '
                              f'{s.batch_rays * spr:,} field samples per step, {array}')
    if s.color_units(config):
        # The colour MLP in a training step: a (width, samples) tensor per layer, and its
        # weights (width x width between hidden layers).
        rows = s.color_width * s.batch_rays * spr
        weights = s.color_width * s.color_width if s.color_layers > 1 else 0
        if max(rows, weights) > MAX_ARRAY_ENTRIES:
            return 'color_width', (f'a colour MLP of width {s.color_width:,} holds arrays of '
                                   f'{max(rows, weights):,} entries (its width x the '
                                   f'{s.batch_rays * spr:,} field samples of a step), {array}')
    need = _bytes(_entries(config, s), machine.threads, s.color_units(config))
    if sum(need.values()) <= budget:
        return None
    what = (f'a run takes about {memory_text(sum(need.values()))} (process '
            f'{memory_text(need["process"])}, grids and MLPs {memory_text(need["grids"])}, occupancy '
            f'{memory_text(need["occupancy"])}, training step {memory_text(need["step"])}), '
            f'more than this machine\'s {memory_text(budget)}')
    grown = {k: v for k, v in need.items() if k != 'process'}
    heaviest = max(grown, key=grown.get)
    if heaviest == 'step' and s.color_units(config) > MEASURED_COLOR_UNITS * s.color_layers:
        return 'color_width', what
    if heaviest == 'grids':
        if s.grid_channels > default_channels:
            return 'grid_channels', what
        parts = _grid_parts(config, s)
        parts['color_width'] = s.color_parameters(config)
        return max(parts, key=parts.get), what
    if heaviest == 'occupancy':
        return 'occupancy_res', what
    default_batch = type(config.schedule)().batch_rays
    return ('batch_rays' if s.batch_rays > default_batch else 'samples'), what


def largest_that_fits(config, option: str, machine: Machine) -> int:
    """The largest value of ``option`` (``batch_rays``, ``samples`` - samples per ray -,
    ``grid_levels`` / ``bg_grid_levels`` - the finest level's resolution, the others kept -,
    ``grid_channels``, ``color_width``, ``occupancy_res``) with which the config fits on ``machine``; 0 when
    none does."""
    m = config.model
    if option in ('grid_levels', 'bg_grid_levels', 'grid_planes', 'bg_grid_planes'):
        levels = list(getattr(m, option))
        i = levels.index(max(levels))
        values = lambda r: {option: tuple(levels[:i] + [r] + levels[i + 1:])}  # noqa: E731
        high = levels[i]
    else:
        key = {'samples': 'samples_per_ray'}.get(option, option)
        values = lambda v: {key: v}  # noqa: E731
        high = {'batch_rays': config.schedule.batch_rays, 'samples': config.samples_per_ray,
                'grid_channels': m.grid_channels, 'color_width': m.color_width,
                'occupancy_res': config.sampling.occupancy_res,
                'sparse_entries': config.schedule.sparse_entries}[option]
    low = {'grid_levels': 2, 'bg_grid_levels': 2, 'grid_planes': 2, 'bg_grid_planes': 2,
           'grid_channels': 2, 'occupancy_res': 4}.get(option, 1)

    def ok(value):
        return _exceeded(config, machine, **values(value)) is None

    if not ok(low):
        return 0
    while ok(high):                                  # fits: look above
        if high >= MAX_ARRAY_ENTRIES:
            return high
        low, high = high, min(2 * high, MAX_ARRAY_ENTRIES)
    while low < high:                                # the largest value that fits, by bisection
        mid = (low + high + 1) // 2
        low, high = (mid, high) if ok(mid) else (low, mid - 1)
    return low


@dataclass(frozen=True)
class Plan:
    """What a training run takes on a machine (:func:`plan`).

    ``entries``: the run's ``grids`` (parameters), ``occupancy`` cells and field ``samples``
    per step; ``bytes``: what the ``process``, the ``grids`` (with gradients, moments and the
    threads' gradient copies), the ``occupancy`` grids and a training ``step`` take;
    ``exceeded``: ``(option, what)`` of the first limit the options exceed, or None, and
    ``largest``: the largest value of that option that fits; ``images``: the bytes left for
    the images (:data:`USABLE_FRACTION` of the memory available, less ``total``)."""
    machine: Machine
    entries: dict
    bytes: dict
    exceeded: tuple | None = None
    largest: int | None = None
    chunk_error: str | None = field(default=None, repr=False)

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


def plan(config, machine: Machine | None = None) -> Plan:
    """Size a training run of ``config`` (a :class:`~mi_nerfpp.training.config.TrainConfig`)
    on ``machine`` (default: :meth:`Machine.here`), once: see :class:`Plan`. Raise with
    :func:`check` to refuse options that do not fit."""
    machine = machine or Machine.here()
    s = Sizes.of(config)
    entries = _entries(config, s)
    chunk_error = None
    try:
        check_chunk_sizes(RENDER_CHUNK_RAYS, config.render_sampling, 1, 1)
    except ValueError:
        sampling, r = config.sampling, config.render_sampling
        per_volume = max(r.fg_samples, r.bg_samples) + r.fine_samples
        chunk_error = (
            f'--samples {sampling.fg_samples} {sampling.bg_samples} {sampling.fine_samples} '
            f'are too many: renders of the model take {per_volume:,} samples per ray of a '
            f'volume (coarse and fine) for {RENDER_CHUNK_RAYS:,} rays at a time, more than the '
            f'nerfpp integrator\'s {MAX_CHUNK_ENTRIES:,} entries per array; at most '
            f'{MAX_CHUNK_ENTRIES // RENDER_CHUNK_RAYS:,} samples per ray of a volume fit')
    exceeded = _exceeded(config, machine)
    best = None if exceeded is None else largest_that_fits(config, exceeded[0], machine)
    return Plan(machine, entries, _bytes(entries, machine.threads, s.color_units(config)),
                exceeded, best, chunk_error)


def check(config, run_plan: Plan):
    """Refuse, before any work, a ``run_plan`` whose options Dr.Jit's arrays cannot hold or
    that do not fit in memory: a ValueError naming the option and the largest value that
    fits. Renders the integrator would refuse come first (a run must not train and then fail
    to evaluate)."""
    if run_plan.chunk_error:
        raise ValueError(run_plan.chunk_error)
    if run_plan.exceeded is None:
        return
    option, what = run_plan.exceeded
    best = run_plan.largest
    if option == 'samples':
        s = config.sampling
        raise ValueError(f'--samples {s.fg_samples} {s.bg_samples} {s.fine_samples} are too '
                         f'many: {what}; at most {best:,} samples per ray (coarse and fine, '
                         f'every volume) fit with --batch-rays {config.schedule.batch_rays}')
    shown = getattr(config.sampling if option == 'occupancy_res' else
                    config.schedule if option in ('batch_rays', 'sparse_entries')
                    else config.model, option)
    shown = ' '.join(map(str, shown)) if isinstance(shown, tuple) else shown
    largest_text = (f'the finest level fits at resolution {best:,} at most'
                    if option.endswith(('grid_levels', 'grid_planes'))
                    else f'at most {best:,} fits')
    if best == 0:
        largest_text = 'not even the smallest value fits: lower the other options'
    raise ValueError(f'{config.flag(option)} {shown} is too large: {what}; {largest_text}')


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
