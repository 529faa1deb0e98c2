"""Volume rendering of NeRF++: quadrature, hierarchical sampling per volume, Eq. 4 composite.

This is the one implementation of volume rendering: the Mitsuba integrator and
training both call :func:`render_rays`. Data flows one way:
rays -> samples (:mod:`.sampling`) -> fields (:mod:`.fields`) -> quadrature -> composite.

Quadrature (NeRF): for samples ``v_0 < … < v_{n-1}`` with interval lengths
``δ_i``, ``α_i = 1 - exp(-σ_i δ_i)``, ``T_i = Π_{j<i}(1 - α_j)``, ``w_i = T_i α_i``;
colour ``Σ w_i c_i``, opacity ``Σ w_i``, depth ``Σ w_i t_i``.

* Foreground: ``v = t`` on ``[t0, t1]`` inside the unit sphere, ``δ_i = v_{i+1} - v_i``
  and the last interval ends at the sphere (``t1``).
* Background: density is per unit of inverse radius ``s``. ``v = 1 - s/s_max``
  on ``[0, 1)``, ``δ_i = s_i - s_{i+1}``, and the last interval reaches ``s = 0``,
  infinity, where it is treated as infinitely long (as NeRF++ does): whatever
  light is left is absorbed by the last sample, so the background is opaque.
  Depth of a background sample is ``t(s)`` with ``s`` clamped to
  ``>= 1/MAX_DEPTH_RADIUS``. Light absorbed by the last (infinite) interval is
  given the distance of the last sample. Without fine samples that is the last
  coarse midpoint, ``v = 1 - 1/(2n)``: radius ``2n`` (128 unit-sphere radii for
  64 coarse samples). With fine samples (the default) the last coarse bin, which
  holds that absorbed weight, reaches ``v = 1`` (``s = 0``) and receives fine
  samples up to it, so the last sample lies beyond ``MAX_DEPTH_RADIUS`` and the
  absorbed light is placed at the cap, 1000 unit-sphere radii.

A surface at ray distance ``far`` (a Mitsuba shape, :mod:`.objects`) ends both volumes:
the foreground segment stops there, the background runs from ``s_max`` down to ``s(far)``
with a finite last interval, so the composite is no longer opaque and ``1 - opacity`` is
the transmittance to the surface.

Hierarchical sampling per volume: the field is evaluated at ``n_coarse`` stratified
samples; ``n_fine`` more are drawn from their weights by inverse CDF; the image composites
the union of both sets, reusing the coarse samples' field values (one field per volume
serves both passes; the coarse pass only places samples).

Colour (paper Fig. 3: the view direction enters late). A field with *deferred* colour (the
grid field) gives each sample a density and a feature vector ``f_i``; the features are
composited along the ray like colour, ``F = Σ w_i f_i``, and the field's colour network runs
once per ray on ``F/α`` and the view direction: ``C = α·c(F/α, d)`` (:func:`composite_features`).
A field with per-sample colour (the pure-MLP fields, closed-form test fields) gives each
sample its colour ``c_i(d)``, composited as ``C = Σ w_i c_i``. For a colour network that is
affine in its features the two agree.

Pixel footprints (anti-aliasing). A ray may carry its pixel's *footprint* ``ρ``: the width of
the pixel per unit distance along the ray (the square root of its solid angle). A sample at
distance ``t`` then covers a width ``ρ·t`` of the foreground, and an angle ``ρ·t·s`` of the
background's sphere of radius ``1/s``; :meth:`Volume.footprint_at` gives it in the units of
the field's domain, and a field that filters (:class:`~.fields.GridField` with ``antialias``)
leaves out what its grid levels cannot resolve at that width. Rays without a footprint
(None) are looked up as points.

Primal renders (the integrator) terminate rays early: the background is rendered only
behind a foreground that lets light through (``skip_occluded`` of :func:`render_rays`), and
per-sample colour is evaluated only at samples that can show, after the densities of both
passes; the image moves by less than 1e-4 per threshold.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from mi_nerfpp.core import geometry as geo
from mi_nerfpp.core.occupancy import DEFAULT_BINS, OccupiedVolume
from mi_nerfpp.core.profiling import settle, stage
from mi_nerfpp.core.rays import Rays
from mi_nerfpp.core.sampling import (FineSampler, flat_index, gather_merged,
                                     merge_order, per_ray, split_merged,
                                     stratified_sample, uniforms)

MAX_DEPTH_RADIUS = 1000.0
INFINITE_DELTA = 1e10
# Early ray termination between the volumes: where the foreground lets less than this
# fraction of light through (λ), the background is not rendered. Colours are in [0, 1],
# so the composite changes by at most this much.
OCCLUDED_TRANSMITTANCE = 1e-4
# Early ray termination within a volume (primal renders): the samples whose colour is not
# evaluated hold less than this much of a ray's weight in all (see :func:`_shade_visible`).
HIDDEN_WEIGHT = 1e-4
# Deferred colour: composited features are divided by the opacity, at least this much (a ray
# that sees nothing has no colour to speak of; its premultiplied colour is ~0 either way).
FEATURE_OPACITY_FLOOR = 1e-4
# The accumulated opacity at which a ray's surface is taken (:func:`surface_distance`).
SURFACE_LEVEL = 0.5


@dataclass
class Shading:
    """Per-ray result of compositing one set of samples (of one volume or both)."""
    rgb: mi.Color3f
    opacity: mi.Float
    depth: mi.Float


@dataclass
class VolumeRender:
    """One volume's quadrature (``shading``: its colour, opacity and depth per ray, of the
    coarse and fine samples merged) and the per-sample weights of its merged samples (for the
    regularizers and the surface estimate)."""
    shading: Shading
    weights: mi.Float          # w_i of the merged samples, flat layout with n samples per ray
    position: mi.Float         # sample positions normalized to [0, 1] along the volume
    n: int
    distance: mi.Float = None  # distance along the ray of each sample (same layout as weights)
    rays: mi.UInt32 = None     # the rays the per-sample arrays belong to (None: every ray)
    # Fused renders (no per-sample arrays): per ray, the distance at which the accumulated
    # weight reaches the surface level, and whether it does (:func:`surface_distance`).
    surface: tuple = None


@dataclass
class RenderResult:
    """Per-ray output of :func:`render_rays`: both volumes and their Eq. 4 composite."""
    fg: VolumeRender
    bg: VolumeRender | None
    composite: Shading       # Eq. 4 composite of the volumes (the image)


# ----------------------------------------------------------------------------- volumes

class Volume:
    """What :func:`render_volume` asks of a volume. Samples are drawn in a *sample
    coordinate* ``v`` on ``[lo, hi]`` per ray, where the quadrature's intervals are measured
    (``δ = Δv · delta_scale``); the field inputs and distances are functions of the *ray
    parameter* ``parameter(ray, v)``, which is ``v`` itself for the volumes here and the
    occupied-length inverse for :class:`~.occupancy.OccupiedVolume`. Renders compute it
    once per sample and pass it to ``inputs`` and ``distance``."""

    infinite_last = False
    open = None
    footprint = None      # per ray: the pixel's width per unit distance, or None
    seed = None           # per ray: the jitter of the samples (None: strata midpoints)

    def parameter(self, ray, v):
        """The ray parameter of sample coordinate ``v`` (the identity here)."""
        return v

    def footprint_at(self, ray, v):
        """The pixel footprint of the samples at ``v`` on rays ``ray`` in the units of the
        field's domain (None for rays without a footprint)."""
        return None


