"""Tests for sample placement (mi_nerfpp.core.sampling): strata, inverse-CDF fine samples, merging."""
from __future__ import annotations

import ast
import pathlib

import numpy as np
import pytest

import mi_nerfpp  # noqa: F401  (sets up libLLVM and the llvm_ad_rgb variant)
import drjit as dr
import mitsuba as mi

from mi_nerfpp.core import geometry as geo
from mi_nerfpp.core import sampling
from mi_nerfpp.core.rays import Rays
from mi_nerfpp.core.render import Background, quadrature
from mi_nerfpp.core.sampling import (PDF_EPSILON, bin_edges, gather_merged, inverse_cdf,
                                     merge_order, split_merged, stratified)


def F(a):
    return mi.Float(np.asarray(a, dtype=np.float32).ravel())


def npf(x, n=None):
    a = np.asarray(x, dtype=np.float64).ravel()
    return a if n is None else a.reshape(-1, n)


def segments(n_rays, seed=0):
    rng = np.random.default_rng(seed)
    lo = rng.uniform(0.0, 0.5, n_rays).astype(np.float32)
    hi = (lo + rng.uniform(0.2, 2.0, n_rays)).astype(np.float32)
    return lo.astype(np.float64), hi.astype(np.float64)


def coarse_midpoints(lo, hi, n):
    return F(lo), F(hi), stratified(F(lo), F(hi), n)


def fine_in_bins(v_f, left, right, n_c, n_f):
    """Per-ray count of fine samples in each coarse bin [left_k, right_k) (last bin closed)."""
    v_f, left, right = npf(v_f, n_f), npf(left, n_c), npf(right, n_c)
    counts = np.zeros(left.shape)
    for k in range(n_c):
        upper = v_f <= right[:, k:k + 1] if k == n_c - 1 else v_f < right[:, k:k + 1]
        counts[:, k] = np.sum((v_f >= left[:, k:k + 1]) & upper, axis=1)
    return counts


# ----------------------------------------------------------------------------- stratified

def test_stratified_midpoints():
    n = 16
    lo, hi = segments(50)
    v = npf(stratified(F(lo), F(hi), n), n)
    k = np.arange(n)
    expected = lo[:, None] + (k + 0.5) / n * (hi - lo)[:, None]
    np.testing.assert_allclose(v, expected, atol=2e-6)
    assert np.all(np.diff(v, axis=1) > 0)


def test_stratified_jitter_stays_in_its_stratum():
    n = 24
    lo, hi = segments(60, seed=1)
    rng = np.random.default_rng(2)
    xi = rng.uniform(size=60 * n)
    xi[:5] = 0.0                                 # stratum edges are reachable
    xi[5:10] = np.nextafter(np.float32(1), np.float32(0))
    v = npf(stratified(F(lo), F(hi), n, F(xi)), n)
    k = np.arange(n)
    width = (hi - lo)[:, None] / n
    start = lo[:, None] + k * width
    eps = 2e-6
    assert np.all(v >= start - eps) and np.all(v <= start + width + eps)
    np.testing.assert_allclose(v, start + xi.reshape(60, n) * width, atol=2e-6)
    assert np.all(np.diff(v, axis=1) >= 0)


def test_uniforms_are_reproducible_and_independent_per_stream():
    seed = mi.UInt32(np.arange(10, dtype=np.uint32) * 7919)
    a = npf(sampling.uniforms(seed, 8, 0))
    assert sampling.uniforms(None, 8, 0) is None
    np.testing.assert_array_equal(a, npf(sampling.uniforms(seed, 8, 0)))
    b = npf(sampling.uniforms(seed, 8, 1))
    assert np.all((a >= 0) & (a < 1)) and a.size == 80
    assert not np.any(a == b)
    assert len(np.unique(a)) == a.size


