"""Tests for volume-rendering quadrature and compositing (mi_nerfpp.core.render) against closed forms.

The quadrature is NeRF's: for sorted samples ``v_0 < … < v_{n-1}``, ``δ_i = v_{i+1} - v_i`` and the
last interval ends at ``hi`` (foreground) or is infinite (background). The part of the segment
before the first sample, ``[lo, v_0]``, is not integrated, so for a constant density σ the
opacity is ``1 - exp(-σ (hi - v_0))``: equal to the continuous ``1 - exp(-σ L)`` exactly when the
first sample sits at ``lo`` (tested with ξ = 0) and short of it by ``σ·(v_0 - lo)`` otherwise.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import mi_nerfpp  # noqa: F401  (sets up libLLVM and the llvm_ad_rgb variant)
import drjit as dr
import mitsuba as mi

from mi_nerfpp.core import geometry as geo
from mi_nerfpp.core import sampling
from mi_nerfpp.core.rays import Rays
from mi_nerfpp.core.render import (INFINITE_DELTA, MAX_DEPTH_RADIUS, Background, Foreground,
                                   RenderOptions, Sampling, Shading, composite, quadrature,
                                   render_rays, render_volume)
from mi_nerfpp.core.sampling import PDF_EPSILON, flat_index, stratified
from tests.helpers import AnalyticField


# ----------------------------------------------------------------------------- helpers

def F(a):
    return mi.Float(np.asarray(a, dtype=np.float32).ravel())


def npf(x, n=None):
    a = np.asarray(x, dtype=np.float64).ravel()
    return a if n is None else a.reshape(-1, n)


def rays(n_rays, seed=0, r_max=0.9):
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n_rays, 3))
    o *= r_max * rng.uniform(size=(n_rays, 1)) ** (1 / 3) / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.normal(size=(n_rays, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return (mi.Point3f(*[F(o[:, i]) for i in range(3)]),
            mi.Vector3f(*[F(d[:, i]) for i in range(3)]))


def constant_field(sigma, rgb):
    return AnalyticField(sigma, rgb)


def const_inputs(n_total, sigma, rgb):
    return constant_field(sigma, rgb)([dr.zeros(mi.Float, n_total)], None, None)


def np_quadrature(v, sigma, hi, infinite_last=False, scale=1.0):
    """float64 reference quadrature for one ray: weights of sorted samples ``v``."""
    delta = np.append(np.diff(v), hi - v[-1]) * scale
    if infinite_last:
        delta[-1] = INFINITE_DELTA
    alpha = 1.0 - np.exp(-sigma * delta)
    trans = np.concatenate([[1.0], np.cumprod(1.0 - alpha)[:-1]])
    return trans * alpha, np.prod(1.0 - alpha)


def uniform_depth(a, h, n, last_delta, sigma):
    """Closed-form depth Σ w_i v_i for constant σ on samples v_i = a + i·h (i < n), where every
    interval is h except the last one, ``last_delta``."""
    q = np.exp(-sigma * h)
    m = n - 1
    s0 = (1 - q ** m) / (1 - q)
    s1 = q * (1 - m * q ** (m - 1) + (m - 1) * q ** m) / (1 - q) ** 2
    return (1 - q) * (a * s0 + h * s1) + q ** m * (1 - np.exp(-sigma * last_delta)) * (a + m * h)


# ----------------------------------------------------------------------------- foreground

N_RAYS = 64


@pytest.fixture(scope='module')
def fg():
    o, d = rays(N_RAYS)
    return Foreground(Rays(o, d))


@pytest.mark.parametrize('n', [1, 2, 7, 64])
@pytest.mark.parametrize('sigma', [0.05, 1.0, 6.0])
def test_constant_density_with_first_sample_at_t0_is_exact(fg, n, sigma):
    """ξ = 0: samples at strata starts, the intervals tile [t0, t1]: opacity = 1 - exp(-σL)."""
    c = (0.2, 0.5, 0.9)
    v = stratified(fg.lo, fg.hi, n, dr.zeros(mi.Float, N_RAYS * n))
    s, rgb = const_inputs(N_RAYS * n, sigma, c)
    shading, w = quadrature(fg, v, s, rgb, n)
    L = npf(fg.hi) - npf(fg.lo)
    opacity = 1.0 - np.exp(-sigma * L)
    np.testing.assert_allclose(npf(shading.opacity), opacity, atol=1e-5)
    np.testing.assert_allclose(npf(shading.rgb, N_RAYS), np.outer(c, opacity), atol=1e-5)
    np.testing.assert_allclose(npf(w, n).sum(axis=1), npf(shading.opacity), atol=1e-6)
    h = L / n
    depth = (uniform_depth(npf(fg.lo), h, n, h, sigma) if n > 1
             else npf(fg.lo) * opacity)
    np.testing.assert_allclose(npf(shading.depth), depth, atol=2e-5)


@pytest.mark.parametrize('n', [1, 3, 16, 64])
@pytest.mark.parametrize('sigma', [0.05, 1.0, 6.0])
def test_constant_density_at_midpoints(fg, n, sigma):
    """Midpoint strata: intervals h, …, h, h/2 from v_0 = t0 + h/2 (closed forms)."""
    c = (1.0, 0.25, 0.0)
    v = stratified(fg.lo, fg.hi, n)
    s, rgb = const_inputs(N_RAYS * n, sigma, c)
    shading, w = quadrature(fg, v, s, rgb, n)
    L = npf(fg.hi) - npf(fg.lo)
    h = L / n
    opacity = 1.0 - np.exp(-sigma * (L - h / 2))
    np.testing.assert_allclose(npf(shading.opacity), opacity, atol=1e-5)
    np.testing.assert_allclose(npf(shading.rgb, N_RAYS), np.outer(c, opacity), atol=1e-5)
    if n > 1:
        depth = uniform_depth(npf(fg.lo) + h / 2, h, n, h / 2, sigma)
    else:
        depth = (npf(fg.lo) + h / 2) * opacity
    np.testing.assert_allclose(npf(shading.depth), depth, atol=2e-5)


def test_depth_limits(fg):
    n = 32
    v = stratified(fg.lo, fg.hi, n)
    v0 = npf(v, n)[:, 0]
    # Opaque: everything stops at the first sample.
    shading, _ = quadrature(fg, v, *const_inputs(N_RAYS * n, 1e5, (1, 1, 1)), n)
    np.testing.assert_allclose(npf(shading.depth), v0, atol=1e-5)
    np.testing.assert_allclose(npf(shading.opacity), 1.0, atol=1e-6)
    # Nearly transparent: depth / opacity is the δ-weighted mean sample position.
    shading, _ = quadrature(fg, v, *const_inputs(N_RAYS * n, 1e-4, (1, 1, 1)), n)
    vv = npf(v, n)
    delta = np.concatenate([np.diff(vv, axis=1), npf(fg.hi)[:, None] - vv[:, -1:]], axis=1)
    mean = np.sum(delta * vv, axis=1) / np.sum(delta, axis=1)
    np.testing.assert_allclose(npf(shading.depth) / npf(shading.opacity), mean, rtol=2e-3)
    # Zero density: nothing.
    shading, w = quadrature(fg, v, *const_inputs(N_RAYS * n, 0.0, (1, 1, 1)), n)
    assert np.all(npf(shading.opacity) == 0) and np.all(npf(w) == 0)


def test_weights_transmittance_and_sums_for_varying_density(fg):
    """Random σ_i, c_i and jittered samples: w_i = Π_{j<i}(1-α_j)·α_i, C = Σ w c,
    opacity = Σ w, depth = Σ w t, and λ = 1 - opacity = Π (1-α_j)."""
    n = 24
    rng = np.random.default_rng(5)
    v = stratified(fg.lo, fg.hi, n, F(rng.uniform(size=N_RAYS * n)))
    sigma = rng.exponential(3.0, size=N_RAYS * n) * (rng.uniform(size=N_RAYS * n) < 0.6)
    col = rng.uniform(size=(3, N_RAYS * n))
    shading, w = quadrature(fg, v, F(sigma), mi.Color3f(*[F(c) for c in col]), n)
    vv, hi = npf(v, n), npf(fg.hi)
    sig = sigma.astype(np.float32).astype(np.float64).reshape(N_RAYS, n)
    cc = col.astype(np.float32).astype(np.float64).reshape(3, N_RAYS, n)
    w_np = npf(w, n)
    for r in range(N_RAYS):
        w_ref, lam = np_quadrature(vv[r], sig[r], hi[r])
        np.testing.assert_allclose(w_np[r], w_ref, atol=2e-6)
        np.testing.assert_allclose(1.0 - npf(shading.opacity)[r], lam, atol=2e-6)
    np.testing.assert_allclose(npf(shading.opacity), w_np.sum(axis=1), atol=2e-6)
    np.testing.assert_allclose(npf(shading.rgb, N_RAYS), np.sum(w_np * cc, axis=2), atol=2e-6)
    np.testing.assert_allclose(npf(shading.depth), np.sum(w_np * vv, axis=1), atol=5e-6)
    assert np.all(w_np >= 0) and np.all(npf(shading.opacity) <= 1 + 1e-6)


def test_empty_foreground_contributes_nothing():
    # Outside origin moving away: t1 == t0, all intervals have zero length.
    o = mi.Point3f(F([2.0]), F([0.0]), F([0.0]))
    d = mi.Vector3f(F([1.0]), F([0.0]), F([0.0]))
    vol = Foreground(Rays(o, d))
    out = render_volume(vol, constant_field(50.0, (1, 1, 1)), 8, 8)
    for sh in (out.shading,):
        assert npf(sh.opacity)[0] == 0 and np.all(npf(sh.rgb) == 0) and npf(sh.depth)[0] == 0


# ----------------------------------------------------------------------------- background

@pytest.fixture(scope='module')
def bg_inside():
    o, d = rays(N_RAYS, seed=1)
    return Background(Rays(o, d)), o, d


@pytest.mark.parametrize('sigma', [1e-3, 0.5, 20.0])
def test_background_is_opaque_for_positive_density(bg_inside, sigma):
    bg, _, _ = bg_inside
    n = 16
    v = stratified(bg.lo, bg.hi, n)
    c = (0.3, 0.6, 0.1)
    shading, w = quadrature(bg, v, *const_inputs(N_RAYS * n, sigma, c), n)
    np.testing.assert_allclose(npf(shading.opacity), 1.0, atol=1e-6)
    np.testing.assert_allclose(npf(shading.rgb, N_RAYS), np.outer(c, np.ones(N_RAYS)), atol=1e-6)
    # Before the last (infinite) interval the light decays as exp(-σ Δs), Δs in inverse radius.
    ww = npf(w, n)
    s = 1.0 - npf(v, n)                                     # s_max = 1 for inside origins
    np.testing.assert_allclose(1.0 - ww[:, :-1].sum(axis=1), np.exp(-sigma * (s[:, 0] - s[:, -1])),
                               atol=2e-6)
    # Zero density: a transparent background.
    shading, _ = quadrature(bg, v, *const_inputs(N_RAYS * n, 0.0, c), n)
    assert np.all(npf(shading.opacity) == 0)


def test_background_weights_scale_with_s_max_for_outside_origins():
    """Origins outside the sphere moving away: s ∈ (0, 1/|o|], δ measured in s."""
    rng = np.random.default_rng(7)
    o = rng.normal(size=(20, 3))
    o *= rng.uniform(1.5, 4.0, size=(20, 1)) / np.linalg.norm(o, axis=1, keepdims=True)
    d = o / np.linalg.norm(o, axis=1, keepdims=True)
    P = mi.Point3f(*[F(o[:, i]) for i in range(3)])
    D = mi.Vector3f(*[F(d[:, i]) for i in range(3)])
    bg = Background(Rays(P, D))
    s_max = npf(bg.s_max)
    np.testing.assert_allclose(s_max, 1.0 / np.linalg.norm(o, axis=1), rtol=2e-6)
    n, sigma = 12, 4.0
    v = stratified(bg.lo, bg.hi, n, F(rng.uniform(size=20 * n)))
    shading, w = quadrature(bg, v, *const_inputs(20 * n, sigma, (1, 1, 1)), n)
    vv, ww = npf(v, n), npf(w, n)
    for r in range(20):
        w_ref, _ = np_quadrature(vv[r], np.full(n, sigma), 1.0, infinite_last=True, scale=s_max[r])
        np.testing.assert_allclose(ww[r], w_ref, atol=2e-6)
    # Rays along the radius: depth of a sample is t(s) = 1/s - |o|.
    ray, _ = flat_index(20, n)
    s = npf(bg.s(ray, v), n)
    np.testing.assert_allclose(s, s_max[:, None] * (1 - vv), rtol=1e-6)
    t = np.where(s >= 1 / MAX_DEPTH_RADIUS, 1 / np.maximum(s, 1 / MAX_DEPTH_RADIUS), MAX_DEPTH_RADIUS)
    t -= np.linalg.norm(o, axis=1)[:, None]
    np.testing.assert_allclose(npf(shading.depth), np.sum(ww * t, axis=1), rtol=1e-4)


def test_background_depth(bg_inside):
    bg, o, d = bg_inside
    t_b, _, b = geo.closest_approach(o, d)
    t_b, b = npf(t_b), npf(b)
    t = lambda s: t_b + np.sqrt(1 / s ** 2 - b ** 2)  # noqa: E731
    # Opaque at the first sample: depth = t(s_0).
    n = 8
    v = stratified(bg.lo, bg.hi, n)
    shading, _ = quadrature(bg, v, *const_inputs(N_RAYS * n, 1e6, (1, 1, 1)), n)
    s0 = 1.0 - 0.5 / n
    np.testing.assert_allclose(npf(shading.depth), t(s0), rtol=1e-5)
    # Only the last sample is dense and it sits beyond MAX_DEPTH_RADIUS: depth is clamped there.
    v = F(np.tile([0.25, 0.9999], N_RAYS))
    sigma = F(np.tile([0.0, 1.0], N_RAYS))
    shading, _ = quadrature(bg, v, sigma, mi.Color3f(dr.full(mi.Float, 1.0, 2 * N_RAYS)), 2)
    np.testing.assert_allclose(npf(shading.opacity), 1.0, atol=1e-6)
    np.testing.assert_allclose(npf(shading.depth), t(1.0 / MAX_DEPTH_RADIUS), rtol=1e-5)


# ----------------------------------------------------------------------------- composite

def test_composite_eq4():
    rng = np.random.default_rng(9)
    n = 50
    def shading():  # noqa: E306
        return Shading(rgb=mi.Color3f(*[F(rng.uniform(size=n)) for _ in range(3)]),
                       opacity=F(rng.uniform(size=n)), depth=F(rng.uniform(0, 10, size=n)))
    fg, bg = shading(), shading()
    out = composite(fg, bg)
    lam = 1.0 - npf(fg.opacity)
    np.testing.assert_allclose(npf(out.rgb, n), npf(fg.rgb, n) + lam * npf(bg.rgb, n), atol=1e-6)
    np.testing.assert_allclose(npf(out.opacity), npf(fg.opacity) + lam * npf(bg.opacity), atol=1e-6)
    np.testing.assert_allclose(npf(out.depth), npf(fg.depth) + lam * npf(bg.depth), atol=1e-5)
    assert composite(fg, None) is fg


def test_render_rays_constant_fields_composite():
    """Constant foreground (σ, c_fg) and opaque background c_bg: C = α c_fg + (1-α) c_bg."""
    o, d = rays(40, seed=11)
    c_fg, c_bg = np.array([0.9, 0.1, 0.2]), np.array([0.1, 0.4, 0.8])
    res = render_rays(Rays(o, d), constant_field(2.0, c_fg), constant_field(0.7, c_bg),
                      Sampling(fg_samples=16, bg_samples=16, fine_samples=32))
    fg, full = res.fg.shading, res.composite
    alpha = npf(fg.opacity)
    assert np.all((alpha > 0.05) & (alpha < 1))
    np.testing.assert_allclose(npf(fg.rgb, 40), np.outer(c_fg, alpha), atol=1e-5)
    np.testing.assert_allclose(npf(full.opacity), 1.0, atol=1e-6)
    np.testing.assert_allclose(npf(full.rgb, 40), np.outer(c_fg, alpha) + np.outer(c_bg, 1 - alpha),
                               atol=1e-5)


# ----------------------------------------------------------------------------- hierarchical

def np_render_volume(lo, hi, sigma_fn, n_c, n_f, xi_c=None, xi_f=None):
    """Independent float64 reference of one foreground ray's coarse + fine passes."""
    k = np.arange(n_c)
    v_c = lo + (k + (0.5 if xi_c is None else xi_c)) / n_c * (hi - lo)
    v_c = v_c.astype(np.float32).astype(np.float64)
    w_c, _ = np_quadrature(v_c, sigma_fn(v_c), hi)
    mids = 0.5 * (v_c[1:] + v_c[:-1])
    edges = np.concatenate([[lo], mids, [hi]])
    p = w_c + PDF_EPSILON
    cdf = np.concatenate([[0], np.cumsum(p) / p.sum()])
    u = (np.arange(n_f) + (0.5 if xi_f is None else xi_f)) / n_f
    v_f = np.interp(u, cdf, edges)
    v = np.sort(np.concatenate([v_c, v_f]))
    w, lam = np_quadrature(v, sigma_fn(v), hi)
    return v, w, lam