class Foreground(Volume):
    """The unit-sphere volume of ``rays`` (:class:`~.rays.Rays`) from distance ``near`` on,
    parametrized by ray distance ``t``; the rays' ``far`` (or None) ends the segment there (the
    ray hit a surface), ``inf`` leaves it whole."""

    def __init__(self, rays: Rays, near=0.0):
        o, d, far = rays.o, rays.d, rays.far
        self.o, self.d, self.footprint, self.seed = o, d, rays.footprint, rays.seed
        # The samples' distances t are constants of the ray parameters (as nerfstudio's):
        # gradients reach o and d through p = o + t·d only.
        self.lo, self.hi = geo.foreground_interval(dr.detach(o), dr.detach(d), near)
        if far is not None:
            self.hi = dr.minimum(dr.maximum(far, self.lo), self.hi)

    def inputs(self, ray, v):
        """Field inputs of the samples at ``v`` on rays ``ray``: the point ``p``."""
        o = dr.gather(mi.Point3f, self.o, ray)
        d = dr.gather(mi.Vector3f, self.d, ray)
        p = dr.fma(d, v, o)
        return [p.x, p.y, p.z]

    def delta_scale(self, ray):
        return 1.0

    def distance(self, ray, v):
        return v

    def footprint_at(self, ray, v):
        """``ρ·t``: the footprint's width at distance ``t``, in the ball's units."""
        if self.footprint is None:
            return None
        return dr.gather(mi.Float, self.footprint, ray) * v

    def normalized(self, ray, v):
        """Position along the chord, 0 at its start and 1 at the sphere."""
        lo, hi = dr.gather(mi.Float, self.lo, ray), dr.gather(mi.Float, self.hi, ray)
        return (v - lo) / dr.maximum(hi - lo, 1e-6)


