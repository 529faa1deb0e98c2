"""Radiance fields: density σ(x) and colour c(x, d) of one volume.

Two domains (the two volumes of the paper's §4):

* ``'ball'`` — the foreground, points ``p`` inside the unit sphere (3 inputs);
* ``'inverted_sphere'`` — the background, ``(x̂, s)`` with ``x̂`` on the unit
  sphere and ``s = 1/r ∈ (0, 1]`` (4 inputs, 3 degrees of freedom).

Three field kinds, chosen per volume by the ``field`` XML parameter:

* :class:`GridField` (``'grid'``, the default) — a multi-resolution dense feature
  grid (Dr.Jit ``Texture3f`` levels, trilinear) plus a small MLP. Density comes
  from position features alone; colour from the features and the encoded view
  direction, injected late (the structure of the paper's Figure 3). The
  background grid is indexed by the spherical angles of ``x̂`` and ``s``.
* :class:`MLPField` with ``structure='nerf'`` (``'nerf'``) — the paper's NeRF-MLP:
  ``γ^10(x)`` through a trunk to σ and a feature vector, ``γ^4(d)`` injected
  at the colour head.
* :class:`MLPField` with ``structure='vanilla'`` (``'vanilla'``) — the paper's §3
  control: σ from the same trunk over ``γ^10(x)``, colour from a separate MLP that
  takes ``γ^10(x)`` and ``γ^10(d)`` together at its input.

MLPs are ``drjit.nn`` networks: tensor mode while training, packed
cooperative vectors while rendering on the CPU, tensor mode on CUDA (see :class:`_Net`).

Every field keeps its learnable arrays in ``self.params`` (name -> ``TensorXf``);
that dict is the single source of truth that the integrator exposes through
``traverse`` and the optimizer updates.
"""
from __future__ import annotations

import os

import drjit as dr
import drjit.nn as nn
import mitsuba as mi
import numpy as np

from mi_nerfpp.core.arrays import llvm_backend
from mi_nerfpp.core.bricks import BrickGrid
from mi_nerfpp.core.geometry import ball_warp, grid_coordinates

DOMAINS = {'ball': 3, 'inverted_sphere': 4}
# How a grid field colours a ray: 'deferred' (features composited, one MLP per ray) or
# 'sample' (an MLP per sample, as the paper's fields and models trained before deferred colour).
COLOR_MODES = ('deferred', 'sample')
# How training colours the background volume unless told (``--bg-color``); the foreground takes
# the grid field's own default (deferred). After 10 minutes, time-matched on the default capture
# (seeds 0-2) and gt_plaza (seeds 0-1), per-sample colour in the background scored 0.2-0.5 dB
# above deferred colour in four runs of five (0.1 dB below in the fifth), with 25 % fewer
# steps (CHANGELOG.md, 2026-11-26).
BACKGROUND_COLOR = 'sample'
# Whether a network that is not being differentiated runs as a packed cooperative-vector network
# fused into the kernel that renders (True) or in tensor mode (False), by backend: packed on the
# CPU (LLVM), about 8x faster there (:class:`_Net`); tensor mode on CUDA, where ``drjit.nn``'s
# cooperative vectors inside a Mitsuba plugin are reported to crash with an OptiX illegal memory
# access (mitsuba3 issue 1825). ``MI_NERFPP_PACKED=1`` (or ``0``) chooses packed (or tensor
# mode) on any backend, to try the other way.
PACKED_ENV = 'MI_NERFPP_PACKED'


def _packed_default() -> bool:
    value = os.environ.get(PACKED_ENV, '').strip()
    return value == '1' if value in ('0', '1') else llvm_backend()


PACKED_INFERENCE = _packed_default()


# ----------------------------------------------------------------------------- helpers

def rows(values):
    """Stack 1-D Floats (or (k, N) tensors) into one ``TensorXf`` of shape (C, N)."""
    parts = []
    for v in values:
        if isinstance(v, mi.TensorXf):
            parts.append(v)
        else:
            parts.append(mi.TensorXf(v, (1, dr.width(v))))
    return dr.concat(parts, axis=0)


def unrows(t):
    """Inverse of :func:`rows`: a (C, N) tensor -> list of C Floats."""
    return [t[i].array for i in range(t.shape[0])]


def softplus(x):
    """``log(1 + e^x)`` without overflow (no NaN gradients for large ``x``)."""
    return dr.maximum(x, 0.0) + dr.log(1.0 + dr.exp(-dr.abs(x)))