def test_uniforms_of_a_ray_do_not_depend_on_its_batch():
    # A render split into chunks must place each ray's samples as the whole frame would.
    seed = mi.UInt32(np.random.default_rng(5).integers(0, 2 ** 32, 12, dtype=np.uint64)
                     .astype(np.uint32))
    whole = npf(sampling.uniforms(seed, 8, 2), 8)
    first = npf(sampling.uniforms(mi.UInt32(np.array(seed)[:5]), 8, 2), 8)
    last = npf(sampling.uniforms(mi.UInt32(np.array(seed)[5:]), 8, 2), 8)
    np.testing.assert_array_equal(whole, np.concatenate([first, last]))
    # ...and rays with different seeds still get different variates
    assert len(np.unique(whole)) == whole.size


# ----------------------------------------------------------------------------- bin edges

def test_bin_edges_tile_the_segment():
    n = 12
    lo, hi = segments(40, seed=3)
    rng = np.random.default_rng(4)
    v = stratified(F(lo), F(hi), n, F(rng.uniform(size=40 * n)))
    left, right = bin_edges(v, F(lo), F(hi), n)
    left, right, vv = npf(left, n), npf(right, n), npf(v, n)
    np.testing.assert_allclose(left[:, 0], lo, atol=1e-6)
    np.testing.assert_allclose(right[:, -1], hi, atol=1e-6)
    np.testing.assert_allclose(left[:, 1:], right[:, :-1], atol=0)
    np.testing.assert_allclose(left[:, 1:], 0.5 * (vv[:, 1:] + vv[:, :-1]), atol=2e-6)
    assert np.all((left <= vv) & (vv <= right))


# ----------------------------------------------------------------------------- inverse CDF

def test_inverse_cdf_sorted_and_inside_segment():
    n_c, n_f, n_rays = 32, 64, 80
    lo, hi = segments(n_rays, seed=5)
    rng = np.random.default_rng(6)
    Lo, Hi = F(lo), F(hi)
    v_c = stratified(Lo, Hi, n_c, F(rng.uniform(size=n_rays * n_c)))
    w = F(rng.exponential(size=n_rays * n_c) * (rng.uniform(size=n_rays * n_c) < 0.3))
    for xi in (None, F(rng.uniform(size=n_rays * n_f))):
        v_f = npf(inverse_cdf(v_c, w, Lo, Hi, n_c, n_f, xi), n_f)
        assert np.all(np.diff(v_f, axis=1) >= 0)
        assert np.all(v_f >= lo[:, None] - 1e-6) and np.all(v_f <= hi[:, None] + 1e-6)


@pytest.mark.parametrize('k0', [0, 7, 31])
def test_inverse_cdf_all_weight_in_one_bin(k0):
    n_c, n_f, n_rays = 32, 128, 20
    lo, hi = segments(n_rays, seed=7)
    rng = np.random.default_rng(8)
    Lo, Hi = F(lo), F(hi)
    v_c = stratified(Lo, Hi, n_c, F(rng.uniform(size=n_rays * n_c)))
    w = np.zeros((n_rays, n_c))
    w[:, k0] = 0.7
    left, right = bin_edges(v_c, Lo, Hi, n_c)
    l0, r0 = npf(left, n_c)[:, k0:k0 + 1], npf(right, n_c)[:, k0:k0 + 1]
    inside = lambda v: (v >= l0 - 1e-6) & (v <= r0 + 1e-6)  # noqa: E731
    # Deterministic strata: every sample in the bin (the ε floor holds < 0.05 % of the mass).
    v_f = npf(inverse_cdf(v_c, F(w), Lo, Hi, n_c, n_f), n_f)
    assert inside(v_f).all()
    # ... and spread uniformly over it.
    np.testing.assert_allclose(v_f, l0 + (np.arange(n_f) + 0.5) / n_f * (r0 - l0), atol=5e-4 * (hi - lo).max())
    # Jittered strata: at most a stray sample per many rays falls outside.
    v_f = npf(inverse_cdf(v_c, F(w), Lo, Hi, n_c, n_f, F(rng.uniform(size=n_rays * n_f))), n_f)
    assert inside(v_f).mean() > 0.995


