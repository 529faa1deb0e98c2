"""Radiance fields: density σ(x) and colour c(x, d) of one volume.

Two domains (the two volumes of the paper's §4):

* ``'ball'`` — the foreground, points ``p`` inside the unit sphere (3 inputs);
* ``'inverted_sphere'`` — the background, ``(x̂, s)`` with ``x̂`` on the unit
  sphere and ``s = 1/r ∈ (0, 1]`` (4 inputs, 3 degrees of freedom).

Three field kinds, chosen per volume by the ``field`` XML parameter:

* :class:`GridField` (``'grid'``, the default) — multi-resolution feature-grid levels
  (dense, plane and sparse, :mod:`mi_nerfpp.core.encodings`) plus a small MLP. Density comes
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

import inspect
import math
import numbers
import os
from dataclasses import dataclass

import drjit as dr
import drjit.nn as nn
import mitsuba as mi
import numpy as np

from mi_nerfpp.core.arrays import llvm_backend
from mi_nerfpp.core.encodings import CHANNELS, DenseLevels, PlaneLevels, SparseLevels
from mi_nerfpp.core.geometry import ball_warp, grid_coordinates
from mi_nerfpp.errors import shown

DOMAINS = {'ball': 3, 'inverted_sphere': 4}
# How a grid field colours a ray: 'deferred' (features composited, one MLP per ray) or
# 'sample' (an MLP per sample, as the paper's fields and models trained before deferred colour).
COLOR_MODES = ('deferred', 'sample')
# What shapes the colour MLP is bounded by sense rather than memory: each layer is traced into
# the step's kernels (thousands of layers compile for hours), and direction frequencies 2^k
# beyond float32's 24-bit mantissa are noise. NeRF-W's appearance codes have 48 numbers; each
# is an input of the colour networks' per-ray layer.
MAX_COLOR_LAYERS = 64
MAX_DIR_OCTAVES = 24
MAX_APPEARANCE_DIMS = 64
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

@dataclass(frozen=True)
class ColorNetwork:
    """The colour MLP of a grid field: ``layers`` hidden layers of ``hidden`` units over the
    features and ``γ^dir_octaves(d)`` (plus ``appearance_dims`` of a per-ray appearance code).
    The default — one layer of 32, ``γ^2`` — is the late-injection prior: the direction passes
    one non-linearity. Two octaves, not NeRF's four: with fewer view-dependent degrees of
    freedom the colour generalizes better to held-out views (measured on the default capture,
    README tuning table). ``layers=4, hidden=64, dir_octaves=10`` is the grid analogue of the
    paper's vanilla MLP (§3): grid features and ``γ^10(d)`` side by side at the input of a deep
    colour MLP."""
    hidden: int = 32
    layers: int = 1
    dir_octaves: int = 2
    appearance_dims: int = 0

    def __post_init__(self):
        if self.layers < 1:
            raise ValueError('GridField needs color_layers >= 1')
        if self.appearance_dims < 0:
            raise ValueError(f'GridField appearance_dims must be >= 0, got {self.appearance_dims}')


class GridField(Field):
    """Multi-resolution feature-grid levels (:mod:`~mi_nerfpp.core.encodings`) + a small colour
    MLP.

    ``levels``: the grid levels it sums, in order — :class:`~.encodings.DenseLevels`,
    :class:`~.encodings.PlaneLevels`, :class:`~.encodings.SparseLevels`, at most one of each
    kind, all of the same channels. Channel 0 of all levels sums to the density logit:
    ``σ = exp(Σ_l g_l[0](x) + density_bias)`` (``density_activation='exp'``, clamped; or
    ``'softplus'``). The exponential lets opaque surfaces (σ·δ ≫ 1) form in a few hundred Adam
    steps. The other channels are concatenated into a feature vector ``f(x)``; colour is
    ``sigmoid(MLP([f, γ(d)]))``, the MLP described by ``network`` (:class:`ColorNetwork`). With
    ``color='deferred'`` (the default) ``f`` is the feature vector composited along the ray
    (normalized by its opacity, see :func:`mi_nerfpp.core.render.composite_features`) and the
    MLP runs once per ray; with ``color='sample'`` (models trained before deferred colour) it
    runs at every sample on ``f(x)``, its first layer's direction share computed once per ray.

    ``antialias``: a level whose cells are smaller than a sample's pixel footprint (its
    ``width``, :meth:`mi_nerfpp.core.render.Volume.footprint_at`) cannot be resolved at that
    width and would alias; its contribution (density logit and features) is weighted by
    ``clip(2 − width/cell, 0, 1)``: whole up to a footprint of one cell, gone from two cells on
    (:func:`~.encodings.level_weight`), so coarse levels alone describe what a wide footprint
    sees. A footprint within the finest cell, or none, is a point lookup exactly. Fields built
    without it (and checkpoints from before it) look up points.

    ``warp_radius`` (ball): dense and plane levels index :func:`~mi_nerfpp.core.geometry.
    ball_warp` of the point (finer cells in the centre, where a 360° capture's cameras look);
    0 indexes the point itself. The background's levels are indexed by the spherical angles of
    ``x̂`` and ``s``.

    Its config (:attr:`config`, stored in checkpoints) is one flat dict; :func:`grid_field`
    builds a field from it.
    """

    kind = 'grid'

    def __init__(self, domain, levels, network=ColorNetwork(), density_bias=-3.0,
                 density_activation='exp', warp_radius=0.0, color='deferred', antialias=False,
                 rng=None):
        super().__init__(domain)
        self.levels = list(levels)
        kinds = [lv.kind for lv in self.levels]
        if len(set(kinds)) != len(kinds) or any(lv.domain != domain for lv in self.levels):
            raise ValueError(f'GridField takes at most one level set of each kind, of its '
                             f'domain {domain!r}: got {kinds}')
        channels = {lv.channels for lv in self.levels}
        if len(channels) > 1:
            raise ValueError(f'GridField levels must have the same channels, got {channels}')
        self.channels = channels.pop() if channels else CHANNELS
        # One dict of parameters, the field's: the levels read theirs from it.
        for lv in self.levels:
            self.params.update(lv.params)
            lv.params = self.params
        # The appearance code of each ray (``appearance_dims`` Floats, one value per ray, or
        # one value for all of them), set by whoever renders (:meth:`mi_nerfpp.core.model.
        # NeRFPPModel.set_appearance`); None: the neutral code, zero.
        self.appearance_code = None
        self.network = network
        self.appearance_dims = network.appearance_dims
        self.antialias = bool(antialias)
        if color not in COLOR_MODES:
            raise ValueError(f"GridField color must be one of {', '.join(COLOR_MODES)}, "
                             f"got {color!r}")
        self.color_mode = color
        self.warp_radius = float(warp_radius)
        if not 0 <= self.warp_radius < 1:
            raise ValueError(f'GridField warp_radius must be in [0, 1), got {warp_radius}')
        self.density_bias = float(density_bias)
        if density_activation not in ACTIVATIONS:
            raise ValueError(f"density_activation must be one of {sorted(ACTIVATIONS)}")
        self.density_activation = density_activation
        rng = dr.rng(seed=0) if rng is None else rng
        n_feat = sum(lv.features for lv in self.levels)
        n_dir = 3 * (1 + 2 * network.dir_octaves)
        self.color_net = _LateNet(self, 'color', n_feat, n_dir + network.appearance_dims,
                                  [network.hidden] * network.layers, 3, rng)

    def _of_kind(self, cls):
        return next((lv for lv in self.levels if isinstance(lv, cls)), cls(self.domain))

    @property
    def dense(self) -> DenseLevels:
        """Its dense levels (none: an empty set)."""
        return self._of_kind(DenseLevels)

    @property
    def planes(self) -> PlaneLevels:
        """Its plane levels (none: an empty set)."""
        return self._of_kind(PlaneLevels)

    @property
    def sparse(self) -> SparseLevels:
        """Its sparse levels (none: an empty set)."""
        return self._of_kind(SparseLevels)

    @property
    def config(self):
        cfg = dict(kind=self.kind, domain=self.domain, resolutions=[], channels=self.channels,
                   hidden=self.network.hidden, dir_octaves=self.network.dir_octaves,
                   color_layers=self.network.layers, density_bias=self.density_bias,
                   density_activation=self.density_activation, warp_radius=self.warp_radius,
                   color=self.color_mode, antialias=self.antialias, planes=[])
        for lv in self.levels:
            cfg.update(lv.config)
        if self.appearance_dims:
            cfg.update(appearance_dims=self.appearance_dims)
        return cfg

    def set_parameters(self, values):
        super().set_parameters(values)
        # Let go of the previous tensors now (a frozen training step, which sets them on
        # lookup, would keep its recording's inputs alive otherwise).
        for lv in self.levels:
            lv.bind()

    def allocated_bricks(self):
        """The allocated bricks of each sparse level: ``{'sparse<i>': flat brick indices}``."""
        return self.sparse.allocated()

    def set_bricks(self, values, start=False):
        """Allocate the bricks of sparse levels (:meth:`~.encodings.SparseLevels.allocate`)."""
        if values:
            self.sparse.allocate(values, start)

    @property
    def deferred(self):
        """Whether colour comes from features composited along the ray (one MLP per ray)."""
        return self.color_mode == 'deferred'

    def _coordinates(self, x, width, warped):
        """Grid coordinates of field inputs ``x`` and the footprint ``width`` in the units the
        levels measure cells in: through the ball's warp (``warped``) or of ``x`` itself."""
        if not warped or self.domain != 'ball':
            return grid_coordinates(self.domain, x), width
        if width is not None and self.warp_radius > 0:
            # The warp scales lengths about the centre by |warp(p)|/|p| (tangentially).
            r = dr.norm(mi.Vector3f(*x))
            warped_x = ball_warp(x, self.warp_radius)
            width = width * dr.norm(mi.Vector3f(*warped_x)) / dr.maximum(r, 1e-12)
            return grid_coordinates(self.domain, warped_x), width
        return grid_coordinates(self.domain, ball_warp(x, self.warp_radius)), width

    def _lookup(self, x, width=None):
        """Density logit and feature vector (all levels) at field inputs ``x``, each level
        weighted by :func:`~.encodings.level_weight` of the footprint ``width`` (``antialias``
        only)."""
        if not self.antialias:
            width = None
        density = mi.Float(self.density_bias)
        features = []
        at = {}         # coordinates and widths by ``warped``: dense and plane levels share them
        for lv in self.levels:
            if not len(lv):
                continue
            if lv.warped not in at:
                at[lv.warped] = self._coordinates(x, width, lv.warped)
            for g in lv.lookup(*at[lv.warped]):
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
        inputs = positional_encoding([d.x, d.y, d.z], self.network.dir_octaves)
        if self.appearance_dims:
            zero = dr.zeros(mi.Float, dr.width(d.x))
            code = self.appearance_code or [0.0] * self.appearance_dims
            inputs += [zero + c for c in code]      # one value per ray
        return inputs

    def __call__(self, x, d, ray, width=None):
        """Per-sample colour (``color='sample'``): the colour MLP at every sample."""
        density, features = self._lookup(x, width)
        return ACTIVATIONS[self.density_activation](density), self.sample_color(features, d, ray)


# Where each entry of a grid field's stored config (:attr:`GridField.config`, one flat dict)
# goes: (the class that takes it, its parameter there). The one home of that layout; each
# entry's default is its parameter's (:func:`grid_default`).
GRID_CONFIG = {
    'resolutions': (DenseLevels, 'resolutions'), 's_ratio': (DenseLevels, 's_ratio'),
    'init': (DenseLevels, 'init'), 'channels': (DenseLevels, 'channels'),
    'planes': (PlaneLevels, 'resolutions'),
    'sparse': (SparseLevels, 'resolutions'), 'sparse_blocks': (SparseLevels, 'blocks'),
    'sparse_s': (SparseLevels, 's'),
    'hidden': (ColorNetwork, 'hidden'), 'color_layers': (ColorNetwork, 'layers'),
    'dir_octaves': (ColorNetwork, 'dir_octaves'),
    'appearance_dims': (ColorNetwork, 'appearance_dims'),
    'density_bias': (GridField, 'density_bias'),
    'density_activation': (GridField, 'density_activation'),
    'warp_radius': (GridField, 'warp_radius'), 'color': (GridField, 'color'),
    'antialias': (GridField, 'antialias')}


def grid_default(entry):
    """The default of an entry of a grid field's stored config (:data:`GRID_CONFIG`)."""
    owner, name = GRID_CONFIG[entry]
    return inspect.signature(owner).parameters[name].default


def _whole(low, high=None):
    return lambda v: (isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= low
                      and (high is None or v <= high))


def _whole_list(low, high=None):
    return lambda v: isinstance(v, (list, tuple)) and all(map(_whole(low, high), v))


def _real(v):
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)