def trunc_exp(x):
    """``exp(x)`` with its argument clamped to 11 (density up to ~6e4): large dynamic range
    from small parameter steps, as instant-ngp's density activation."""
    return dr.exp(dr.minimum(x, 11.0))


def sigmoid(x):
    return dr.rcp(1.0 + dr.exp(-x))


def positional_encoding(x, octaves):
    """The paper's ``γ^L``: ``[x, sin(2^k π x), cos(2^k π x)]_{k<L}`` of a list of Floats."""
    out = list(x)
    for k in range(octaves):
        for v in x:
            out += dr.sincos(v * (dr.pi * 2 ** k))
    return out


def mlp(widths, out):
    """``Linear -> ReLU`` for each width, then ``Linear(out)``."""
    layers = []
    for w in widths:
        layers += [nn.Linear(-1, w), nn.ReLU()]
    layers.append(nn.Linear(-1, out))
    return nn.Sequential(*layers)


ACTIVATIONS = {'exp': trunc_exp, 'softplus': softplus}


def level_weight(width, cell):
    """The weight of a grid level of cells ``cell`` wide for a footprint ``width`` wide:
    ``clip(2 − width/cell, 0, 1)`` — 1 while a cell spans the footprint, falling linearly to 0
    at two cells, beyond which the level's detail is finer than the footprint resolves."""
    return dr.clip(2.0 - width * (1.0 / cell), 0.0, 1.0)


# The coordinate pairs of a plane level of :class:`GridField`: (first, second) texture axes, by
# index into :func:`~mi_nerfpp.core.geometry.grid_coordinates`.
PLANE_AXES = {'xy': (0, 1), 'xz': (0, 2), 'yz': (1, 2)}