def test_inverse_cdf_uniform_weights_give_uniform_samples():
    """Equal bins (midpoint coarse samples) and equal weights: fine samples are the fine strata."""
    n_c, n_f = 16, 40
    lo, hi = segments(30, seed=9)
    Lo, Hi, v_c = coarse_midpoints(lo, hi, n_c)
    w = F(np.full(30 * n_c, 0.25))
    v_f = npf(inverse_cdf(v_c, w, Lo, Hi, n_c, n_f), n_f)
    np.testing.assert_allclose(v_f, npf(stratified(Lo, Hi, n_f), n_f), atol=3e-6)
    # Zero weights everywhere (an empty ray) fall back to the same uniform placement.
    v_f0 = npf(inverse_cdf(v_c, F(np.zeros(30 * n_c)), Lo, Hi, n_c, n_f), n_f)
    np.testing.assert_allclose(v_f0, npf(stratified(Lo, Hi, n_f), n_f), atol=3e-6)


def two_bumps(n_c):
    k = np.arange(n_c)
    return np.exp(-0.5 * ((k - 0.25 * n_c) / 2.0) ** 2) + 0.5 * np.exp(-0.5 * ((k - 0.7 * n_c) / 3.0) ** 2)


def test_inverse_cdf_histogram_matches_the_weights():
    """Many jittered rays: the fraction of fine samples per coarse bin is the normalized weight."""
    n_c, n_f, n_rays = 32, 64, 500
    lo, hi = segments(n_rays, seed=10)
    rng = np.random.default_rng(11)
    Lo, Hi = F(lo), F(hi)
    v_c = stratified(Lo, Hi, n_c, F(rng.uniform(size=n_rays * n_c)))   # unequal bins
    w = two_bumps(n_c)
    w_rays = np.tile(w, n_rays) * 0.3
    v_f = inverse_cdf(v_c, F(w_rays), Lo, Hi, n_c, n_f, F(rng.uniform(size=n_rays * n_f)))
    left, right = bin_edges(v_c, Lo, Hi, n_c)
    counts = fine_in_bins(v_f, left, right, n_c, n_f)
    assert np.all(counts.sum(axis=1) == n_f)
    frac = counts.sum(axis=0) / (n_rays * n_f)
    p = 0.3 * w + PDF_EPSILON
    p /= p.sum()
    np.testing.assert_allclose(frac, p, atol=2e-3)
    # Piecewise-constant PDF: within its bin, a sample's relative position is uniform.
    vf, le, ri = npf(v_f, n_f), npf(left, n_c), npf(right, n_c)
    rel = []
    for r in range(n_rays):
        k = np.clip(np.searchsorted(ri[r], vf[r], side='right'), 0, n_c - 1)
        rel.append((vf[r] - le[r, k]) / (ri[r, k] - le[r, k]))
    rel = np.sort(np.concatenate(rel))
    ks = np.max(np.abs(rel - (np.arange(rel.size) + 0.5) / rel.size))
    assert ks < 0.02


def test_inverse_cdf_deterministic_matches_piecewise_linear_cdf():
    """xi = None: fine sample j sits where the coarse CDF reaches (j + ½)/n_f (numpy reference)."""
    n_c, n_f = 20, 50
    lo, hi = np.array([0.3]), np.array([1.7])
    rng = np.random.default_rng(12)
    Lo, Hi = F(lo), F(hi)
    v_c = stratified(Lo, Hi, n_c, F(rng.uniform(size=n_c)))
    w = rng.uniform(size=n_c) ** 3
    left, right = bin_edges(v_c, Lo, Hi, n_c)
    edges = np.concatenate([npf(left), npf(right)[-1:]])
    p = w.astype(np.float32).astype(np.float64) + PDF_EPSILON
    cdf = np.concatenate([[0], np.cumsum(p) / p.sum()])
    u = (np.arange(n_f) + 0.5) / n_f
    expected = np.interp(u, cdf, edges)
    v_f = npf(inverse_cdf(v_c, F(w), Lo, Hi, n_c, n_f))
    np.testing.assert_allclose(v_f, expected, atol=2e-5)


