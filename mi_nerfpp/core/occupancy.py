"""Empty-space skipping: an occupancy grid per volume and the sample coordinate it induces.

An :class:`OccupancyGrid` covers the domain of one volume's field with coarse cells
(the unit ball: ``R³`` cells over ``[-1, 1]³``; the inverted sphere: longitude ×
colatitude × ``s`` cells, ``R × R/2 × R/4``) and holds, per cell, a running maximum
of the field's density at jittered points in the cell (instant-ngp's density
grid: ``d ← max(decay·d, σ(x))``, refreshed every few training steps). A cell is
*occupied* when its density exceeds ``threshold``.

:class:`OccupiedVolume` wraps a volume of :mod:`.render` and replaces its ray
parameter ``v`` by ``u ∈ [0, 1]``, the fraction of the ray's *occupied length*
before the point: ``K`` bins of equal length along ``[lo, hi]`` are looked up in
the grid, an empty bin counts ``EMPTY_WEIGHT`` of its length, and ``u`` is the
normalized cumulative sum. Stratified and hierarchical samples drawn uniformly in
``u`` therefore land in occupied space, and the quadrature interval of a sample,
``Δu·L_occ``, is the occupied length it stands for: empty space contributes
(almost) nothing, whatever the field holds there. That is the convention of
instant-ngp and nerfacc (density in empty cells is zero), expressed in the fixed
sample layout that the rest of :mod:`.render` uses, so training and the
integrator share one sampler.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_nerfpp.core.arrays import owned
from mi_nerfpp.core.geometry import grid_coordinates

# Weight of an empty bin's length in the occupied-length coordinate: small enough
# that empty space absorbs nothing visible, non-zero so that a ray through empty
# space alone still has a well-defined, monotonic coordinate.
EMPTY_WEIGHT = 1e-3
DEFAULT_RESOLUTION = 64
# Density (per unit of the volume's parameter) below which a cell is empty. Surfaces on the
# 128³ foreground grid need σ ≫ 10; haze that a compositor would see as a veil sits below
# 0.5. Measured on the default capture (1,500 steps): 0.01 pruned nothing, 0.3 left 4.5 % of
# the foreground cells at unchanged PSNR, 1.0 cut into surfaces (-1.8 dB).
DEFAULT_THRESHOLD = 0.3
DEFAULT_DECAY = 0.95
DEFAULT_EVERY = 16           # training steps between refreshes
DEFAULT_BINS = {'ball': 128, 'inverted_sphere': 64}
# Density a new grid starts with: every cell occupied until the first update from the field.
INITIAL_DENSITY = 1e4
# Jittered points per cell at which :meth:`OccupancyGrid.sampled` takes the field's density.
ALLOCATION_POINTS = 4


def grid_shape(domain, resolution):
    """Cells (Z, Y, X) of an occupancy grid of ``resolution`` over ``domain``'s field inputs: the
    last axis varies fastest in the flat index."""
    r = int(resolution)
    return (r, r, r) if domain == 'ball' else (max(r // 4, 4), max(r // 2, 4), r)


def cell_index(domain, shape, x):
    """Flat index of the cell of field inputs ``x`` (list of Floats) in a grid of ``shape``
    cells (Z, Y, X) over ``domain``, clamped to the grid: an occupancy cell, or a sparse
    level's brick (one per occupancy cell)."""
    Z, Y, X = shape
    idx = [mi.UInt32(dr.clip(mi.Int32(dr.floor(c * n)), 0, n - 1))
           for c, n in zip(grid_coordinates(domain, x), (X, Y, Z))]
    return (idx[2] * Y + idx[1]) * X + idx[0]