def plane_shapes(domain, r):
    """``[(axes, (H, W))]`` of the three planes of a plane level at resolution ``r``: ``r x r``
    in the ball; in the inverted sphere (longitude, colatitude) ``r x 2r``, (longitude, s)
    ``r/2 x 2r`` and (colatitude, s) ``r/2 x r`` (as a dense level of ``s_ratio`` 0.5)."""
    if domain == 'ball':
        return [(a, (r, r)) for a in PLANE_AXES]
    n = {0: 2 * r, 1: r, 2: max(r // 2, 4)}       # cells along longitude, colatitude, s
    return [(a, (n[j], n[i])) for a, (i, j) in PLANE_AXES.items()]


class Field:
    """Base class: config, parameters and the ``(x, d) -> (σ, rgb)`` interface."""

    kind = None

    def __init__(self, domain):
        if domain not in DOMAINS:
            raise ValueError(f"unknown field domain '{domain}' (expected one of {list(DOMAINS)})")
        self.domain = domain
        self.params = {}

    @property
    def config(self):
        raise NotImplementedError

    def __call__(self, x, d, ray, width=None):
        """Density and colour at sample points.

        ``x``: list of Floats, the domain's inputs per sample (``p`` for 'ball',
        ``(x̂, s)`` for 'inverted_sphere'); ``d``: unit view direction of each *ray*
        (Vector3f); ``ray``: the ray of each sample (UInt32 index into ``d``); ``width``: the
        pixel footprint of each sample in the domain's units
        (:meth:`mi_nerfpp.core.render.Volume.footprint_at`), or None for points (only a grid
        field with ``antialias`` uses it).
        Returns ``(sigma: Float >= 0, rgb: Color3f in [0, 1])`` per sample.
        """
        raise NotImplementedError

    def density(self, x, width=None):
        """Density σ alone at sample points ``x`` (the domain's inputs, list of Floats)."""
        raise NotImplementedError

    def set_parameters(self, values):
        """Replace parameters by name (arrays with matching shapes)."""
        for k, v in values.items():
            if k not in self.params:
                raise KeyError(f"field '{self.kind}' has no parameter '{k}' (has {sorted(self.params)})")
            if tuple(v.shape) != tuple(self.params[k].shape):
                raise ValueError(f"parameter '{k}': shape {tuple(v.shape)} does not match "
                                 f"the field's {tuple(self.params[k].shape)}")
            self.params[k] = mi.TensorXf(v)
        for i, tex in enumerate(getattr(self, 'textures', ())):
            # Let go of the previous tensors now (a frozen training step, which sets them on
            # lookup, would keep its recording's inputs alive otherwise).
            tex.set_tensor(self.params[f'grid{i}'])
        for key, tex in getattr(self, 'plane_textures', {}).items():
            tex.set_tensor(self.params[key])


class _Net:
    """A ``drjit.nn`` MLP whose weights live in a Field's params dict.

    Evaluated in tensor mode (a ``TensorXf`` of shape (features, samples)) when
    any weight is being differentiated — a training step measured 91 ms against
    229 ms with packed cooperative vectors — and as a packed cooperative-vector
    network fused into the rendering kernel otherwise (about 8x faster than
    tensor mode for inference on this CPU), unless :data:`PACKED_INFERENCE` is off
    (on CUDA): then in tensor mode too, detached.
    """

    def __init__(self, field, prefix, module, n_in, rng):
        self.field, self.prefix = field, prefix
        self.module = module.alloc(mi.TensorXf, n_in, rng=rng)
        for k in self.module.keys():
            field.params[f'{prefix}.{k}'] = mi.TensorXf(self.module[k])

    @property
    def differentiated(self):
        """Whether any of the weights is being differentiated (tensor mode)."""
        return any(dr.grad_enabled(self.field.params[f'{self.prefix}.{k}'])
                   for k in self.module.keys())

    def _bind(self):
        """The module's weights from the params dict (detached unless differentiated)."""
        differentiate = self.differentiated
        for k in self.module.keys():
            w = self.field.params[f'{self.prefix}.{k}']
            self.module[k] = w if differentiate else dr.detach(w)
        return differentiate

    def __call__(self, inputs):
        """List of input Floats -> list of output Floats."""
        if self._bind() or not PACKED_INFERENCE:
            return unrows(self.module(rows(inputs)))
        packed = nn.pack(self.module, layout='inference')
        return list(packed(nn.CoopVec(*inputs)))

    def tensor(self, t):
        """A (inputs, N) tensor -> the (outputs, N) tensor, in tensor mode."""
        self._bind()
        return self.module(t)


class _LateNet:
    """An MLP whose input is split into per-sample and per-ray parts.

    ``MLP([a, b]) = rest(A·a + (B·b + bias))``: the view direction ``b`` is the
    same for every sample of a ray, so its share of the first layer is computed
    once per ray and gathered. Equal to one MLP over the concatenated input,
    with a first layer of ``n_sample + n_ray`` inputs split into ``sample.*`` and
    ``ray.*`` parameters.
    """

    def __init__(self, field, prefix, n_sample, n_ray, widths, out, rng):
        first, rest = widths[0], list(widths[1:])
        self.sample = _Net(field, f'{prefix}.sample', nn.Sequential(nn.Linear(-1, first, bias=False)),
                           n_sample, rng)
        self.ray = _Net(field, f'{prefix}.ray', nn.Sequential(nn.Linear(-1, first)), n_ray, rng)
        layers = [nn.ReLU()]
        for w in rest:
            layers += [nn.Linear(-1, w), nn.ReLU()]
        self.rest = _Net(field, f'{prefix}.rest', nn.Sequential(*layers, nn.Linear(-1, out)),
                         first, rng)

    def __call__(self, sample_inputs, ray_inputs, ray=None):
        """``ray``: the ray of each sample (UInt32), or None when the sample inputs are per
        ray too (deferred colour)."""
        if ray is None:
            per_ray = self.ray(ray_inputs)
            return self.rest([a + b for a, b in zip(self.sample(sample_inputs), per_ray)])
        if any(net.differentiated for net in (self.sample, self.ray, self.rest)):
            return unrows(self.rest.tensor(self._first_layer(sample_inputs, ray_inputs, ray)))
        per_ray = self.ray(ray_inputs)
        # One kernel for all of them: a gather from an unevaluated array evaluates that array
        # alone, so each of the ``first`` outputs would otherwise be a kernel of its own.
        dr.eval(per_ray)
        h = [a + dr.gather(mi.Float, b, ray) for a, b in zip(self.sample(sample_inputs), per_ray)]
        return self.rest(h)

    def _first_layer(self, sample_inputs, ray_inputs, ray):
        """The first layer's (width, samples) tensor in tensor mode (training): ``A·a`` of each
        sample plus ``B·b + bias`` of its ray, gathered for all rows at once (row by row, the
        split into Floats and back cost kernels of their own, forward and backward)."""
        a = self.sample.tensor(rows(sample_inputs))
        b = self.ray.tensor(rows(ray_inputs))
        width, n, n_rays = a.shape[0], a.shape[1], b.shape[1]
        k = dr.arange(mi.UInt32, width * n)
        row = k // n
        index = row * n_rays + dr.gather(mi.UInt32, ray, k - row * n)
        return mi.TensorXf(a.array + dr.gather(mi.Float, b.array, index), (width, n))


# ----------------------------------------------------------------------------- grid + MLP

class GridField(Field):
    """Multi-resolution dense feature grid + small colour MLP.

    Each level is a ``Texture3f`` with ``channels`` channels. Channel 0 of all
    levels sums to the density logit: ``σ = exp(Σ_l g_l[0](x) + density_bias)``
    (``density_activation='exp'``, clamped; or ``'softplus'``). The exponential
    lets opaque surfaces (σ·δ ≫ 1) form in a few hundred Adam steps.
    The other channels are concatenated into a feature vector ``f(x)``; colour
    is ``sigmoid(MLP([f, γ^dir_octaves(d)]))`` with ``color_layers`` hidden
    layers of ``hidden`` units. With ``color='deferred'`` (the default) ``f`` is the
    feature vector composited along the ray (normalized by its opacity, see
    :func:`mi_nerfpp.core.render.composite_features`) and the MLP runs once per ray; with
    ``color='sample'`` (models trained before deferred colour) it runs at every sample on
    ``f(x)``, its first layer's direction share computed once per ray. The default — one
    layer of 32, ``γ^2`` — is the late-injection prior: the direction passes one
    non-linearity. Two octaves, not NeRF's four: with
    fewer view-dependent degrees of freedom the colour generalizes better to held-out views
    (measured on the default capture, README tuning table). ``color_layers=4, hidden=64,
    dir_octaves=10`` is the grid analogue of the paper's vanilla MLP (§3): grid
    features and ``γ^10(d)`` side by side at the input of a deep colour MLP.

    ``antialias``: a level whose cells are smaller than a sample's pixel footprint (its
    ``width``, :meth:`mi_nerfpp.core.render.Volume.footprint_at`) cannot be resolved at that
    width and would alias; its contribution (density logit and features) is weighted by
    ``clip(2 − width/cell, 0, 1)``: whole up to a footprint of one cell, gone from two cells on
    (:func:`level_weight`), so coarse levels alone describe what a wide footprint sees. A
    footprint within the finest cell, or none, is today's point lookup exactly. Fields built
    without it (and checkpoints from before it) look up points.

    ``planes``: plane levels (resolutions ``R``), a factorized level that holds fine cells in
    few entries: three ``Texture2f`` planes over the coordinate pairs (x, y), (x, z), (y, z) of
    the ball (``R x R`` each; in the background (longitude, colatitude) ``2R x R``, and
    longitude and colatitude against ``s`` with ``R/2`` cells along ``s``), whose bilinear
    lookups are summed into one more level's density logit and features (so density is their
    product, as K-Planes'). ``3R²`` entries instead of ``R³``: a step's cost grows with the
    entries (the Adam update and the gradient buffers), not with the resolution. They start
    at zero, so what no sample reaches adds nothing.

    ``sparse``: sparse levels (resolutions ``R``, :class:`~mi_nerfpp.core.bricks.BrickGrid`):
    fine texels (``R³`` in the ball; ``2R x R`` in angle and ``sparse_s`` along ``s`` in the
    background) stored only in allocated bricks, one brick per cell of a ``sparse_blocks``
    grid (the occupancy grid's cells). They index the domain unwarped, start with no brick
    (adding nothing) and take bricks from :meth:`set_bricks`, which training calls where the
    occupancy grid finds surfaces; their lookups are summed like the dense levels'.

    ``init``: the standard deviation of the normal noise the dense levels start with (the
    colour MLP starts the same whatever it is); 0 starts them neutral, so that a cell no sample
    reaches holds no colour of its own (after 10 minutes 0.1-0.2 dB lower than with noise on two
    captures; docs/experiments.md, 2026-11-26).

    Ball domain: level ``R`` is an ``R³`` grid over ``[-1, 1]³``, indexed by the point itself or,
    with ``warp_radius > 0``, by :func:`~mi_nerfpp.core.geometry.ball_warp` of it (finer cells in the
    centre, where a 360° capture's cameras look).
    Inverted-sphere domain: level ``R`` is a grid over (longitude, colatitude,
    s) of ``2R × R × max(s_ratio·R, 4)`` cells, periodic in longitude. Distant content
    needs angular resolution more than resolution in ``s``: a small ``s_ratio`` buys finer
    angles for the same number of parameters. ``s_ratio`` is one number or one per level
    (e.g. a fine angular level with only 4 cells along ``s`` over coarser levels resolved in
    depth: a factorization of angle and depth).
    """

    kind = 'grid'

    def __init__(self, domain, resolutions=(32, 128), channels=4, hidden=32, dir_octaves=2,
                 density_bias=-3.0, density_activation='exp', color_layers=1, s_ratio=0.5,
                 warp_radius=0.0, color='deferred', antialias=False, planes=(), init=0.1,
                 sparse=(), sparse_blocks=None, sparse_s=None, appearance_dims=0, seed=0):
        super().__init__(domain)
        self.appearance_dims = int(appearance_dims)
        if self.appearance_dims < 0:
            raise ValueError(f'GridField appearance_dims must be >= 0, got {appearance_dims}')
        # The appearance code of each ray (``appearance_dims`` Floats, one value per ray, or
        # one value for all of them), set by whoever renders (:meth:`mi_nerfpp.core.model.
        # NeRFPPModel.set_appearance`); None: the neutral code, zero.
        self.appearance_code = None
        self.init = float(init)
        if not self.init >= 0:
            raise ValueError(f'GridField init must be a standard deviation >= 0, got {init}')
        self.antialias = bool(antialias)
        if color not in COLOR_MODES:
            raise ValueError(f"GridField color must be one of {', '.join(COLOR_MODES)}, "
                             f"got {color!r}")
        self.color_mode = color
        self.warp_radius = float(warp_radius)
        if not 0 <= self.warp_radius < 1:
            raise ValueError(f'GridField warp_radius must be in [0, 1), got {warp_radius}')
        if channels < 2:
            raise ValueError('GridField needs channels >= 2 (density + features)')
        self.resolutions = [int(r) for r in resolutions]
        # One ratio for all levels, or one per level (fine angles with few cells along s).
        ratios = [s_ratio] * len(self.resolutions) if isinstance(s_ratio, (int, float)) \
            else list(s_ratio)
        if len(ratios) != len(self.resolutions) or not all(0 < float(q) <= 1 for q in ratios):
            raise ValueError(f'GridField s_ratio must be a number in (0, 1] or one per level '
                             f'({len(self.resolutions)}), got {s_ratio}')
        self.s_ratio = float(s_ratio) if isinstance(s_ratio, (int, float)) \
            else [float(q) for q in ratios]
        self.s_ratios = [float(q) for q in ratios]
        self.channels = int(channels)
        self.hidden = int(hidden)
        self.dir_octaves = int(dir_octaves)
        self.color_layers = int(color_layers)
        if self.color_layers < 1:
            raise ValueError('GridField needs color_layers >= 1')
        self.density_bias = float(density_bias)
        if density_activation not in ACTIVATIONS:
            raise ValueError(f"density_activation must be one of {sorted(ACTIVATIONS)}")
        self.density_activation = density_activation
        rng = dr.rng(seed=seed)
        wrap = dr.WrapMode.Repeat if domain == 'inverted_sphere' else dr.WrapMode.Clamp
        self.textures = []
        for i, r in enumerate(self.resolutions):
            shape = self._grid_shape(r, i) + (self.channels,)
            size = shape[0] * shape[1] * shape[2] * shape[3]
            noise = rng.normal(mi.Float, size)    # drawn at any init: the MLP's start is the same
            self.params[f'grid{i}'] = mi.TensorXf(noise * self.init, shape)
            self.textures.append(mi.Texture3f(self.params[f'grid{i}'], use_accel=False, wrap_mode=wrap))
        self.planes = [int(r) for r in planes]
        if any(r < 2 for r in self.planes):
            raise ValueError(f'GridField planes must be resolutions of at least 2, got {planes}')
        # Plane levels start at zero: a plane cell that no sample reaches adds nothing, so the
        # dense levels alone describe what training did not see.
        self.plane_textures = {}         # parameter name -> Texture2f
        for i, r in enumerate(self.planes):
            for axes, shape in plane_shapes(self.domain, r):
                key = f'plane{i}{axes}'
                self.params[key] = mi.TensorXf(dr.zeros(mi.Float, shape[0] * shape[1]
                                                        * self.channels), shape + (self.channels,))
                self.plane_textures[key] = mi.Texture2f(self.params[key], use_accel=False,
                                                        wrap_mode=wrap)
        self.sparse = [int(r) for r in sparse]
        self.sparse_blocks = None if sparse_blocks is None else [int(b) for b in sparse_blocks]
        self.sparse_s = None if sparse_s is None else int(sparse_s)
        # Sparse levels start with no brick allocated: they add nothing until the run allocates
        # bricks where the occupancy says the surfaces are (:meth:`set_bricks`).
        self.bricks = []
        if self.sparse:
            if self.sparse_blocks is None or len(self.sparse_blocks) != 3:
                raise ValueError('GridField sparse levels need sparse_blocks, the bricks per '
                                 'axis (Z, Y, X)')
            for i, r in enumerate(self.sparse):
                grid = BrickGrid(self._sparse_shape(r), self.sparse_blocks, self.channels,
                                 periodic=domain == 'inverted_sphere')
                self.bricks.append(grid)
                self.params[f'sparse{i}'] = mi.TensorXf(np.zeros(grid.pool_shape(), np.float32))
        n_feat = (len(self.resolutions) + len(self.planes) + len(self.sparse)) \
            * (self.channels - 1)
        n_dir = 3 * (1 + 2 * self.dir_octaves)
        self.color_net = _LateNet(self, 'color', n_feat, n_dir + self.appearance_dims,
                                  [self.hidden] * self.color_layers, 3, rng)

    def _grid_shape(self, r, level):
        """Tensor shape (Z, Y, X) of a level at resolution ``r``: texture axes are (x, y, z) =
        coordinates."""
        if self.domain == 'ball':
            return (r, r, r)
        return (max(int(r * self.s_ratios[level]), 4), r, 2 * r)

    def _sparse_shape(self, r):
        """Texel shape (Z, Y, X) of a sparse level at resolution ``r``: ``r³`` in the ball; in
        the inverted sphere ``2r`` along longitude, ``r`` along colatitude and ``sparse_s`` (by
        default one texel per brick) along ``s``: fine angles, depth from the occupied bricks."""
        if self.domain == 'ball':
            return (r, r, r)
        return (self.sparse_s or self.sparse_blocks[0], r, 2 * r)

    @property
    def config(self):
        cfg = dict(kind=self.kind, domain=self.domain, resolutions=self.resolutions,
                   channels=self.channels, hidden=self.hidden, dir_octaves=self.dir_octaves,
                   color_layers=self.color_layers, density_bias=self.density_bias,
                   density_activation=self.density_activation, s_ratio=self.s_ratio,
                   warp_radius=self.warp_radius, color=self.color_mode,
                   antialias=self.antialias, planes=self.planes, init=self.init)
        if self.sparse:            # (so that files without sparse levels stay as they were)
            cfg.update(sparse=self.sparse, sparse_blocks=self.sparse_blocks,
                       sparse_s=self.sparse_s)
        if self.appearance_dims:
            cfg.update(appearance_dims=self.appearance_dims)
        return cfg

    def allocated_bricks(self):
        """The allocated bricks of each sparse level: ``{'sparse<i>': flat brick indices}``."""
        return {f'sparse{i}': g.allocated for i, g in enumerate(self.bricks)}

    def set_bricks(self, values):
        """Allocate the bricks of sparse levels (``{'sparse<i>': flat brick indices}``): the
        texels of bricks kept stay, new bricks start at zero, the others are let go. The
        parameter changes shape (an optimiser must take it anew)."""
        for key, bricks in values.items():
            i = int(key[len('sparse'):]) if key.startswith('sparse') else -1
            if not 0 <= i < len(self.bricks):
                raise KeyError(f"field '{self.kind}' has no sparse level '{key}'")
            grid = self.bricks[i]
            pool = grid.moved(self.params[key].numpy(), bricks)
            grid.allocate(bricks)
            self.params[key] = mi.TensorXf(pool)

    @property
    def deferred(self):
        """Whether colour comes from features composited along the ray (one MLP per ray)."""
        return self.color_mode == 'deferred'

    def cell_size(self, level):
        """The width of a cell of ``level`` in the units of :meth:`Volume.footprint_at
        <mi_nerfpp.core.render.Volume.footprint_at>`: ``2/R`` of the (warped) ball, ``π/R`` radians of
        the background's colatitude (and of its longitude at the equator)."""
        return self._cell_width(self.resolutions[level])

    def plane_cell_size(self, level):
        """The width of a cell of plane level ``level``, as :meth:`cell_size`."""
        return self._cell_width(self.planes[level])

    def sparse_cell_size(self, level):
        """The width of a texel of sparse level ``level``, as :meth:`cell_size`."""
        return self._cell_width(self.sparse[level])

    def _cell_width(self, r):
        return 2.0 / r if self.domain == 'ball' else dr.pi / r

    def _lookup(self, x, width=None):
        """Density logit and feature vector (all levels) at field inputs ``x``, each level
        weighted by :func:`level_weight` of the footprint ``width`` (``antialias`` only)."""
        if not self.antialias:
            width = None
        plain, plain_width = x, width      # sparse levels index the domain unwarped
        if self.domain == 'ball':
            if width is not None and self.warp_radius > 0:
                # The warp scales lengths about the centre by |warp(p)|/|p| (tangentially).
                r = dr.norm(mi.Vector3f(*x))
                warped = ball_warp(x, self.warp_radius)
                width = width * dr.norm(mi.Vector3f(*warped)) / dr.maximum(r, 1e-12)
                x = warped
            else:
                x = ball_warp(x, self.warp_radius)
        coords = grid_coordinates(self.domain, x)
        density = mi.Float(self.density_bias)
        features = []
        for i, (tex, r) in enumerate(zip(self.textures, self.resolutions)):
            tex.set_tensor(self.params[f'grid{i}'])
            shape = self._grid_shape(r, i)
            if self.domain == 'inverted_sphere':
                # Periodic in longitude only: keep colatitude and s off the wrap.
                c = [coords[0]] + [dr.clip(coords[k], 0.5 / shape[2 - k], 1.0 - 0.5 / shape[2 - k])
                                   for k in (1, 2)]
            else:
                c = coords
            g = list(tex.eval(mi.Point3f(*c)))
            if width is not None:
                w = level_weight(width, self.cell_size(i))
                g = [w * v for v in g]
            density += g[0]
            features += g[1:]
        for i, r in enumerate(self.planes):
            g = None
            for axes, shape in plane_shapes(self.domain, r):
                tex = self.plane_textures[f'plane{i}{axes}']
                tex.set_tensor(self.params[f'plane{i}{axes}'])
                a, b = PLANE_AXES[axes]
                c = [coords[a], coords[b]]
                if self.domain == 'inverted_sphere':
                    # Periodic in longitude only (axis 0): keep colatitude and s off the wrap.
                    c = [c[k] if (a, b)[k] == 0 else
                         dr.clip(c[k], 0.5 / shape[1 - k], 1.0 - 0.5 / shape[1 - k])
                         for k in (0, 1)]
                v = list(tex.eval(mi.Point2f(*c)))
                g = v if g is None else [p + q for p, q in zip(g, v)]
            if width is not None:
                w = level_weight(width, self.plane_cell_size(i))
                g = [w * v for v in g]
            density += g[0]
            features += g[1:]
        if self.bricks:
            coords = grid_coordinates(self.domain, plain)
        for i, grid in enumerate(self.bricks):
            c = coords
            if self.domain == 'inverted_sphere':
                Z, Y, _ = grid.shape
                c = [coords[0], dr.clip(coords[1], 0.5 / Y, 1.0 - 0.5 / Y),
                     dr.clip(coords[2], 0.5 / Z, 1.0 - 0.5 / Z)]
            g = grid.lookup(self.params[f'sparse{i}'].array, c)
            if plain_width is not None:
                w = level_weight(plain_width, self.sparse_cell_size(i))
                g = [w * v for v in g]
            density += g[0]
            features += g[1:]
        return density, features

    def density(self, x, width=None):
        return ACTIVATIONS[self.density_activation](self._lookup(x, width)[0])

    def features(self, x, width=None):
        """Density and feature vector (list of Floats) at field inputs ``x`` (footprints
        ``width``): what deferred colour composites along a ray."""
        density, features = self._lookup(x, width)
        return ACTIVATIONS[self.density_activation](density), features

    def color(self, features, d):
        """Colour (Color3f in [0, 1]) of composited ``features`` (one list entry per feature
        channel, one value per ray) seen along unit directions ``d`` (one per ray)."""
        out = self.color_net(features, self._ray_inputs(d))
        return mi.Color3f(*[sigmoid(o) for o in out])

    def sample_color(self, features, d, ray):
        """Per-sample colour (``color='sample'``) of samples with ``features`` (one list entry
        per feature channel, one value per sample) on rays ``ray`` of unit directions ``d``
        (one per ray)."""
        out = self.color_net(features, self._ray_inputs(d), ray)
        return mi.Color3f(*[sigmoid(o) for o in out])

    def _ray_inputs(self, d):
        """What the colour network takes once per ray: the encoded direction and the ray's
        appearance code (zero unless set, :attr:`appearance_code`)."""
        inputs = positional_encoding([d.x, d.y, d.z], self.dir_octaves)
        if self.appearance_dims:
            zero = dr.zeros(mi.Float, dr.width(d.x))
            code = self.appearance_code or [0.0] * self.appearance_dims
            inputs += [zero + c for c in code]      # one value per ray
        return inputs

    def __call__(self, x, d, ray, width=None):
        """Per-sample colour (``color='sample'``): the colour MLP at every sample."""
        density, features = self._lookup(x, width)
        return ACTIVATIONS[self.density_activation](density), self.sample_color(features, d, ray)


# ----------------------------------------------------------------------------- pure MLP

class MLPField(Field):
    """The paper's pure-MLP fields (positional encoding, no grid).

    ``structure='nerf'``: ``γ^pos_octaves(x)`` -> trunk (``depth`` ReLU layers of
    ``width``) -> ``[σ, feature]``; ``[feature, γ^dir_octaves(d)]`` -> ``width/2`` -> rgb.
    ``structure='vanilla'`` (paper §3, "keeping the structure of σ the same"): the
    same trunk gives σ; colour is a second MLP of ``depth`` ReLU layers of ``width``
    over ``[γ^pos_octaves(x), γ^pos_octaves(d)]`` — position and direction treated
    symmetrically, both at the first layer with the same encoding (``dir_octaves``
    is unused). About twice the network evaluations of ``'nerf'``.
    The paper's network is depth 8, width 256 with a skip connection; the
    defaults here are smaller for the CPU and have no skip. Samples are points: a footprint
    ``width`` is ignored.
    """

    def __init__(self, domain, structure='nerf', depth=4, width=64, pos_octaves=10,
                 dir_octaves=4, density_bias=0.0, seed=0):
        super().__init__(domain)
        if structure not in ('nerf', 'vanilla'):
            raise ValueError(f"MLPField structure must be 'nerf' or 'vanilla', not '{structure}'")
        self.structure = self.kind = structure
        self.depth, self.width = int(depth), int(width)
        self.pos_octaves, self.dir_octaves = int(pos_octaves), int(dir_octaves)
        self.density_bias = float(density_bias)
        rng = dr.rng(seed=seed)
        n_x = DOMAINS[domain] * (1 + 2 * self.pos_octaves)
        if structure == 'nerf':
            n_d = 3 * (1 + 2 * self.dir_octaves)
            self.trunk = _Net(self, 'trunk', mlp([self.width] * self.depth, 1 + self.width), n_x, rng)
            self.head = _LateNet(self, 'head', self.width, n_d, [max(self.width // 2, 1)], 3, rng)
        else:
            n_d = 3 * (1 + 2 * self.pos_octaves)
            self.trunk = _Net(self, 'trunk', mlp([self.width] * self.depth, 1), n_x, rng)
            self.color = _LateNet(self, 'color', n_x, n_d, [self.width] * self.depth, 3, rng)

    @property
    def config(self):
        return dict(kind=self.structure, domain=self.domain, depth=self.depth, width=self.width,
                    pos_octaves=self.pos_octaves, dir_octaves=self.dir_octaves,
                    density_bias=self.density_bias)

    def density(self, x, width=None):
        return softplus(self.trunk(positional_encoding(list(x), self.pos_octaves))[0]
                        + self.density_bias)

    def __call__(self, x, d, ray, width=None):
        gx = positional_encoding(list(x), self.pos_octaves)
        dirs = [d.x, d.y, d.z]
        if self.structure == 'nerf':
            h = self.trunk(gx)
            out = self.head(h[1:], positional_encoding(dirs, self.dir_octaves), ray)
        else:
            h = self.trunk(gx)
            out = self.color(gx, positional_encoding(dirs, self.pos_octaves), ray)
        return softplus(h[0] + self.density_bias), mi.Color3f(*[sigmoid(o) for o in out])


# ----------------------------------------------------------------------------- factory

def make_field(config, seed=0):
    """Build a field from its ``config`` dict (as stored in checkpoints)."""
    cfg = dict(config)
    kind = cfg.pop('kind', 'grid')
    domain = cfg.pop('domain')
    try:
        if kind == 'grid':
            return GridField(domain, seed=seed, **cfg)
        if kind in ('nerf', 'vanilla'):
            return MLPField(domain, structure=kind, seed=seed, **cfg)
    except TypeError as e:
        raise ValueError(f"invalid field config {config}: {e}") from None
    raise ValueError(f"unknown field kind '{kind}' (expected 'grid', 'nerf' or 'vanilla')")