@pytest.mark.parametrize('segment', ['foreground', 'background'])
def test_inverse_cdf_is_not_mirrored(segment):
    """Weight at the END of the segment must give fine samples at the end, not at the start."""
    n_c, n_f, n_rays = 32, 64, 40
    if segment == 'foreground':
        lo, hi = segments(n_rays, seed=13)
    else:                                         # v = 1 - s/s_max ∈ [0, 1): the far end comes last
        lo, hi = np.zeros(n_rays), np.ones(n_rays)
    rng = np.random.default_rng(14)
    Lo, Hi = F(lo), F(hi)
    v_c = stratified(Lo, Hi, n_c, F(rng.uniform(size=n_rays * n_c)))
    w = np.zeros((n_rays, n_c))
    w[:, -3:] = [0.2, 0.3, 0.5]
    left, _ = bin_edges(v_c, Lo, Hi, n_c)
    start_of_weight = npf(left, n_c)[:, -3:-2]
    for xi in (None, F(rng.uniform(size=n_rays * n_f))):
        v_f = npf(inverse_cdf(v_c, F(w), Lo, Hi, n_c, n_f, xi), n_f)
        frac_end = np.mean(v_f >= start_of_weight - 1e-6)
        assert frac_end > 0.99
        rel = (v_f - lo[:, None]) / (hi - lo)[:, None]
        assert rel.mean() > 0.9
    # And weight at the START gives samples at the start.
    w = w[:, ::-1].copy()
    _, right = bin_edges(v_c, Lo, Hi, n_c)
    v_f = npf(inverse_cdf(v_c, F(w), Lo, Hi, n_c, n_f), n_f)
    assert np.all(v_f <= npf(right, n_c)[:, 2:3] + 1e-6)


def test_background_fine_samples_go_where_the_far_density_is():
    """Pipeline check on the inverted sphere: density only far away (s < 0.2) pulls the fine
    samples to small s (v near 1), not to the sphere (s near 1) as a mirrored PDF would."""
    n_c, n_f = 32, 64
    rng = np.random.default_rng(15)
    o = rng.normal(size=(50, 3))
    o = 0.8 * o / np.linalg.norm(o, axis=1, keepdims=True) * rng.uniform(size=(50, 1))
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = mi.Point3f(*[F(o[:, i]) for i in range(3)])
    d = mi.Vector3f(*[F(d[:, i]) for i in range(3)])
    bg = Background(Rays(o, d))
    v_c = stratified(bg.lo, bg.hi, n_c)
    ray, _ = sampling.flat_index(50, n_c)
    s_c = bg.s(ray, v_c)
    sigma = dr.select(s_c < 0.2, 30.0, 0.0)
    rgb = mi.Color3f(dr.full(mi.Float, 1.0, dr.width(v_c)))
    _, w = quadrature(bg, v_c, sigma, rgb, n_c)
    w_np = npf(w, n_c)
    assert np.all(w_np[:, npf(s_c, n_c)[0] >= 0.2] == 0)
    v_f = inverse_cdf(v_c, w, bg.lo, bg.hi, n_c, n_f)
    ray_f, _ = sampling.flat_index(50, n_f)
    s_f = npf(bg.s(ray_f, v_f))
    bin_width = 1.0 / n_c
    assert np.all(s_f < 0.2 + 1.5 * bin_width)
    # The fine directions are then far-away points: x̂ is close to the ray direction d.
    x = bg.inputs(ray_f, v_f)
    s_max = npf(geo.background_s_max(o, d))
    assert np.all(s_max == 1.0) and np.all(np.asarray(x[3]) == np.asarray(bg.s(ray_f, v_f)))


# ----------------------------------------------------------------------------- merging