class Background(Volume):
    """The inverted-sphere volume of ``rays`` (:class:`~.rays.Rays`), parametrized by
    ``v = 1 - s/s_max`` (see module docs).

    The rays' ``far`` (or None) ends the segment at that ray distance: ``v`` then stops at
    ``v_far = 1 - s(far)/s_max`` and the last interval is finite (the volume is no longer
    opaque); a ``far`` before the start of the outgoing part gives an empty segment, and
    ``far = inf`` leaves the ray as without ``far``. ``open`` (None without ``far``) says per
    ray whether the segment still reaches infinity."""

    infinite_last = True

    def __init__(self, rays: Rays):
        o, d, far = rays.o, rays.d, rays.far
        self.d, self.footprint, self.seed = d, rays.footprint, rays.seed
        self.t_b, self.p_m, self.b = geo.closest_approach(o, d)
        self.s_max = geo.background_s_max(dr.detach(o), dr.detach(d))   # constant, as t
        self.lo = dr.zeros(mi.Float, dr.width(d))
        self.hi = dr.ones(mi.Float, dr.width(d))
        self.open = None
        if far is not None:
            self.open = dr.isinf(far)
            finite = dr.select(self.open, 0.0, far)
            # The outgoing part starts at the sphere exit, or at the origin / closest
            # approach for an origin outside the sphere (see geometry).
            o0, d0 = dr.detach(o), dr.detach(d)          # a constant, as s_max
            t_b, _, b = geo.closest_approach(o0, d0)
            start = dr.maximum(t_b + dr.safe_sqrt(1.0 - dr.square(b)), 0.0)
            s_far = dr.rcp(dr.maximum(dr.norm(dr.fma(d0, finite, o0)), 1.0))
            v_far = dr.clip(1.0 - s_far / self.s_max, 0.0, 1.0)
            self.hi = dr.select(self.open, 1.0, dr.select(finite <= start, 0.0, v_far))

    def s(self, ray, v):
        return dr.gather(mi.Float, self.s_max, ray) * (1.0 - v)

    def inputs(self, ray, v):
        """Field inputs of the samples at ``v`` on rays ``ray``: ``(x̂, s)``."""
        d = dr.gather(mi.Vector3f, self.d, ray)
        s = self.s(ray, v)
        x = geo.inverted_sphere_direction(dr.gather(mi.Point3f, self.p_m, ray),
                                          dr.gather(mi.Float, self.b, ray), d, s)
        return [x.x, x.y, x.z, s]

    def delta_scale(self, ray):
        return dr.gather(mi.Float, self.s_max, ray)

    def normalized(self, ray, v):
        """``v = 1 − s/s_max`` is already 0 at the sphere and 1 at infinity."""
        return v

    def distance(self, ray, v):
        s = dr.maximum(self.s(ray, v), 1.0 / MAX_DEPTH_RADIUS)
        return geo.inverted_sphere_distance(dr.gather(mi.Float, self.t_b, ray),
                                            dr.gather(mi.Float, self.b, ray), s)

    def footprint_at(self, ray, v):
        """``ρ·t·s``: the angle (radians) the footprint's width at distance ``t`` subtends
        on the sphere of radius ``1/s`` it lies on."""
        if self.footprint is None:
            return None
        return (dr.gather(mi.Float, self.footprint, ray) * self.distance(ray, v)
                * self.s(ray, v))


# ----------------------------------------------------------------------------- quadrature

def weights(volume, v, sigma, n):
    """Quadrature weights ``w_i = T_i α_i`` and transmittances ``T_i`` of ``n`` sorted samples
    per ray (flat layout)."""
    n_rays = dr.width(volume.lo)
    ray, k = flat_index(n_rays, n)
    last = k == n - 1
    v_next = dr.gather(mi.Float, v, ray * n + k + 1, ~last)
    v_end = dr.select(last, dr.gather(mi.Float, volume.hi, ray), v_next)
    delta = (v_end - v) * volume.delta_scale(ray)
    if volume.infinite_last:
        # A background segment that a surface ends (``open`` False) keeps its finite interval.
        infinite = last if volume.open is None else last & dr.gather(mi.Bool, volume.open, ray)
        delta = dr.select(infinite, INFINITE_DELTA, delta)
    tau = sigma * delta
    transmittance = dr.exp(-dr.block_prefix_sum(tau, n, exclusive=True))
    return transmittance * (1.0 - dr.exp(-tau)), transmittance


def shade(w, rgb, distance, n):
    """Colour, opacity and depth of ``n`` samples per ray with weights ``w`` at ``distance``."""
    r, g, b, opacity, depth = dr.block_sum([w * rgb.x, w * rgb.y, w * rgb.z, w, w * distance], n)
    return Shading(rgb=mi.Color3f(r, g, b), opacity=opacity, depth=depth)


def quadrature(volume, v, sigma, rgb, n):
    """Composite ``n`` sorted samples per ray. Returns ``(Shading, weights)``."""
    w, _ = weights(volume, v, sigma, n)
    ray, _ = flat_index(dr.width(volume.lo), n)
    return shade(w, rgb, volume.distance(ray, volume.parameter(ray, v)), n), w


def composite(fg, bg):
    """Eq. 4: ``C = C_fg + λ·C_bg`` with ``λ = 1 - opacity_fg`` (depth likewise)."""
    if bg is None:
        return fg
    lam = 1.0 - fg.opacity
    return Shading(rgb=fg.rgb + lam * bg.rgb,
                   opacity=fg.opacity + lam * bg.opacity,
                   depth=fg.depth + lam * bg.depth)


def scale_gradient(x, scale):
    """``x`` unchanged, with the gradient that reaches it through the result times ``scale``."""
    return x + (x - dr.detach(x)) * (scale - 1.0)


def near_gradient_scale(distance, radius):
    """Gradient scale ``min(1, (t/radius)²)`` of samples at ``distance`` t from the camera
    (Philip and Deschaintre 2023, "Floaters No More"): a sample near a camera covers a large part
    of its image, so its gradients are large and the field grows floaters there; scaling them by
    the square of the distance evens out the pull per unit of scene."""
    return dr.minimum(dr.square(distance * (1.0 / radius)), 1.0)