def _ratio(v):
    return _real(v) and 0 < v <= 1


# What each entry of a stored field config must be (checked before anything is built from it:
# a damaged checkpoint is refused in a line, not by an allocation, issue 63): entry ->
# (check, what it must be). Resolutions are bounded by what one array holds (a dense level of
# 2048³ texels is past Dr.Jit's 2^32 entries); the reader compares the sizes they make with
# the stored parameters.
MAX_RESOLUTION = 2048
FIELD_ENTRIES = {
    'kind': (lambda v: v in ('grid', 'nerf', 'vanilla') if isinstance(v, str) else False,
             "'grid', 'nerf' or 'vanilla'"),
    'domain': (lambda v: isinstance(v, str) and v in DOMAINS,
               ' or '.join(map(repr, DOMAINS))),
    'resolutions': (lambda v: _whole_list(2, MAX_RESOLUTION)(v) and len(v) >= 1,
                    f'a list of one or more whole numbers from 2 to {MAX_RESOLUTION}'),
    'planes': (_whole_list(2, 1 << 15), 'a list of whole numbers from 2 to 32768'),
    'sparse': (_whole_list(2, 1 << 14), 'a list of whole numbers from 2 to 16384'),
    'sparse_blocks': (lambda v: v is None or (_whole_list(1)(v) and len(v) == 3),
                      'three whole numbers >= 1, or null'),
    'sparse_s': (lambda v: v is None or _whole(1)(v), 'a whole number >= 1, or null'),
    'channels': (_whole(1, 1 << 10), 'a whole number from 1 to 1024'),
    'hidden': (_whole(1, 1 << 14), 'a whole number from 1 to 16384'),
    'width': (_whole(1, 1 << 14), 'a whole number from 1 to 16384'),
    'depth': (_whole(1, MAX_COLOR_LAYERS), f'a whole number from 1 to {MAX_COLOR_LAYERS}'),
    'color_layers': (_whole(1, MAX_COLOR_LAYERS),
                     f'a whole number from 1 to {MAX_COLOR_LAYERS}'),
    'dir_octaves': (_whole(0, MAX_DIR_OCTAVES), f'a whole number from 0 to {MAX_DIR_OCTAVES}'),
    'pos_octaves': (_whole(0, MAX_DIR_OCTAVES), f'a whole number from 0 to {MAX_DIR_OCTAVES}'),
    'appearance_dims': (_whole(0, MAX_APPEARANCE_DIMS),
                        f'a whole number from 0 to {MAX_APPEARANCE_DIMS}'),
    's_ratio': (lambda v: _ratio(v) or (isinstance(v, (list, tuple)) and v
                                        and all(map(_ratio, v))),
                'a number in (0, 1], or a list of them'),
    'init': (lambda v: _real(v) and v >= 0, 'a finite number >= 0'),
    'density_bias': (_real, 'a finite number'),
    'warp_radius': (lambda v: _real(v) and 0 <= v < 1, 'a number in [0, 1)'),
    'antialias': (lambda v: isinstance(v, bool), 'true or false'),
    'color': (lambda v: isinstance(v, str) and v in COLOR_MODES,
              ' or '.join(map(repr, COLOR_MODES))),
    'density_activation': (lambda v: isinstance(v, str) and v in ACTIVATIONS,
                           ' or '.join(map(repr, ACTIVATIONS))),
}


