"""Feature-grid levels: the three kinds of level a grid field sums (dense, plane, sparse).

Each kind is one class behind one small interface (:class:`Levels`): its learnable arrays in
``params`` (name -> ``TensorXf``), ``len()`` levels at ``resolutions``, the width of a cell of
each (:meth:`Levels.cell_size`), and :meth:`Levels.lookup`, which gives, for grid coordinates
in ``[0, 1]`` (:func:`~mi_nerfpp.core.geometry.grid_coordinates`), one list of ``channels``
Floats per level: channel 0 adds to the density logit, the others are features.
:class:`~mi_nerfpp.core.fields.GridField` composes them with its colour network.

* :class:`DenseLevels` — a ``Texture3f`` per level (``R³`` in the ball; ``2R x R x s_ratio·R``
  over longitude, colatitude and ``s`` in the background), trilinear, starting as noise.
* :class:`PlaneLevels` — per level three ``Texture2f`` planes over coordinate pairs, summed (a
  factorized level, as K-Planes': ``3R²`` entries instead of ``R³``), starting at zero.
* :class:`SparseLevels` — per level a :class:`~mi_nerfpp.core.bricks.BrickGrid`: fine texels only
  in allocated bricks, starting with none.

Dense and plane levels index the ball through its warp (``warped``); sparse levels index the
domain itself. Parameter names are ``grid<i>``, ``plane<i><axes>`` and ``sparse<i>``, as stored
in checkpoints.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_nerfpp.core.bricks import BrickGrid

# Channels per level unless told: the density logit and three features.
CHANNELS = 4
# Cells along the background's s per cell of colatitude unless told (dense levels; the sparse
# levels follow the dense ones, :func:`sparse_s`).
S_RATIO = 0.5

# The coordinate pairs of a plane level: (first, second) texture axes, by index into
# :func:`~mi_nerfpp.core.geometry.grid_coordinates`.
PLANE_AXES = {'xy': (0, 1), 'xz': (0, 2), 'yz': (1, 2)}


def level_weight(width, cell):
    """The weight of a grid level of cells ``cell`` wide for a footprint ``width`` wide:
    ``clip(2 − width/cell, 0, 1)`` — 1 while a cell spans the footprint, falling linearly to 0
    at two cells, beyond which the level's detail is finer than the footprint resolves."""
    return dr.clip(2.0 - width * (1.0 / cell), 0.0, 1.0)