@pytest.mark.parametrize('seeded', [False, True])
def test_render_volume_fine_pass_constant_density(seeded):
    n_rays, n_c, n_f, sigma = 24, 16, 32, 3.0
    c = (0.4, 0.7, 0.2)
    o, d = rays(n_rays, seed=12)
    seed = mi.UInt32(np.arange(n_rays, dtype=np.uint32) * 31 + 5) if seeded else None
    vol = Foreground(Rays(o, d, seed=seed))
    out = render_volume(vol, constant_field(sigma, c), n_c, n_f, stream=0)
    lo, hi = npf(vol.lo), npf(vol.hi)
    xi_c = npf(sampling.uniforms(seed, n_c, 0), n_c) if seeded else [None] * n_rays
    xi_f = npf(sampling.uniforms(seed, n_f, 1), n_f) if seeded else [None] * n_rays
    for r in range(n_rays):
        v, w, lam = np_render_volume(lo[r], hi[r], lambda t: np.full(t.shape, sigma),
                                     n_c, n_f, xi_c[r], xi_f[r])
        # Closed form for constant σ: the merged intervals telescope from the first sample.
        alpha = 1.0 - np.exp(-sigma * (hi[r] - v[0]))
        assert np.isclose(1.0 - lam, alpha)
        assert npf(out.shading.opacity)[r] == pytest.approx(alpha, abs=1e-5)
        np.testing.assert_allclose(npf(out.shading.rgb, n_rays)[:, r], np.multiply(c, alpha), atol=1e-5)
        # Depth depends on every interval: only right if the merged samples are in order.
        assert npf(out.shading.depth)[r] == pytest.approx(np.sum(w * v), abs=1e-4)
        # (The coarse pass only places samples: its weights are checked through the merged
        # sample positions of the reference, which the fine samples follow.)
        assert npf(out.distance, n_c + n_f)[r] == pytest.approx(v, abs=1e-5)