def check_field_config(config: dict, domain) -> None:
    """ValueError naming the first entry of the stored config of a field over ``domain`` that
    is not what :data:`FIELD_ENTRIES` says it must be."""
    field = f'the {domain} field' if isinstance(domain, str) and domain in DOMAINS else 'a field'
    for entry, value in config.items():
        if entry in FIELD_ENTRIES and not FIELD_ENTRIES[entry][0](value):
            raise ValueError(f'{field} entry {entry!r} must be {FIELD_ENTRIES[entry][1]}, '
                             f'got {shown(value)}')


def grid_field(domain, seed=0, **config):
    """A :class:`GridField` from the entries of its stored config (:attr:`GridField.config`,
    :data:`GRID_CONFIG`, each checked: :func:`check_field_config`), the others at their
    defaults: dense, plane and sparse levels (all with ``channels``) and the colour network,
    drawn from one generator seeded ``seed``."""
    unknown = sorted(set(config) - set(GRID_CONFIG))
    if unknown:
        raise TypeError(f"unexpected grid field entries {unknown}")
    check_field_config(config, domain)
    args = {}
    for entry, value in config.items():
        owner, name = GRID_CONFIG[entry]
        args.setdefault(owner, {})[name] = value
    channels = args.get(DenseLevels, {}).get('channels', CHANNELS)
    rng = dr.rng(seed=seed)
    levels = [DenseLevels(domain, rng=rng, **args.get(DenseLevels, {})),
              PlaneLevels(domain, channels=channels, **args.get(PlaneLevels, {})),
              SparseLevels(domain, channels=channels, seed=seed,
                           init=args.get(DenseLevels, {}).get('init', grid_default('init')),
                           **args.get(SparseLevels, {}))]
    return GridField(domain, levels, network=ColorNetwork(**args.get(ColorNetwork, {})),
                     rng=rng, **args.get(GridField, {}))

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
    """Build a field from its ``config`` dict (as stored in checkpoints; checked:
    :func:`check_field_config`)."""
    if not isinstance(config, dict):
        raise ValueError(f'a field config must be an object, got {type(config).__name__}')
    check_field_config(config, config.get('domain'))
    cfg = dict(config)
    kind = cfg.pop('kind', 'grid')
    domain = cfg.pop('domain')
    try:
        if kind == 'grid':
            return grid_field(domain, seed=seed, **cfg)
        if kind in ('nerf', 'vanilla'):
            check_field_config(cfg, domain)
            return MLPField(domain, structure=kind, seed=seed, **cfg)
    except TypeError as e:
        raise ValueError(f"invalid field config {config}: {e}") from None
    raise ValueError(f"unknown field kind '{kind}' (expected 'grid', 'nerf' or 'vanilla')")