def merge_case(n_rays, n_a, n_b, seed, grid=None):
    rng = np.random.default_rng(seed)
    a = rng.uniform(size=(n_rays, n_a))
    b = rng.uniform(size=(n_rays, n_b))
    if grid is not None:                       # quantize: many ties within and across sets
        a, b = np.round(a * grid) / grid, np.round(b * grid) / grid
    a, b = np.sort(a, axis=1), np.sort(b, axis=1)
    # A few rays entirely before / after the other set.
    b[0] += 2.0
    a[1] += 2.0
    return a.astype(np.float32).astype(np.float64), b.astype(np.float32).astype(np.float64)


@pytest.mark.parametrize('n_a, n_b, grid', [(8, 16, None), (16, 8, 6), (5, 5, 3), (1, 7, None), (7, 1, 2)])
def test_merge_is_sorted_permutation_of_the_union(n_a, n_b, grid):
    n_rays = 30
    a, b = merge_case(n_rays, n_a, n_b, seed=n_a * 100 + n_b, grid=grid)
    order = merge_order(F(a), n_a, F(b), n_b)
    merged = npf(gather_merged(order, F(a), F(b)), n_a + n_b)
    np.testing.assert_array_equal(merged, np.sort(np.concatenate([a, b], axis=1), axis=1))

    # Every element of a and of b is used exactly once, by its own ray.
    from_b = np.asarray(order[0]).reshape(n_rays, -1)
    index = np.asarray(order[1], dtype=np.int64).reshape(n_rays, -1)
    ray = np.arange(n_rays)[:, None]
    ia, ib = index[~from_b], index[from_b]
    assert sorted(ia) == list(range(n_rays * n_a))
    assert sorted(ib) == list(range(n_rays * n_b))
    assert np.all(np.where(from_b, index // n_b, index // n_a) == ray)

    # Ties put a first; and a payload follows its value (the permutation is the real one).
    ids = gather_merged(order, F(np.arange(n_rays * n_a)), F(-1 - np.arange(n_rays * n_b)))
    ids = npf(ids, n_a + n_b).astype(np.int64)
    values = np.where(ids >= 0, a.ravel()[np.maximum(ids, 0)], b.ravel()[np.maximum(-1 - ids, 0)])
    np.testing.assert_array_equal(values, merged)
    tie = merged[:, 1:] == merged[:, :-1]
    assert not np.any(tie & (ids[:, 1:] >= 0) & (ids[:, :-1] < 0))      # no b before an equal a
    if grid is not None:
        assert tie.any()


def test_gather_merged_vectors_and_gradients():
    n_rays, n_a, n_b = 6, 4, 5
    a, b = merge_case(n_rays, n_a, n_b, seed=3)
    order = merge_order(F(a), n_a, F(b), n_b)
    ca = mi.Color3f(F(a), F(2 * a), F(3 * a))
    cb = mi.Color3f(F(b), F(2 * b), F(3 * b))
    merged = np.asarray(gather_merged(order, ca, cb), dtype=np.float64)
    ref = np.sort(np.concatenate([a, b], axis=1), axis=1).ravel()
    np.testing.assert_allclose(merged, np.stack([ref, 2 * ref, 3 * ref]), rtol=1e-6)

    # Gradients flow to both inputs through the merge.
    xa, xb = F(a), F(b)
    dr.enable_grad(xa, xb)
    m = gather_merged(order, xa, xb)
    pos = mi.Float(np.tile(np.arange(n_a + n_b, dtype=np.float32), n_rays))
    dr.backward(dr.sum(m * pos))
    ga, gb = npf(dr.grad(xa), n_a), npf(dr.grad(xb), n_b)
    # The gradient of each element is its merged position: a permutation of 0..m-1 per ray.
    both = np.sort(np.concatenate([ga, gb], axis=1), axis=1)
    np.testing.assert_array_equal(both, np.tile(np.arange(n_a + n_b), (n_rays, 1)))
    assert np.all(np.diff(ga, axis=1) > 0) and np.all(np.diff(gb, axis=1) > 0)


@pytest.mark.parametrize('n_a, n_b, grid', [(16, 8, 6), (1, 7, None), (7, 1, 2)])
def test_split_merged_inverts_gather_merged(n_a, n_b, grid):
    """A merged quantity taken back to the elements of a and b (how the renderer composites
    features where they were evaluated) is exactly what was merged, and its gradient reaches
    the merged slot of each element."""
    n_rays = 12
    a, b = merge_case(n_rays, n_a, n_b, seed=7 + n_a, grid=grid)
    order = merge_order(F(a), n_a, F(b), n_b)
    pa, pb = F(np.arange(n_rays * n_a) * 2.0), F(np.arange(n_rays * n_b) * 3.0 + 0.5)
    back_a, back_b = split_merged(order, gather_merged(order, pa, pb))
    np.testing.assert_array_equal(np.asarray(back_a), np.asarray(pa))
    np.testing.assert_array_equal(np.asarray(back_b), np.asarray(pb))
    # d/dx of sum(x_a * c_a) + sum(x_b * c_b) + 10 sum(x) is c at the merged slots + 10:
    # the split adds to the gradient of x's other uses.
    x = F(np.zeros(n_rays * (n_a + n_b)))
    dr.enable_grad(x)
    xa, xb = split_merged(order, x)
    dr.backward(dr.sum(xa * pa) + dr.sum(xb * pb) + 10.0 * dr.sum(x))
    np.testing.assert_array_equal(np.asarray(dr.grad(x)),
                                  np.asarray(gather_merged(order, pa, pb)) + 10.0)


# ----------------------------------------------------------------------------- one home

SAMPLE_COUNTS = ('fg_samples', 'bg_samples', 'fine_samples')


def sample_count_literals(root):
    """``[(file, line)]`` of every whole number written as a sample count in the package's
    source: a keyword ``fg_samples=16``, a field or assignment ``fine_samples = 8`` or
    ``option(16, ...)`` of such a field."""
    found = []
    for path in sorted(root.rglob('*.py')):
        tree = ast.parse(path.read_text(encoding='utf-8'))
        for node in ast.walk(tree):
            value = None
            if isinstance(node, ast.keyword) and node.arg in SAMPLE_COUNTS:
                value = node.value
            elif (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
                  and node.target.id in SAMPLE_COUNTS):
                value = node.value
                if isinstance(value, ast.Call) and value.args:      # option(16, ...)
                    value = value.args[0]
            if isinstance(value, ast.Constant) and isinstance(value.value, int):
                found.append((str(path.relative_to(root.parent)), node.lineno))
    return found


def test_the_sample_count_defaults_have_one_home():
    """16/16/8 (empty-space skipping, training) and 64/64/128 (whole rays) are written once,
    in mi_nerfpp.core.render; the options, the integrator and old checkpoints read them."""
    from mi_nerfpp.core.render import SKIPPING, Sampling
    from mi_nerfpp.training.config import SamplingOptions
    root = pathlib.Path(__file__).resolve().parent.parent.parent / 'mi_nerfpp'
    places = {file for file, _ in sample_count_literals(root)}
    assert places == {'mi_nerfpp/core/render.py'}, places
    options = SamplingOptions()
    assert (options.fg_samples, options.bg_samples, options.fine_samples) == (
        SKIPPING.fg_samples, SKIPPING.bg_samples, SKIPPING.fine_samples)
    assert Sampling() == Sampling(64, 64, 128, 0.0)


def test_a_sample_count_written_elsewhere_is_found(tmp_path):
    package = tmp_path / 'pkg'
    package.mkdir()
    (package / 'a.py').write_text('def f(x):\n    return x(fine_samples=4, near=0)\n')
    (package / 'b.py').write_text('class C:\n    bg_samples: int = option(16, "help")\n')
    assert sample_count_literals(package) == [('pkg/a.py', 2), ('pkg/b.py', 2)]