def test_render_volume_fine_pass_varying_density():
    """A density shell (σ only for 0.3 < |x| < 0.6): fine pass equals the float64 reference."""
    n_rays, n_c, n_f = 16, 24, 48
    o, d = rays(n_rays, seed=13)

    def shell(x, d, ray):
        r2 = dr.square(x[0]) + dr.square(x[1]) + dr.square(x[2])
        sigma = dr.select((r2 > 0.09) & (r2 < 0.36), 8.0, 0.0)
        return sigma, mi.Color3f(dr.sqrt(r2), 0.5, 1.0 - dr.sqrt(r2))

    vol = Foreground(Rays(o, d))
    out = render_volume(vol, shell, n_c, n_f)
    lo, hi = npf(vol.lo), npf(vol.hi)
    on, dn = npf(o, n_rays).T, npf(d, n_rays).T
    for r in range(n_rays):
        radius = lambda t: np.linalg.norm(on[r] + t[:, None] * dn[r], axis=1)  # noqa: E731
        sig = lambda t: np.where((radius(t) > 0.3) & (radius(t) < 0.6), 8.0, 0.0)  # noqa: E731
        v, w, lam = np_render_volume(lo[r], hi[r], sig, n_c, n_f)
        assert npf(out.shading.opacity)[r] == pytest.approx(1 - lam, abs=1e-4)
        assert npf(out.shading.rgb, n_rays)[0, r] == pytest.approx(np.sum(w * radius(v)), abs=1e-4)
        assert npf(out.shading.depth)[r] == pytest.approx(np.sum(w * v), abs=2e-4)