class OccupancyGrid:
    """Occupied cells of one volume's domain (see module docs)."""

    def __init__(self, domain, resolution=DEFAULT_RESOLUTION, threshold=DEFAULT_THRESHOLD,
                 density=None):
        if domain not in ('ball', 'inverted_sphere'):
            raise ValueError(f"unknown occupancy domain '{domain}'")
        if resolution < 4:
            raise ValueError(f'occupancy resolution must be >= 4, got {resolution}')
        self.domain, self.resolution, self.threshold = domain, int(resolution), float(threshold)
        self.shape = grid_shape(domain, self.resolution)
        n = int(np.prod(self.shape))
        # A new grid takes the field's density at its first update (no running maximum).
        self.fresh = density is None
        if density is None:
            self.density = dr.full(mi.Float, INITIAL_DENSITY, n)
        else:
            density = np.asarray(density, dtype=np.float32).ravel()
            if density.size != n:
                raise ValueError(f'occupancy grid of {self.shape} needs {n} values, got {density.size}')
            self.density = owned(density, mi.Float)    # a training step may release it

    @property
    def config(self):
        return {'domain': self.domain, 'resolution': self.resolution, 'threshold': self.threshold}

    def cell(self, x):
        """Flat cell index of field inputs ``x`` (list of Floats), clamped to the grid."""
        return cell_index(self.domain, self.shape, x)

    def occupied(self, x):
        """Whether the cells of ``x`` are occupied (Bool per point)."""
        return dr.gather(mi.Float, self.density, self.cell(x)) > self.threshold

    def fraction(self):
        """Fraction of occupied cells."""
        return float(dr.mean(mi.Float(self.density > self.threshold)).array[0])

    def cell_points(self, xi):
        """Field inputs of one point per cell, at fraction ``xi`` (Point3f of [0,1]³) within it."""
        Z, Y, X = self.shape
        i = dr.arange(mi.UInt32, X * Y * Z)
        cx, cy, cz = i % X, (i // X) % Y, i // (X * Y)
        c = [(mi.Float(cx) + xi.x) / X, (mi.Float(cy) + xi.y) / Y, (mi.Float(cz) + xi.z) / Z]
        if self.domain == 'ball':
            return [dr.fma(v, 2.0, -1.0) for v in c]
        lon = (c[0] - 0.5) * (2.0 * dr.pi)
        sin_t, cos_t = dr.sincos(c[1] * dr.pi)
        sin_p, cos_p = dr.sincos(lon)
        return [sin_t * cos_p, sin_t * sin_p, cos_t, c[2]]

    def _density_at_jittered(self, field, seed):
        """The field's density at one point per cell, jittered by ``seed`` (detached)."""
        n = dr.width(self.density)
        # An opaque seed: as a literal, each refresh's new seed compiled the kernel anew
        # (~100 ms against ~6 ms per refresh, every 16 training steps).
        rng = mi.PCG32(size=n, initstate=dr.opaque(mi.UInt64, seed))
        xi = mi.Point3f(rng.next_float32(), rng.next_float32(), rng.next_float32())
        with dr.suspend_grad():
            return dr.detach(field.density(self.cell_points(xi)))

    def update(self, field, seed, decay=DEFAULT_DECAY):
        """``density ← max(decay·density, σ(x))`` at one jittered point per cell."""
        sigma = self._density_at_jittered(field, seed)
        self.density = sigma if self.fresh else dr.maximum(self.density * decay, sigma)
        self.fresh = False
        dr.eval(self.density)

    def sampled(self, field, seed, points=ALLOCATION_POINTS):
        """The field's density now, as NumPy over the cells: the largest at ``points``
        jittered points per cell, without the running maximum's memory of densities that
        training has since carved away (what sparse levels allocate their bricks from)."""
        out = None
        for k in range(int(points)):
            sigma = self._density_at_jittered(field, seed * points + k)
            out = sigma if out is None else dr.maximum(out, sigma)
        return out.numpy().reshape(self.shape)

    def numpy(self):
        return self.density.numpy().reshape(self.shape)


class OccupiedVolume:
    """A volume of :mod:`.render` re-parametrized by occupied length (see module docs): its
    sample coordinate is ``u``, and ``inputs`` and ``distance`` take the wrapped volume's own
    parameter, ``parameter(ray, u)`` (the protocol of :class:`~.render.Volume`).

    A ray's ``K`` bins all have the same length, so its occupied-length coordinate is fixed by
    which bins are occupied: one bit per bin (``K/32`` words per ray, :func:`occupied_words`).
    The cumulative length before bin ``b`` is ``width·(n_b + ε·(b − n_b))`` with ``n_b`` the
    occupied bins before it (a population count), so sample placement reads a few words per
    ray instead of per-bin arrays."""

    def __init__(self, volume, grid, bins):
        self.base, self.bins = volume, int(bins)
        if self.bins % 32:
            raise ValueError(f'occupancy bins per ray must be a multiple of 32, got {bins}')
        self.infinite_last, self.open = volume.infinite_last, volume.open
        self.d, self.footprint, self.seed = volume.d, volume.footprint, volume.seed
        self.words = occupied_words(volume, grid, self.bins)
        # Occupied bins before each word (before[0] = 0).
        self.before = [dr.zeros(mi.UInt32, dr.width(volume.lo))]
        for word in self.words:
            self.before.append(self.before[-1] + dr.popcnt(word))
        occupied = self.before.pop()
        # Bin length; a segment of zero length keeps a finite (tiny) coordinate.
        self.width = dr.maximum((volume.hi - volume.lo) * (1.0 / self.bins), 1e-12)
        self.total = self.width * (mi.Float(occupied)
                                   + EMPTY_WEIGHT * mi.Float(self.bins - occupied))
        dr.eval(self.words, self.before[1:], self.width, self.total)
        n_rays = dr.width(volume.lo)
        self.lo = dr.zeros(mi.Float, n_rays)
        self.hi = dr.ones(mi.Float, n_rays)

    def parameter(self, ray, u):
        """The wrapped volume's parameter ``v`` at occupied-length fraction ``u``: the word of
        bins that holds it (from the occupied bins before each word), then a binary search in
        that word's 32 bins (renders compute it once per sample)."""
        K = self.bins
        width = dr.gather(mi.Float, self.width, ray)
        target = u * dr.gather(mi.Float, self.total, ray)

        def cdf(b, n):
            """Occupied length before bin ``b`` with ``n`` occupied bins before it."""
            return width * (mi.Float(n) + EMPTY_WEIGHT * mi.Float(b - n))

        # The last word whose first bin starts at or before the target (cdf is monotonic).
        q, word, n_q = mi.UInt32(0), dr.gather(mi.UInt32, self.words[0], ray), mi.UInt32(0)
        for w in range(1, len(self.words)):
            n_w = dr.gather(mi.UInt32, self.before[w], ray)
            past = cdf(32 * w, n_w) <= target
            q = dr.select(past, w, q)
            word = dr.select(past, dr.gather(mi.UInt32, self.words[w], ray), word)
            n_q = dr.select(past, n_w, n_q)

        def before(r):
            """Occupied bins before bin ``32q + r`` (0 <= r <= 32: the search probes 32)."""
            low = dr.select(r >= 32, word, word & ((mi.UInt32(1) << (r & 31)) - 1))
            return n_q + dr.popcnt(low)

        # The last bin of the word whose start lies at or before the target.
        r = dr.binary_search(1, 32, lambda r: cdf(32 * q + r, before(r)) <= target) - 1
        b = 32 * q + r
        mass = width * dr.select(((word >> r) & 1) == 1, 1.0, EMPTY_WEIGHT)
        frac = dr.clip((target - cdf(b, before(r))) / mass, 0.0, 1.0)
        lo = dr.gather(mi.Float, self.base.lo, ray)
        hi = dr.gather(mi.Float, self.base.hi, ray)
        return dr.fma((mi.Float(b) + frac) * (1.0 / K), hi - lo, lo)

    def inputs(self, ray, v):
        return self.base.inputs(ray, v)

    def delta_scale(self, ray):
        return dr.gather(mi.Float, self.total, ray) * self.base.delta_scale(ray)

    def distance(self, ray, v):
        return self.base.distance(ray, v)

    def footprint_at(self, ray, v):
        return self.base.footprint_at(ray, v)

    def normalized(self, ray, u):
        return u


def occupied_words(volume, grid, bins):
    """Which of ``bins`` equal bins along each ray of ``volume`` are occupied in ``grid`` (looked
    up at the bins' midpoints): ``bins/32`` UInt32 arrays, one bit per bin, bin ``k`` at bit
    ``k % 32`` of word ``k // 32``.

    One kernel: symbolic loops over the bins per ray (one per word), so the ``rays·bins``
    lookups (128 per foreground ray) never become arrays of their own (a wavefront of them wrote
    and summed ~0.5 GB per 1280x720 render)."""
    n_rays = dr.width(volume.lo)
    ray = dr.arange(mi.UInt32, n_rays)
    words = []
    with dr.suspend_grad():            # bits are constants of the ray parameters
        lo = dr.detach(volume.lo)
        step = (dr.detach(volume.hi) - lo) * (1.0 / bins)
        for first in range(0, bins, 32):          # one loop of 32 bins per word
            def body(r, word):
                mid = dr.fma(mi.Float(r + first) + 0.5, step, lo)
                bit = dr.select(grid.occupied(volume.inputs(ray, mid)), mi.UInt32(1) << r, 0)
                return r + 1, word | bit

            _, word = dr.while_loop(
                # (An opaque zero: with a literal one, a grid without occupied cells leaves the
                # word literal through the first recording and the loop refuses the second.)
                (dr.zeros(mi.UInt32, n_rays), dr.opaque(mi.UInt32, 0, n_rays)),
                lambda r, word: r < 32, body, labels=('r', 'word'), label='occupied_words')
            words.append(word)
    return list(words)