# ----------------------------------------------------------------------------- field lookups
# What a pass of :func:`render_volume` asks of a field at its samples: ``(density, values)``,
# the values those that the quadrature composites. One lookup per render, chosen by
# :func:`field_lookup`.

class SampleColor:
    """Density and colour per sample (fields with per-sample colour): the colour is composited
    sample by sample."""
    shades_later = False

    def __init__(self, field):
        self.field = field

    def __call__(self, x, d, ray, width):
        sigma, rgb = self.field(x, d, ray, **width)
        return sigma, [rgb.x, rgb.y, rgb.z]


class Features:
    """Density and features per sample (deferred colour): the features are composited and the
    colour network runs once per ray (:func:`composite_features`)."""
    shades_later = False

    def __init__(self, field):
        self.field = field

    def __call__(self, x, d, ray, width):
        return self.field.features(x, **width)


class DensityOnly:
    """Density alone (primal renders of fields with per-sample colour): the colour is evaluated
    afterwards at the samples that can show (:func:`_shade_visible`)."""
    shades_later = True

    def __init__(self, field):
        self.field = field

    def __call__(self, x, d, ray, width):
        return self.field.density(x, **width), []


class KeptFeatures(Features):
    """Density and features, kept for the samples that show (a grid field with per-sample
    colour in a primal render): its features come with its density, so only its colour network
    runs where the samples show (:meth:`~.fields.GridField.sample_color`)."""
    shades_later = True


def field_lookup(field, visible_only: bool):
    """The lookup of ``field`` for a render that evaluates colour only where samples show
    (``visible_only``: primal renders with fine samples) or everywhere."""
    if getattr(field, 'deferred', False):
        return Features(field)           # the same render either way
    if not visible_only:
        return SampleColor(field)
    return KeptFeatures(field) if hasattr(field, 'sample_color') else DensityOnly(field)


def render_volume(volume, field, n_coarse, n_fine, options=None, stream=0, level=SURFACE_LEVEL):
    """Hierarchical sampling and quadrature of one volume (see module docs).

    The coarse pass places ``n_coarse`` stratified samples and evaluates the field there; its
    weights (constants) place ``n_fine`` more by inverse CDF, where the field is evaluated too;
    the union of both sets is composited. For a field with ``deferred`` colour the composite
    is of the field's features (:func:`composite_features`) and the colour network runs once per
    ray; otherwise the field's colour is composited sample by sample.

    The samples are jittered by the volume's ``seed`` (its rays', see :class:`Foreground`),
    from random stream ``stream``; the ``options`` (:class:`RenderOptions`, None: the defaults)
    say how:

    ``skip_occluded`` (primal rendering of a field with per-sample colour, with fine samples):
    colour is evaluated at the merged samples that can show (:func:`_shade_visible`): a grid
    field's passes keep its features (they come with its density) and only its colour network
    runs there; other fields' passes take densities only, and the field is evaluated again. A
    deferred field's render is the same with or without it.
    ``near_gradient`` (training; 0: off): the gradients of samples within this distance of the
    ray's origin are scaled down by :func:`near_gradient_scale`; values are unchanged.
    ``fused`` (primal rendering): the merge and the quadrature in one kernel per ray
    (:func:`_fused_quadrature`), without per-sample arrays in the result; its ``surface`` is
    taken at accumulated weight ``level`` (a number or one per ray)."""
    options = options or RenderOptions()
    near_gradient, seed = options.near_gradient, volume.seed
    deferred = getattr(field, 'deferred', False)
    lookup = field_lookup(field, options.skip_occluded and n_fine > 0)
    lazy = lookup.shades_later
    keep = isinstance(lookup, KeptFeatures)
    fused = options.fused and n_fine > 0 and not lazy
    n_rays = dr.width(volume.lo)

    def evaluate(ray, t):
        """Density and the per-sample values to composite (features, or colour) at ``t``."""
        x, width = volume.inputs(ray, t), _footprint(volume.footprint_at(ray, t))
        out = lookup(x, volume.d, ray, width)
        if near_gradient > 0 and not lazy:
            scale = near_gradient_scale(dr.detach(volume.distance(ray, t)), near_gradient)
            out = (scale_gradient(out[0], scale), [scale_gradient(f, scale) for f in out[1]])
        # One kernel computes all outputs of the field; without this, every later
        # use (gathers, block sums) would re-trace the field for its own channel.
        dr.eval(out)
        return out

    ray_c, _ = flat_index(n_rays, n_coarse)
    with stage('sampling'):
        xi_c = uniforms(seed, n_coarse, stream)
        v_c, t_c = _placed(volume, n_rays, n_coarse, lambda ray, k: stratified_sample(
            volume.lo, volume.hi, ray, k, n_coarse, xi_c))
    with stage('field'):
        sigma_c, values_c = evaluate(ray_c, t_c)
    order = None
    if n_fine == 0:
        v, t, sigma, n = v_c, t_c, sigma_c, n_coarse
    else:
        with stage('sampling'):
            w_c, _ = weights(volume, v_c, dr.detach(sigma_c), n_coarse)
            ray_f, _ = flat_index(n_rays, n_fine)
            fine = FineSampler(v_c, w_c, volume.lo, volume.hi, n_coarse, n_fine,
                               uniforms(seed, n_fine, stream + 1))
            v_f, t_f = _placed(volume, n_rays, n_fine, fine.sample)
        with stage('field'):
            sigma_f, values_f = evaluate(ray_f, t_f)
        if fused:
            with stage('quadrature'):
                return _fused_quadrature(volume, field, (v_c, t_c, sigma_c, values_c, n_coarse),
                                         (v_f, t_f, sigma_f, values_f, n_fine), level)
        with stage('merge'):
            # Only what the weights need is merged: the values are composited where they
            # are, with the merged weights taken back to the coarse and fine samples.
            order = merge_order(v_c, n_coarse, v_f, n_fine)
            v, t = gather_merged(order, v_c, v_f), gather_merged(order, t_c, t_f)
            sigma = gather_merged(order, sigma_c, sigma_f)
            settle(v, t, sigma)
        n = n_coarse + n_fine
    ray, _ = flat_index(n_rays, n)
    with stage('quadrature'):
        w, transmittance = weights(volume, v, sigma, n)
        if lazy:
            rgb = _shade_visible(volume, field, t, w, transmittance, n,
                                 (order, values_c, values_f) if keep else None)
            parts = [(w, [rgb.x, rgb.y, rgb.z], n)]
        elif order is None:
            parts = [(w, values_c, n)]
        else:
            dr.eval(w)         # (read by three sums: computed once)
            w_c, w_f = split_merged(order, w)
            parts = [(w_c, values_c, n_coarse), (w_f, values_f, n_fine)]
        distance = volume.distance(ray, t)
        shading = _shading(field, deferred, parts, w, distance, n, volume.d)
        settle(shading.rgb, shading.opacity, shading.depth, w, distance)
    return VolumeRender(shading, w, volume.normalized(ray, v), n, distance)