def test_distortion_loss_matches_pairwise_definition():
    from mi_nerfpp.training.priors import distortion
    rng = np.random.default_rng(3)
    n_rays, n = 7, 9
    m = np.sort(rng.uniform(0, 1, (n_rays, n)), axis=1)
    w = rng.uniform(0, 0.2, (n_rays, n))
    got = np.array(distortion(F(w.ravel()), F(m.ravel()), n))
    delta = np.concatenate([np.diff(m, axis=1), 1 - m[:, -1:]], axis=1)
    ref = (np.abs(m[:, :, None] - m[:, None, :]) * w[:, :, None] * w[:, None, :]).sum((1, 2)) \
        + (w ** 2 * delta).sum(1) / 3
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-7)
    # Concentrating the same total weight in one sample lowers it.
    w1 = np.zeros((1, n))
    w1[0, 4] = 0.9
    spread = np.full((1, n), 0.1)
    assert np.array(distortion(F(w1.ravel()), F(m[0]), n))[0] < \
        np.array(distortion(F(spread.ravel()), F(m[0]), n))[0]


def _pairwise_distortion(w, m):
    """float64 reference: mip-NeRF 360's distortion of sorted positions ``m`` (rays × n)."""
    delta = np.concatenate([np.diff(m, axis=1), 1 - m[:, -1:]], axis=1)
    return (np.abs(m[:, :, None] - m[:, None, :]) * w[:, :, None] * w[:, None, :]).sum((1, 2)) \
        + (w ** 2 * delta).sum(1) / 3