def plane_shapes(domain, r):
    """``[(axes, (H, W))]`` of the three planes of a plane level at resolution ``r``: ``r x r``
    in the ball; in the inverted sphere (longitude, colatitude) ``r x 2r``, (longitude, s)
    ``r/2 x 2r`` and (colatitude, s) ``r/2 x r`` (as a dense level of ``s_ratio`` 0.5)."""
    if domain == 'ball':
        return [(a, (r, r)) for a in PLANE_AXES]
    n = {0: 2 * r, 1: r, 2: max(r // 2, 4)}       # cells along longitude, colatitude, s
    return [(a, (n[j], n[i])) for a, (i, j) in PLANE_AXES.items()]


def sparse_shape(domain, r, blocks, s=None):
    """Texels (Z, Y, X) of a sparse level at resolution ``r`` cut into ``blocks`` bricks per
    axis: ``r³`` in the ball; in the inverted sphere ``2r`` along longitude, ``r`` along
    colatitude and ``s`` (by default one texel per brick) along ``s``: fine angles, depth from
    the occupied bricks."""
    if domain == 'ball':
        return (r, r, r)
    return (s or blocks[0], r, 2 * r)


def sparse_s(resolutions, s_ratio, blocks):
    """Texels along ``s`` of the inverted sphere's sparse levels of ``resolutions`` over
    ``blocks`` bricks: as many as a dense level of the finest resolution and ``s_ratio`` has
    (:meth:`DenseLevels.shape`), a whole number per brick."""
    cells = max(int(max(resolutions) * float(s_ratio)), 4)
    return max(round(cells / blocks[0]), 1) * int(blocks[0])


def _inside(c, cells):
    """Coordinate ``c`` kept half a cell inside ``[0, 1]`` (off the wrap of a periodic
    texture, for the axes that are not periodic)."""
    return dr.clip(c, 0.5 / cells, 1.0 - 0.5 / cells)


class Levels:
    """Grid levels of one kind over a field's ``domain`` (``'ball'`` or ``'inverted_sphere'``)
    at ``resolutions``, each of ``channels`` channels."""

    kind = None
    warped = True       # indexes the ball through the field's warp

    def __init__(self, domain, resolutions=(), channels=CHANNELS):
        self.domain = domain
        self.resolutions = [int(r) for r in resolutions]
        self.channels = int(channels)
        if self.channels < 2:
            raise ValueError('GridField needs channels >= 2 (density + features)')
        self.params = {}
        self.wrap = dr.WrapMode.Repeat if domain == 'inverted_sphere' else dr.WrapMode.Clamp

    def __len__(self):
        return len(self.resolutions)

    @property
    def features(self) -> int:
        """Feature channels these levels add to the field's feature vector."""
        return len(self) * (self.channels - 1)

    @property
    def config(self) -> dict:
        """Their entries of the field's stored config."""
        raise NotImplementedError

    def cell_size(self, level) -> float:
        """The width of a cell of ``level`` in the units of :meth:`Volume.footprint_at
        <mi_nerfpp.core.render.Volume.footprint_at>`: ``2/R`` of the (warped) ball, ``π/R``
        radians of the background's colatitude (and of its longitude at the equator)."""
        r = self.resolutions[level]
        return 2.0 / r if self.domain == 'ball' else dr.pi / r

    def bind(self):
        """Point whatever reads the parameters (textures) at the current ``params``."""

    def level(self, i, coords) -> list:
        """The ``channels`` Floats of level ``i`` at grid coordinates ``coords``."""
        raise NotImplementedError

    def lookup(self, coords, width=None) -> list[list]:
        """Each level's channels at grid coordinates ``coords`` (three Floats in ``[0, 1]``),
        weighted by :func:`level_weight` of the footprint ``width`` (None: points)."""
        out = []
        for i in range(len(self)):
            g = self.level(i, coords)
            if width is not None:
                w = level_weight(width, self.cell_size(i))
                g = [w * v for v in g]
            out.append(g)
        return out


class DenseLevels(Levels):
    """Dense levels: level ``R`` a ``Texture3f`` of ``R³`` cells over ``[-1, 1]³`` (the warped
    ball), or over (longitude, colatitude, s) of ``2R × R × max(s_ratio·R, 4)`` cells, periodic
    in longitude. Distant content needs angular resolution more than resolution in ``s``: a
    small ``s_ratio`` buys finer angles for the same number of parameters; it is one number or
    one per level. They start as normal noise of standard deviation ``init``, drawn from
    ``rng`` (whatever ``init``, so that what is drawn after them starts the same)."""

    kind = 'dense'

    def __init__(self, domain, resolutions=(32, 128), channels=CHANNELS, s_ratio=S_RATIO,
                 init=0.1, rng=None):
        super().__init__(domain, resolutions, channels)
        ratios = [s_ratio] * len(self) if isinstance(s_ratio, (int, float)) else list(s_ratio)
        if len(ratios) != len(self) or not all(0 < float(q) <= 1 for q in ratios):
            raise ValueError(f'GridField s_ratio must be a number in (0, 1] or one per level '
                             f'({len(self)}), got {s_ratio}')
        self.s_ratio = float(s_ratio) if isinstance(s_ratio, (int, float)) \
            else [float(q) for q in ratios]
        self.s_ratios = [float(q) for q in ratios]
        self.init = float(init)
        if not self.init >= 0:
            raise ValueError(f'GridField init must be a standard deviation >= 0, got {init}')
        rng = dr.rng(seed=0) if rng is None else rng
        self.textures = []
        for i in range(len(self)):
            shape = self.shape(i) + (self.channels,)
            noise = rng.normal(mi.Float, int(np.prod(shape)))
            self.params[f'grid{i}'] = mi.TensorXf(noise * self.init, shape)
            self.textures.append(mi.Texture3f(self.params[f'grid{i}'], use_accel=False,
                                              wrap_mode=self.wrap))

    def shape(self, level):
        """Cells (Z, Y, X) of ``level``: texture axes (x, y, z) are the grid coordinates."""
        r = self.resolutions[level]
        if self.domain == 'ball':
            return (r, r, r)
        return (max(int(r * self.s_ratios[level]), 4), r, 2 * r)

    @property
    def config(self):
        return dict(resolutions=self.resolutions, s_ratio=self.s_ratio, init=self.init)

    def bind(self):
        for i, tex in enumerate(self.textures):
            tex.set_tensor(self.params[f'grid{i}'])

    def level(self, i, coords):
        tex = self.textures[i]
        tex.set_tensor(self.params[f'grid{i}'])
        c = coords
        if self.domain == 'inverted_sphere':
            Z, Y, _ = self.shape(i)
            c = [coords[0], _inside(coords[1], Y), _inside(coords[2], Z)]
        return list(tex.eval(mi.Point3f(*c)))


class PlaneLevels(Levels):
    """Plane levels: level ``R`` three ``Texture2f`` planes over the coordinate pairs (x, y),
    (x, z), (y, z) (:func:`plane_shapes`), whose bilinear lookups are summed, so that density is
    their product. ``3R²`` entries instead of ``R³``: a step's cost grows with the entries (the
    Adam update and the gradient buffers), not with the resolution. They start at zero: a cell
    no sample reaches adds nothing, and the dense levels alone describe what training did not
    see."""

    kind = 'plane'

    def __init__(self, domain, resolutions=(), channels=CHANNELS):
        super().__init__(domain, resolutions, channels)
        if any(r < 2 for r in self.resolutions):
            raise ValueError(f'GridField planes must be resolutions of at least 2, '
                             f'got {tuple(resolutions)}')
        self.textures = {}          # parameter name -> Texture2f
        for i, r in enumerate(self.resolutions):
            for axes, shape in plane_shapes(domain, r):
                key = f'plane{i}{axes}'
                self.params[key] = mi.TensorXf(dr.zeros(mi.Float, shape[0] * shape[1]
                                                        * self.channels), shape + (self.channels,))
                self.textures[key] = mi.Texture2f(self.params[key], use_accel=False,
                                                  wrap_mode=self.wrap)

    @property
    def config(self):
        return dict(planes=self.resolutions)

    def bind(self):
        for key, tex in self.textures.items():
            tex.set_tensor(self.params[key])

    def level(self, i, coords):
        g = None
        for axes, shape in plane_shapes(self.domain, self.resolutions[i]):
            key = f'plane{i}{axes}'
            tex = self.textures[key]
            tex.set_tensor(self.params[key])
            a, b = PLANE_AXES[axes]
            c = [coords[a], coords[b]]
            if self.domain == 'inverted_sphere':
                # Periodic in longitude only (axis 0): keep colatitude and s off the wrap.
                c = [c[k] if (a, b)[k] == 0 else _inside(c[k], shape[1 - k]) for k in (0, 1)]
            v = list(tex.eval(mi.Point2f(*c)))
            g = v if g is None else [p + q for p, q in zip(g, v)]
        return g


class SparseLevels(Levels):
    """Sparse levels (:class:`~mi_nerfpp.core.bricks.BrickGrid`): fine texels (``R³`` in the
    ball; ``2R x R`` in angle and ``s`` (by default one texel per brick) along ``s`` in the
    background) stored only in allocated bricks, one brick per cell of a ``blocks`` grid (the
    occupancy grid's cells, Z, Y, X). They index the domain unwarped, start with no brick
    (adding nothing) and take bricks from :meth:`allocate`, which training calls where the
    occupancy grid finds surfaces."""

    kind = 'sparse'
    warped = False

    def __init__(self, domain, resolutions=(), channels=CHANNELS, blocks=None, s=None,
                 init=0.0, seed=0):
        super().__init__(domain, resolutions, channels)
        self.blocks = None if blocks is None else [int(b) for b in blocks]
        self.s = None if s is None else int(s)
        self.init = float(init)
        self._noise = np.random.default_rng(seed)    # new bricks' starting texels
        self.bricks = []
        if len(self) and (self.blocks is None or len(self.blocks) != 3):
            raise ValueError('GridField sparse levels need sparse_blocks, the bricks per '
                             'axis (Z, Y, X)')
        for i in range(len(self)):
            grid = BrickGrid(self.shape(i), self.blocks, self.channels,
                             periodic=domain == 'inverted_sphere')
            self.bricks.append(grid)
            self.params[f'sparse{i}'] = mi.TensorXf(np.zeros(grid.pool_shape(), np.float32))

    def shape(self, level):
        """Texels (Z, Y, X) of ``level`` (:func:`sparse_shape`)."""
        return sparse_shape(self.domain, self.resolutions[level], self.blocks, self.s)

    @property
    def config(self):
        if not len(self):          # (so that files without sparse levels stay as they were)
            return {}
        return dict(sparse=self.resolutions, sparse_blocks=self.blocks, sparse_s=self.s)

    def allocated(self) -> dict:
        """The allocated bricks of each level: ``{'sparse<i>': flat brick indices}``."""
        return {f'sparse{i}': g.allocated for i, g in enumerate(self.bricks)}

    def allocate(self, values: dict, start: bool = False):
        """Allocate the bricks of levels (``{'sparse<i>': flat brick indices}``): the texels
        of bricks kept stay, the others are let go, new bricks start at zero (a level added
        to what the dense levels learned adds nothing until trained) or, with ``start`` (the
        level allocated at the run's first step, in place of a dense level), as a dense level
        does: normal noise of standard deviation ``init``. The parameter changes shape (an
        optimiser must take it anew)."""
        for key, chosen in values.items():
            i = int(key[len('sparse'):]) if key[len('sparse'):].isdigit() \
                and key.startswith('sparse') else -1
            if not 0 <= i < len(self.bricks):
                raise KeyError(f"field 'grid' has no sparse level '{key}'")
            grid = self.bricks[i]
            fill = None
            if start and self.init > 0:
                fill = self._noise.normal(0.0, self.init, grid.pool_shape(len(chosen)))
            pool = grid.moved(self.params[key].numpy(), chosen, fill)
            grid.allocate(chosen)
            self.params[key] = mi.TensorXf(pool)

    def level(self, i, coords):
        grid = self.bricks[i]
        c = coords
        if self.domain == 'inverted_sphere':
            Z, Y, _ = grid.shape
            c = [coords[0], _inside(coords[1], Y), _inside(coords[2], Z)]
        return grid.lookup(self.params[f'sparse{i}'].array, c)