def _fused_quadrature(volume, field, coarse, fine, level):
    """The quadrature of a volume's coarse and fine samples (each ``(v, t, σ, values, n)``, sorted
    per ray) for primal rendering, in one kernel: a symbolic loop per ray walks both sets in
    merged order (ties: coarse first, as :func:`~.sampling.merge_order`) and accumulates
    :func:`weights`, the composite of the values (features or colour), opacity, depth, and the
    first sample at which the accumulated weight reaches ``level`` (:func:`_crossing`), without
    merged or per-sample arrays. The same sums as the wavefront path, in sequential order
    (float32 rounding apart); its ``VolumeRender`` has no per-sample arrays."""
    deferred = getattr(field, 'deferred', False)
    n_rays = dr.width(volume.lo)
    ray = dr.arange(mi.UInt32, n_rays)
    with dr.suspend_grad():
        sets = []
        for v, t, sigma, values, n in (coarse, fine):
            ray_n, _ = flat_index(n_rays, n)
            sets.append((dr.detach(v), dr.detach(sigma), dr.detach(volume.distance(ray_n, t)),
                         [dr.detach(f) for f in values], n))
        (v_c, sigma_c, dist_c, values_c, n_c), (v_f, sigma_f, dist_f, values_f, n_f) = sets
        scale = dr.detach(volume.delta_scale(ray))
        hi = dr.detach(dr.gather(mi.Float, volume.hi, ray))
        infinite = None
        if volume.infinite_last:
            infinite = dr.full(mi.Bool, True, n_rays) if volume.open is None \
                else dr.gather(mi.Bool, volume.open, ray)
        level = dr.full(mi.Float, level, n_rays) if isinstance(level, (int, float)) \
            else mi.Float(dr.detach(level))
        dr.eval(dist_c, dist_f, scale, hi, infinite, level)

        def body(i, j, head_c, head_f, transmittance, opacity, depth, sums, hit_distance,
                 found):
            take_c = (i < n_c) & ((j >= n_f) | (head_c <= head_f))
            take_f = ~take_c
            at_c, at_f = ray * n_c + i, ray * n_f + j

            def pick(a, b):
                return dr.select(take_c, dr.gather(mi.Float, a, at_c, take_c),
                                 dr.gather(mi.Float, b, at_f, take_f))
            x = dr.select(take_c, head_c, head_f)
            sigma, distance = pick(sigma_c, sigma_f), pick(dist_c, dist_f)
            values = [pick(a, b) for a, b in zip(values_c, values_f)]
            i, j = dr.select(take_c, i + 1, i), dr.select(take_f, j + 1, j)
            has_c, has_f = i < n_c, j < n_f
            # The next sample of the set just taken from.
            head_c = dr.select(take_c, dr.gather(mi.Float, v_c, at_c + 1, take_c & has_c), head_c)
            head_f = dr.select(take_f, dr.gather(mi.Float, v_f, at_f + 1, take_f & has_f), head_f)
            last = ~has_c & ~has_f
            x_next = dr.select(has_c & has_f, dr.minimum(head_c, head_f),
                               dr.select(has_c, head_c, dr.select(has_f, head_f, hi)))
            delta = (x_next - x) * scale
            if infinite is not None:
                delta = dr.select(last & infinite, INFINITE_DELTA, delta)
            passed = dr.exp(-sigma * delta)
            w = transmittance * (1.0 - passed)
            before = opacity
            opacity = opacity + w
            hit = ~found & (opacity >= level) & (before < level)
            return (i, j, head_c, head_f, transmittance * passed, opacity,
                    dr.fma(w, distance, depth),
                    tuple(dr.fma(w, f, a) for f, a in zip(values, sums)),
                    dr.select(hit, distance, hit_distance), found | hit)

        def zeros(tp=mi.Float, value=0):
            return dr.opaque(tp, value, n_rays)
        state = (zeros(mi.UInt32), zeros(mi.UInt32), dr.gather(mi.Float, v_c, ray * n_c),
                 dr.gather(mi.Float, v_f, ray * n_f), zeros(value=1.0), zeros(), zeros(),
                 tuple(zeros() for _ in values_c), zeros(), zeros(mi.Bool, False))
        _, _, _, _, _, opacity, depth, sums, hit_distance, found = dr.while_loop(
            state, lambda i, j, *_: i + j < n_c + n_f, body, label='fused_quadrature')
        if deferred:
            with stage('color'):
                rgb = composite_features(field, list(sums), opacity, volume.d)
        else:
            rgb = mi.Color3f(*sums[:3])
        shading = Shading(rgb=rgb, opacity=opacity, depth=depth)
        settle(shading.rgb, shading.opacity, shading.depth, hit_distance, found)
    return VolumeRender(shading, None, None, n_c + n_f, surface=(hit_distance, found))