def test_ray_distortion_puts_both_volumes_on_one_axis():
    """The whole-ray distortion equals the pairwise definition over the foreground samples at
    m/2 (weights w_fg) followed by the background samples at ½ + m/2 (weights λ·w_bg), and it
    penalizes a ray whose weight is split between the volumes more than one that either
    volume owns."""
    from mi_nerfpp.core.render import RenderResult, VolumeRender
    from mi_nerfpp.training.priors import ray_distortion
    rng = np.random.default_rng(5)
    n_rays, n_fg, n_bg = 6, 5, 4

    def result(w_fg, w_bg, m_fg, m_bg):
        alpha = w_fg.sum(1)
        fg = VolumeRender(Shading(None, F(alpha), None), F(w_fg), F(m_fg), n_fg)
        bg = VolumeRender(None, F(w_bg), F(m_bg), n_bg)
        return RenderResult(fg, bg, None), alpha

    m_fg = np.sort(rng.uniform(0, 1, (n_rays, n_fg)), axis=1)
    m_bg = np.sort(rng.uniform(0, 1, (n_rays, n_bg)), axis=1)
    w_fg = rng.dirichlet(np.ones(n_fg), n_rays) * rng.uniform(0, 1, (n_rays, 1))
    w_bg = rng.dirichlet(np.ones(n_bg), n_rays)
    res, alpha = result(w_fg, w_bg, m_fg, m_bg)
    ref = _pairwise_distortion(np.concatenate([w_fg, (1 - alpha)[:, None] * w_bg], axis=1),
                               np.concatenate([0.5 * m_fg, 0.5 + 0.5 * m_bg], axis=1))
    np.testing.assert_allclose(np.array(ray_distortion(res)), ref, rtol=1e-5, atol=1e-7)

    # One surface per volume (a sample each): all in the foreground, all in the background,
    # or half and half.
    one = np.zeros((3, n_fg))
    one[:, 2] = [1.0, 0.0, 0.5]
    other = np.zeros((3, n_bg))
    other[:, 1] = 1.0
    split, _ = result(one, other, m_fg[:3], m_bg[:3])
    loss = np.array(ray_distortion(split))
    assert loss[2] > 3 * max(loss[0], loss[1]), loss


def test_ray_distortion_gradient_matches_finite_differences():
    """d/dθ of the whole-ray distortion of a rendered batch, where θ scales the foreground's
    density (so it moves weight between the volumes through λ), against central differences."""
    from mi_nerfpp.training.priors import ray_distortion
    o, d = rays(64, seed=9)
    seed = mi.UInt32(np.arange(64, dtype=np.uint32))
    bg = AnalyticField(lambda x: 2.0 + 3.0 * x[3], (0.2, 0.3, 0.4))

    def loss(theta):
        fg = AnalyticField(lambda x: theta * dr.exp(-4.0 * (dr.square(x[0]) + dr.square(x[1]))),
                           (1.0, 0.5, 0.0))
        return dr.mean(ray_distortion(render_rays(Rays(o, d, seed=seed), fg, bg,
                                                  Sampling(16, 16, 16))))

    theta = mi.Float(1.5)
    dr.enable_grad(theta)
    value = loss(theta)
    dr.backward(value)
    eps = 1e-2
    fd = (loss(mi.Float(1.5 + eps)).array[0] - loss(mi.Float(1.5 - eps)).array[0]) / (2 * eps)
    assert abs(fd) > 1e-3
    assert np.array(dr.grad(theta))[0] == pytest.approx(fd, rel=2e-2)


def test_skipping_the_occluded_background_changes_the_composite_by_at_most_its_threshold():
    """Early termination between the volumes: rays whose foreground transmittance λ is below
    OCCLUDED_TRANSMITTANCE get no background; the composite moves by at most λ·C_bg ≤ 1e-4
    (colours ≤ 1), and rays that see the background render it exactly as before."""
    from mi_nerfpp.core.render import OCCLUDED_TRANSMITTANCE

    half_opaque = AnalyticField(               # opaque for x > 0, clear elsewhere
        lambda x: dr.select(x[0] > 0.0, 200.0, 0.0),
        lambda x: [dr.full(mi.Float, c, dr.width(x[0])) for c in (1, 0, 0)])

    o, d = rays(256, seed=3)
    sampling = Sampling(32, 16, 16)
    bg_field = constant_field(0.7, (0.1, 0.9, 1.0))
    full = render_rays(Rays(o, d), half_opaque, bg_field, sampling)
    skip = render_rays(Rays(o, d), half_opaque, bg_field, sampling,
                       RenderOptions(skip_occluded=True))
    lam = 1.0 - npf(full.fg.shading.opacity)
    occluded = lam <= OCCLUDED_TRANSMITTANCE
    assert 0.1 < occluded.mean() < 0.9
    np.testing.assert_allclose(npf(skip.composite.rgb, 256), npf(full.composite.rgb, 256), atol=OCCLUDED_TRANSMITTANCE)
    assert (npf(skip.bg.shading.rgb, 256)[:, occluded] == 0).all()
    np.testing.assert_allclose(npf(skip.bg.shading.rgb, 256)[:, ~occluded],
                               npf(full.bg.shading.rgb, 256)[:, ~occluded], atol=1e-6)
    # All rays occluded: no background is rendered at all.
    o_in = mi.Point3f(0.5, 0.0, 0.0)
    none = render_rays(Rays(o_in, mi.Vector3f(1, 0, 0)), half_opaque, bg_field, sampling,
                       RenderOptions(skip_occluded=True))
    assert npf(none.bg.shading.opacity)[0] == 0.0


def test_early_termination_within_a_volume_changes_the_composite_by_at_most_its_threshold():
    """Primal renders evaluate colour only where a sample can show (``visible_only``): not
    behind an opaque slab (transmittance below HIDDEN_WEIGHT / 2) and not where the weight is
    negligible. On a known density - thin haze, then an opaque slab at x in [-0.1, 0.1] - the
    composite moves by less than HIDDEN_WEIGHT, opacity and depth stay exact, and most samples
    behind the slab are never shaded."""
    from mi_nerfpp.core.render import HIDDEN_WEIGHT

    field = AnalyticField(
        lambda x: dr.select(dr.abs(x[0]) < 0.1, 300.0, 0.01),
        lambda x: [0.5 + 0.5 * dr.sin(7.0 * x[0]), 0.5 + 0.5 * dr.cos(5.0 * x[1]),
                   0.5 + 0.5 * dr.sin(3.0 * x[2] + 1.0)], record=True)
    n_rays, n_c, n_f = 512, 32, 32
    o = mi.Point3f(dr.full(mi.Float, -0.95, n_rays), F(np.linspace(-0.3, 0.3, n_rays)), 0.0)
    d = mi.Vector3f(1.0, 0.0, 0.0)
    seed = mi.UInt32(np.arange(n_rays, dtype=np.uint32))
    full = render_volume(Foreground(Rays(o, d, seed=seed)), field, n_c, n_f)
    field.shaded, field.shaded_x = 0, []
    lazy = render_volume(Foreground(Rays(o, d, seed=seed)), field, n_c, n_f,
                         RenderOptions(skip_occluded=True))
    # Nothing behind the front half of the slab is shaded (the transmittance there is below
    # exp(-300·0.1)); about half of all samples lie behind it.
    assert np.concatenate(field.shaded_x).max() < 0.0
    assert field.shaded < 0.6 * n_rays * (n_c + n_f), field.shaded
    assert npf(full.shading.opacity).min() > 0.999           # every ray meets the slab
    np.testing.assert_allclose(npf(lazy.shading.rgb, n_rays), npf(full.shading.rgb, n_rays),
                               rtol=0, atol=HIDDEN_WEIGHT)
    np.testing.assert_allclose(npf(lazy.shading.opacity), npf(full.shading.opacity), rtol=1e-6)
    np.testing.assert_allclose(npf(lazy.shading.depth), npf(full.shading.depth), rtol=1e-6)
    np.testing.assert_allclose(npf(lazy.weights), npf(full.weights), rtol=1e-6, atol=1e-9)
    # render_rays uses it for primal renders (skip_occluded) in both volumes: each volume's
    # skipped samples and the skipped occluded background add at most their thresholds.
    from mi_nerfpp.core.render import OCCLUDED_TRANSMITTANCE
    bg = constant_field(0.7, (0.1, 0.9, 1.0))
    o2, d2 = rays(256, seed=4)
    a = render_rays(Rays(o2, d2), field, bg, Sampling(32, 16, 16))
    b = render_rays(Rays(o2, d2), field, bg, Sampling(32, 16, 16),
                    RenderOptions(skip_occluded=True))
    np.testing.assert_allclose(npf(b.composite.rgb, 256), npf(a.composite.rgb, 256), rtol=0,
                               atol=2 * HIDDEN_WEIGHT + OCCLUDED_TRANSMITTANCE)


@pytest.mark.parametrize('domain', ['ball', 'inverted_sphere'])
def test_early_termination_of_a_grid_field_colours_the_features_its_passes_kept(domain):
    """A grid field with per-sample colour looks its grids up once per sample in a primal
    render (``skip_occluded``): the features come with the densities of both passes, and the
    shown samples only run the colour network on them. The composite is the full render's
    within HIDDEN_WEIGHT, opacity and depth exactly, and the field takes exactly two lookups
    (the coarse and the fine pass), not a third at the shown samples."""
    from mi_nerfpp.core.fields import grid_field
    from mi_nerfpp.core.render import HIDDEN_WEIGHT
    field = grid_field(domain, resolutions=(8, 16), color='sample', init=1.0, density_bias=0.0,
                       seed=3)
    lookups = []
    lookup = field._lookup
    field._lookup = lambda x, width=None: (lookups.append(dr.width(x[0])), lookup(x, width))[1]
    n_rays, n_c, n_f = 256, 16, 8
    o, d = rays(n_rays, seed=5)
    seed = mi.UInt32(np.arange(n_rays, dtype=np.uint32))
    ray_batch = Rays(o, d, seed=seed)
    volume = ((lambda: Foreground(ray_batch)) if domain == 'ball'
              else (lambda: Background(ray_batch)))
    skip = RenderOptions(skip_occluded=True)
    full = render_volume(volume(), field, n_c, n_f)
    lookups.clear()
    lazy = render_volume(volume(), field, n_c, n_f, skip)
    assert lookups == [n_rays * n_c, n_rays * n_f]
    assert npf(full.shading.opacity).max() > 0.5       # a field that shows
    np.testing.assert_allclose(npf(lazy.shading.rgb, n_rays), npf(full.shading.rgb, n_rays),
                               rtol=0, atol=HIDDEN_WEIGHT)
    np.testing.assert_allclose(npf(lazy.shading.opacity), npf(full.shading.opacity), rtol=1e-6)
    np.testing.assert_allclose(npf(lazy.shading.depth), npf(full.shading.depth), rtol=1e-6)
    # The same through the linear-radiance wrapper of an sRGB model (how renders see it).
    from mi_nerfpp.core.model import LinearRadiance
    lookups.clear()
    linear = render_volume(volume(), LinearRadiance(field), n_c, n_f, skip)
    assert lookups == [n_rays * n_c, n_rays * n_f]
    np.testing.assert_allclose(npf(linear.shading.opacity), npf(full.shading.opacity), rtol=1e-6)