def _placed(volume, n_rays, n, sample):
    """``n`` samples per ray of ``volume``: their coordinates ``v = sample(ray, k)`` and ray
    parameters, placed in one loop per ray (:func:`~.sampling.per_ray`: the occupied-length
    inverse reads its per-ray arrays once per ray, not once per sample). Evaluated."""
    def both(ray, k):
        v = sample(ray, k)
        return v, volume.parameter(ray, v)
    v, t = per_ray(n_rays, n, 2, both)
    dr.eval(v, t)
    return v, t


def _footprint(width):
    """The keyword a field is looked up with: ``width`` where the rays have a footprint (fields
    that do not filter take none)."""
    return {} if width is None else {'width': width}


def _shading(field, deferred, parts, w, distance, n, d):
    """Colour, opacity and depth of ``n`` samples per ray with weights ``w`` at ``distance``;
    ``parts``: ``(weights, values, m)`` of the sample sets (``m`` per ray) whose values (the
    features, or colour) are composited: ``Σ w·f`` over the sets."""
    opacity, depth = dr.block_sum([w, w * distance], n)
    sums = None
    for weight, values, m in parts:
        part = dr.block_sum([weight * f for f in values], m)
        sums = part if sums is None else [a + b for a, b in zip(sums, part)]
    if deferred:
        with stage('color'):
            rgb = composite_features(field, sums, opacity, d)
    else:
        rgb = mi.Color3f(*sums[:3])
    return Shading(rgb=rgb, opacity=opacity, depth=depth)


def composite_features(field, features, opacity, d):
    """Deferred colour of a volume: the colour network of ``field`` evaluated once per ray on
    its composited features ``F = Σ w_i f_i``, normalized by the opacity ``α = Σ w_i`` (the
    features of what the ray sees, whatever its opacity), premultiplied: ``α·c(F/α, d)``."""
    scale = dr.rcp(dr.maximum(opacity, FEATURE_OPACITY_FLOOR))
    return opacity * field.color([f * scale for f in features], d)


def _shade_visible(volume, field, t, w, transmittance, n, features=None):
    """Colours of the samples at ray parameters ``t`` (``n`` per ray, weights ``w``), evaluated
    only where they can show and zero elsewhere: not behind the point where a ray's
    transmittance falls below ``HIDDEN_WEIGHT / 2`` (early ray termination: all later weights
    sum to less) and not where a sample's own weight is below ``HIDDEN_WEIGHT / (2n)``. Colours
    lie in [0, 1], so the composite moves by less than ``HIDDEN_WEIGHT``; its opacity and depth
    are exact. ``features``: ``(order, features of the coarse set, of the fine set)`` of a grid
    field, where ``t`` is in the merged ``order`` (:func:`~.sampling.merge_order`): the shown
    samples' features are taken from there, and only the colour network runs; without them
    the field is evaluated anew at the shown samples."""
    dr.eval(w, transmittance)
    shown = dr.compress((transmittance >= 0.5 * HIDDEN_WEIGHT)
                        & (w >= 0.5 * HIDDEN_WEIGHT / n))
    rgb = dr.zeros(mi.Color3f, dr.width(t))
    if dr.width(shown) > 0:
        ray = shown // n
        if features is not None:
            order, f_a, f_b = features
            f = [gather_merged(order, a, b, at=shown) for a, b in zip(f_a, f_b)]
            rgb_shown = field.sample_color(f, volume.d, ray)
        else:
            t_shown = dr.gather(mi.Float, t, shown)
            _, rgb_shown = field(volume.inputs(ray, t_shown), volume.d, ray,
                                 **_footprint(volume.footprint_at(ray, t_shown)))
        dr.scatter(rgb, rgb_shown, shown)
    return rgb


@dataclass
class Sampling:
    """Samples per ray - coarse foreground, coarse background, fine per volume - and the ray
    distance where camera rays start (``near``): the one home of the sample-count defaults.

    The field defaults are for whole rays: renders without empty-space skipping and random
    fields. :data:`SKIPPING` is for samples placed in occupied space only (training's default,
    so the counts a trained model renders with). The integrator's XML parameters override
    them one by one."""
    fg_samples: int = 64
    bg_samples: int = 64
    fine_samples: int = 128
    near: float = 0.0

    @classmethod
    def of_model(cls, kind: str, fg_samples: int, bg_samples: int, fine_samples: int):
        """The samples a model of ``kind`` (``'nerfpp'`` or ``'nerf'``) renders with, trained
        with these counts: the NeRF baseline gets both volumes' coarse budget and twice the
        fine samples in its one volume."""
        if kind == 'nerf':
            return cls(fg_samples + bg_samples, bg_samples, 2 * fine_samples)
        return cls(fg_samples, bg_samples, fine_samples)


# Samples per ray where empty-space skipping places them (occupied space only): training's.
SKIPPING = Sampling(fg_samples=16, bg_samples=16, fine_samples=8)


@dataclass(frozen=True)
class RenderOptions:
    """How :func:`render_rays` renders a batch (besides its rays, fields and samples).

    ``occupancy`` (dict ``'fg'``/``'bg'`` -> :class:`~.occupancy.OccupancyGrid`, either may be
    missing): samples are placed in occupied space only (:class:`~.occupancy.OccupiedVolume`).
    ``skip_occluded`` (primal rendering only) terminates rays early: the background is
    rendered only for rays whose foreground transmittance ``λ`` exceeds
    :data:`OCCLUDED_TRANSMITTANCE` (elsewhere its layers are zero), and within a volume whose
    field has per-sample colour, colour is evaluated only at the samples that can show
    (:func:`_shade_visible`: densities of both passes first, then colour where the
    transmittance and the weight exceed :data:`HIDDEN_WEIGHT`); a grid field's features are
    kept from both passes for it, other fields are asked for ``density(x)`` too.
    ``fused`` (primal rendering only): each volume's merge and quadrature in one kernel per
    ray (:func:`_fused_quadrature`); the result then has no per-sample arrays (what the
    regularizers and deep output read) but the surfaces that :func:`surface_distance` needs.
    ``ray_gradients``: let gradients flow to the rays' ``o`` and ``d`` (pose refinement,
    :mod:`.poses`) through the sample positions; the samples' distances along the ray stay
    constants. Otherwise the rays are detached.
    ``near_gradient`` (training; 0: off): the gradients of samples within this distance of the
    ray's origin are scaled down by :func:`near_gradient_scale`; values are unchanged.
    ``coverage`` (:class:`~.coverage.CoverageFill`, rendering only): paint the background's
    colour where the training views did not see the rays' directions, on rays that no ``far``
    ends (the background's ``shading`` only; its samples are kept as they are)."""
    occupancy: dict | None = None
    skip_occluded: bool = False
    fused: bool = False
    ray_gradients: bool = False
    near_gradient: float = 0.0
    coverage: object = None


def _render_visible_background(rays, fg, render):
    """The background of the rays that the foreground does not occlude, zero elsewhere
    (``render(rays)`` of those rays)."""
    n_rays = dr.width(fg.shading.opacity)
    dr.eval(fg.shading.opacity)
    visible = dr.compress(1.0 - fg.shading.opacity > OCCLUDED_TRANSMITTANCE)

    def expand(shading):
        out = Shading(rgb=dr.zeros(mi.Color3f, n_rays), opacity=dr.zeros(mi.Float, n_rays),
                      depth=dr.zeros(mi.Float, n_rays))
        if shading is not None:
            for name in ('rgb', 'opacity', 'depth'):
                dr.scatter(getattr(out, name), getattr(shading, name), visible)
        return out

    if dr.width(visible) == 0:
        return VolumeRender(expand(None), None, None, 0)
    sub = render(rays.gather(visible), visible)
    return dataclasses.replace(sub, shading=expand(sub.shading), rays=visible)