def test_scale_gradient_keeps_the_value_and_scales_the_gradient():
    from mi_nerfpp.core.render import scale_gradient
    x = mi.Float(0.3, -1.2, 2.5)
    s = mi.Float(0.25, 1.0, 0.0)
    dr.enable_grad(x)
    y = scale_gradient(dr.square(x), s)
    assert np.array_equal(np.array(y), np.array(dr.square(dr.detach(x))))
    dr.backward(dr.sum(y))
    assert np.allclose(np.array(dr.grad(x)), 2 * np.array([0.3, -1.2, 2.5]) * np.array(s))


def test_near_gradient_scales_each_sample_by_its_squared_distance():
    """Floaters No More: ``near_gradient=R`` leaves the image unchanged and multiplies the
    gradient of each sample at distance t < R by (t/R)². With R beyond every sample, all of
    them are scaled, so doubling R quarters the gradient exactly; with R below every sample
    (strata midpoints, none closer than half a stratum) the gradient is unchanged."""
    o, d = rays(32, seed=4)

    def render(theta, radius):
        fg = AnalyticField(lambda x: theta * (1.0 + dr.square(x[0])),
                           lambda x: mi.Color3f(theta * (0.2 + 0.1 * x[0]), 0.5 + 0.1 * x[1], theta * x[2]))
        return render_rays(Rays(o, d), fg, None, Sampling(8, 8, 8),
                           RenderOptions(near_gradient=radius))

    grads, images = [], []
    for radius in (0.0, 1e-4, 4.0, 8.0):
        theta = mi.Float(0.7)
        dr.enable_grad(theta)
        res = render(theta, radius)
        loss = dr.mean(res.composite.rgb.x + res.composite.rgb.z + res.fg.shading.rgb.y + res.composite.opacity)
        dr.backward(loss)
        grads.append(np.array(dr.grad(theta))[0])
        images.append(np.array(dr.detach(res.composite.rgb)))
    for image in images[1:]:
        assert np.array_equal(image, images[0])
    assert abs(grads[0]) > 1e-3
    assert grads[1] == pytest.approx(grads[0], rel=1e-6)
    assert grads[3] == pytest.approx(grads[2] / 4, rel=1e-5)
    assert 0 < grads[2] < grads[0]


# ----------------------------------------------------------------------------- deferred colour

class AffineColorField:
    """Closed-form density, two features per sample, and a colour that is affine in the
    features: ``c(F, d) = A·F + b(d)``. With ``deferred`` it composites the features and
    colours each ray once (the grid field's path); without, it colours every sample."""

    A = np.array([[0.7, -0.2], [0.1, 0.5], [-0.3, 0.4]])

    def __init__(self, deferred):
        self.deferred = deferred

    def density(self, x):
        return 2.0 + 6.0 * dr.square(x[0])

    def _features(self, x):
        return [0.5 + 0.4 * dr.sin(3.0 * x[0] + x[1]), 0.2 + 0.3 * dr.cos(2.0 * x[2] - x[1])]

    def _bias(self, d):
        return [0.1 + 0.05 * d.x, 0.2 - 0.1 * d.y, 0.05 * d.z]

    def features(self, x):
        return self.density(x), self._features(x)

    def color(self, f, d):
        b = self._bias(d)
        # (Python floats: a NumPy scalar times a Dr.Jit array would become a NumPy array.)
        A = self.A.tolist()
        return mi.Color3f(*[A[i][0] * f[0] + A[i][1] * f[1] + b[i] for i in range(3)])

    def __call__(self, x, d, ray):
        return self.density(x), self.color(self._features(x), dr.gather(mi.Vector3f, d, ray))


def test_deferred_and_per_sample_colour_agree_for_an_affine_colour_network():
    """``α·c(Σw f/α, d) = Σ w c(f, d)`` when c is affine in f: both volumes, jittered samples."""
    o, d = rays(64, seed=21)
    seed = mi.UInt32(np.arange(64, dtype=np.uint32) * 7 + 3)
    out = {}
    for deferred in (False, True):
        out[deferred] = render_rays(Rays(o, d, seed=seed), AffineColorField(deferred),
                                    AffineColorField(deferred), Sampling(12, 12, 12))
    for name in ('fg', 'bg'):
        a, b = getattr(out[False], name).shading, getattr(out[True], name).shading
        assert npf(a.opacity).min() > 0.05
        np.testing.assert_allclose(npf(b.rgb, 64), npf(a.rgb, 64), rtol=0, atol=1e-5)
        np.testing.assert_array_equal(npf(b.opacity), npf(a.opacity))
    np.testing.assert_allclose(npf(out[True].composite.rgb, 64), npf(out[False].composite.rgb, 64),
                               rtol=0, atol=1e-5)


def test_deferred_grid_field_colours_the_composited_features_once_per_ray():
    """A grid field's volume colour is ``α·c(F/α, d)`` with ``F = Σ w_i f_i`` over its merged
    samples (float64 composite of the field's own features at the returned positions)."""
    from tests.helpers import TINY_GRID
    from mi_nerfpp.core.fields import grid_field
    field = grid_field('ball', **{k: v for k, v in TINY_GRID.items() if k != 'kind'},
                       density_bias=1.0, seed=3)
    assert field.deferred
    n_rays, n_c, n_f = 32, 8, 8
    o, d = rays(n_rays, seed=22)
    vol = Foreground(Rays(o, d))
    out = render_volume(vol, field, n_c, n_f)
    n = n_c + n_f
    ray, _ = flat_index(n_rays, n)
    sigma, feats = field.features(vol.inputs(ray, out.distance))
    w = npf(out.weights, n)
    f = np.stack([npf(c, n) for c in feats])                    # (channels, rays, n)
    F64 = (w[None] * f).sum(-1)
    alpha = w.sum(-1)
    assert alpha.min() > 0.01
    c = field.color([mi.Float(x.astype(np.float32)) for x in F64 / alpha], d)
    np.testing.assert_allclose(npf(out.shading.opacity), alpha, atol=1e-6)
    np.testing.assert_allclose(npf(out.shading.rgb, n_rays), npf(c, n_rays) * alpha, atol=2e-6)


@pytest.mark.parametrize('deferred', [False, True])
def test_gradients_through_the_merged_samples_match_finite_differences(deferred):
    """The merged samples' values reach the field through permutation gathers (their adjoints
    are plain scatters): the gradient of a render with fine samples equals central finite
    differences in a parameter θ that scales the features/colour and not the density (so the
    sample positions, which follow the density, do not move)."""
    o, d = rays(48, seed=23)
    seed = mi.UInt32(np.arange(48, dtype=np.uint32) * 5 + 1)
    w = mi.Float(np.random.default_rng(5).uniform(0.2, 1.0, 48).astype(np.float32))

    class Scaled(AffineColorField):
        def _features(self, x):
            return [self.theta * f for f in super()._features(x)]

    def loss(theta):
        field = Scaled(deferred)
        field.theta = theta
        res = render_rays(Rays(o, d, seed=seed), field, field, Sampling(10, 10, 10))
        return dr.sum(w * (res.composite.rgb.x + 2.0 * res.composite.rgb.y - res.composite.rgb.z))

    theta = mi.Float(0.8)
    dr.enable_grad(theta)
    value = loss(theta)
    dr.backward(value)
    grad = float(dr.grad(theta)[0])
    eps = 1e-2
    fd = (float(loss(mi.Float(0.8 + eps))[0]) - float(loss(mi.Float(0.8 - eps))[0])) / (2 * eps)
    assert abs(grad) > 0.1
    assert grad == pytest.approx(fd, rel=2e-3)


def _fused_and_wavefront(rays, fg_field, bg_field, sampling, options=RenderOptions()):
    from mi_nerfpp.core.render import surface_distance
    out = []
    for fused in (False, True):
        res = render_rays(rays, fg_field, bg_field, sampling,
                          dataclasses.replace(options, fused=fused))
        n = dr.width(res.composite.opacity)
        out.append({'rgb': npf(res.composite.rgb, n), 'opacity': npf(res.composite.opacity),
                    'depth': npf(res.composite.depth), 'fg': npf(res.fg.shading.rgb, n),
                    'fg_opacity': npf(res.fg.shading.opacity), 'fg_depth': npf(res.fg.shading.depth),
                    'surface': npf(surface_distance(res)), 'fused': res.fg.weights is None})
    assert not out[0]['fused'] and out[1]['fused']
    return out


@pytest.mark.parametrize('far', [False, True])
def test_fused_quadrature_matches_the_wavefront_quadrature(far):
    """The primal render's fused merge and quadrature (one loop per ray over both sample sets)
    gives the composite, depth and surface distance of the merged wavefront path, float32
    rounding apart: an opaque half-space in the foreground (surfaces to cross), a coloured
    background, hierarchical samples that interleave with ties, rays ending at ``far``."""
    opaque = AnalyticField(lambda x: dr.select(x[0] > 0.2, 40.0, 0.3),
                           lambda x: [0.5 + 0.4 * dr.sin(3.0 * c) for c in x[:3]])
    bg_field = AnalyticField(lambda x: 0.5 + 2.0 * dr.square(x[1]),
                             lambda x: [0.3 + 0.2 * c for c in x[:3]])
    n = 200
    o, d = rays(n, seed=11)
    ray_batch = Rays(o, d)
    if far:
        t = np.random.default_rng(2).uniform(0.2, 5.0, n)
        t[::3] = np.inf
        ray_batch.far = F(t)
    wave, fused = _fused_and_wavefront(ray_batch, opaque, bg_field, Sampling(16, 16, 8))
    assert 0.2 < (wave['fg_opacity'] > 0.99).mean() < 0.9
    _agree(fused, wave)


def _agree(fused, wave):
    for key in ('rgb', 'opacity', 'fg', 'fg_opacity', 'fg_depth', 'surface'):
        np.testing.assert_allclose(fused[key], wave[key], rtol=1e-5, atol=2e-6, err_msg=key)
    # The composite depth adds λ·(background depth): the rounding of a foreground opacity near
    # 1 (~1e-8 in λ) times the background's far samples (up to MAX_DEPTH_RADIUS).
    np.testing.assert_allclose(fused['depth'], wave['depth'], rtol=1e-5,
                               atol=1e-7 * MAX_DEPTH_RADIUS, err_msg='depth')


def test_fused_quadrature_matches_on_a_trained_model(tiny_run):
    """The same on a trained grid model (deferred colour, occupancy grids), with the occluded
    background skipped as the integrator renders it."""
    from mi_nerfpp.files.checkpoint import load_checkpoint
    model, _, _ = load_checkpoint(f'{tiny_run}/model.npz')
    o, d = rays(500, seed=5)
    wave, fused = _fused_and_wavefront(Rays(o, d), *model.radiance_fields(), Sampling(16, 16, 8),
                                       RenderOptions(occupancy=model.occupancy,
                                                     skip_occluded=True))
    _agree(fused, wave)