def render_rays(rays: Rays, fg_field, bg_field, sampling, options: RenderOptions = None):
    """Render ``rays`` (:class:`~.rays.Rays`: origins, unit directions and what each ray
    carries) through the foreground and background volumes: hierarchical sampling and
    quadrature in each (:func:`render_volume`), then Eq. 4.

    ``bg_field=None`` renders the foreground volume alone (a bounded NeRF). ``sampling``
    (:class:`Sampling`) gives the samples per ray and where camera rays start. The rays'
    ``seed`` jitters sample placement (None: strata midpoints); their ``far`` ends every ray
    at that distance, where it meets a surface: both volumes are integrated on ``[near, far]``
    only, the background is then not opaque (``composite.opacity < 1``: ``1 -
    composite.opacity`` is the light that reaches the surface), and a ray with ``far = inf``
    renders exactly as without it; their ``footprint`` filters the lookups of fields that
    filter (module docs, "Pixel footprints"). ``options`` (:class:`RenderOptions`; None: the
    defaults): empty-space skipping, early termination, fused quadrature, gradients to the
    rays, the coverage fill.
    """
    options = options or RenderOptions()
    o, d = mi.Point3f(rays.o), mi.Vector3f(rays.d)
    if not options.ray_gradients:
        o, d = dr.detach(o), dr.detach(d)
    rays = rays.replace(o=o, d=d,
                        far=None if rays.far is None else dr.detach(mi.Float(rays.far)),
                        footprint=(None if rays.footprint is None
                                   else dr.detach(mi.Float(rays.footprint))))
    occupancy = options.occupancy or {}

    def volume(v, key):
        grid = occupancy.get(key)
        if grid is None:
            return v
        with stage('occupancy sampling'):
            return OccupiedVolume(v, grid, DEFAULT_BINS[grid.domain])

    fused = options.fused
    fg = render_volume(volume(Foreground(rays, sampling.near), 'fg'), fg_field,
                       sampling.fg_samples, sampling.fine_samples, options, stream=0)
    bg = None
    # Fused: the background's share of the surface level, in its own accumulated weight.
    level = _background_level(fg.shading.opacity, SURFACE_LEVEL) if fused else SURFACE_LEVEL
    if bg_field is not None and options.skip_occluded:
        bg = _render_visible_background(rays, fg, lambda sub, visible: render_volume(
            volume(Background(sub), 'bg'), bg_field, sampling.bg_samples,
            sampling.fine_samples, options, stream=2,
            level=dr.gather(mi.Float, level, visible) if fused else SURFACE_LEVEL))
    elif bg_field is not None:
        bg = render_volume(volume(Background(rays), 'bg'), bg_field, sampling.bg_samples,
                           sampling.fine_samples, options, stream=2, level=level)
    if bg is not None and options.coverage is not None:
        bg = dataclasses.replace(bg, shading=options.coverage.blend(d, bg.shading, rays.far))
    return RenderResult(fg=fg, bg=bg, composite=composite(fg.shading, bg.shading if bg else None))


def _crossing(weights, distance, n, level):
    """Per ray: the distance of the first sample at which the accumulated weight reaches
    ``level`` (a per-ray Float), and whether it does. The quadrature gives a sample's whole
    interval the sample's distance, so this is the surface as the composite sees it."""
    n_rays = dr.width(weights) // n
    ray, _ = flat_index(n_rays, n)
    target = dr.gather(mi.Float, level, ray)
    after = dr.block_prefix_sum(weights, n, exclusive=False)
    hit = (after >= target) & (after - weights < target)
    t = dr.block_sum(dr.select(hit, distance, 0.0), n)
    found = dr.block_sum(dr.select(hit, 1.0, 0.0), n) > 0.0
    return t, found


def _background_level(alpha, level):
    """The background's share of accumulated opacity ``level`` in its own accumulated weight
    (it is opaque), behind a foreground of opacity ``alpha``."""
    alpha = dr.detach(alpha)
    return (level - alpha) / dr.maximum(1.0 - alpha, 1e-12)


def surface_distance(res: RenderResult, level=SURFACE_LEVEL):
    """Per ray: the distance at which the accumulated opacity of the composite (foreground,
    then ``λ·`` background) reaches ``level`` - a robust surface estimate, unlike the expected
    depth, which lands between surfaces at soft edges and in haze. Rays whose composite never
    reaches ``level`` (a foreground-only render over nothing) get the foreground's expected
    depth, or the :data:`MAX_DEPTH_RADIUS` cap where it is empty. A fused render found its
    surfaces at :data:`SURFACE_LEVEL` while it composited (``VolumeRender.surface``)."""
    fg = res.fg
    fused = fg.weights is None
    if fused and level != SURFACE_LEVEL:
        raise ValueError(f'a fused render has its surfaces at level {SURFACE_LEVEL}, not {level}')
    alpha = dr.detach(fg.shading.opacity)
    if fused:
        t_fg, found_fg = fg.surface
    else:
        t_fg, found_fg = _crossing(dr.detach(fg.weights), fg.distance, fg.n,
                                   dr.full(mi.Float, level, dr.width(alpha)))
    empty = dr.maximum(res.composite.opacity, 0.0) <= 1e-6
    fallback = dr.select(empty, MAX_DEPTH_RADIUS,
                         res.composite.depth / dr.maximum(res.composite.opacity, 1e-6))
    depth = dr.select(found_fg, t_fg, fallback)
    bg = res.bg
    if bg is None or (bg.weights is None and bg.surface is None):
        return depth
    rays = bg.rays if bg.rays is not None else dr.arange(mi.UInt32, dr.width(alpha))
    if bg.surface is not None:
        t_bg, found_bg = bg.surface
    else:
        t_bg, found_bg = _crossing(dr.detach(bg.weights), bg.distance, bg.n,
                                   dr.gather(mi.Float, _background_level(alpha, level), rays))
    behind = dr.full(mi.Float, MAX_DEPTH_RADIUS, dr.width(alpha))
    dr.scatter(behind, dr.select(found_bg, t_bg, MAX_DEPTH_RADIUS), rays)
    return dr.select(alpha >= level, depth, behind)
