"""Empty-space skipping (mi_nerfpp.core.occupancy) against closed forms.

The scene of these tests: density σ in the half-space x > 0 of the unit ball, zero elsewhere.
Its occupancy grid marks exactly the cells with x > 0 (the grid splits at x = 0).
"""
from __future__ import annotations

import numpy as np
import pytest

import mi_nerfpp  # noqa: F401
import drjit as dr
import mitsuba as mi

from mi_nerfpp.core.occupancy import EMPTY_WEIGHT, OccupancyGrid, OccupiedVolume
from mi_nerfpp.core.rays import Rays
from mi_nerfpp.core.render import (Foreground, RenderOptions, Sampling, render_rays,
                                   render_volume)
from mi_nerfpp.core.sampling import stratified
from tests.helpers import AnalyticField, tiny_model

SIGMA = 3.0
COLOR = (0.2, 0.6, 0.9)


def F(a):
    return mi.Float(np.asarray(a, dtype=np.float32).ravel())


def npf(x, n=None):
    a = np.asarray(x, dtype=np.float64).ravel()
    return a if n is None else a.reshape(-1, n)


def half_space_field():
    """σ = SIGMA for x > 0, else 0; constant colour."""
    return AnalyticField(lambda x: dr.select(x[0] > 0.0, SIGMA, 0.0), COLOR)


def axis_rays(n=16, seed=0):
    """Rays along +x from x = -0.9, with small random offsets in y and z."""
    rng = np.random.default_rng(seed)
    yz = rng.uniform(-0.3, 0.3, size=(n, 2))
    o = mi.Point3f(F(np.full(n, -0.9)), F(yz[:, 0]), F(yz[:, 1]))
    d = mi.Vector3f(F(np.ones(n)), F(np.zeros(n)), F(np.zeros(n)))
    return o, d, yz


def half_space_grid(resolution=16):
    grid = OccupancyGrid('ball', resolution)
    grid.update(half_space_field(), seed=1)
    return grid


def random_volume(domain, n, rng):
    """The volume of ``domain`` along ``n`` random rays from inside the ball, and an occupancy grid
    of 32 cells per axis with 30 % of them occupied at random."""
    from mi_nerfpp.core.render import Background
    o = rng.normal(size=(n, 3))
    o *= 0.9 * rng.uniform(size=(n, 1)) ** (1 / 3) / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    O = mi.Point3f(*[F(o[:, i]) for i in range(3)])
    D = mi.Vector3f(*[F(d[:, i]) for i in range(3)])
    grid = OccupancyGrid(domain, 32)
    grid.density = F((rng.uniform(size=dr.width(grid.density)) < 0.3) * 10.0)
    return (Foreground(Rays(O, D)) if domain == 'ball' else Background(Rays(O, D))), grid


@pytest.mark.parametrize('domain', ['ball', 'inverted_sphere'])
def test_cell_points_map_back_to_their_cells(domain):
    grid = OccupancyGrid(domain, 16)
    n = dr.width(grid.density)
    for xi in (0.5, 0.01, 0.99):
        p = grid.cell_points(mi.Point3f(xi, xi, xi))
        np.testing.assert_array_equal(np.asarray(grid.cell(p)), np.arange(n))


def test_update_marks_the_occupied_half():
    grid = half_space_grid()
    occ = grid.numpy() > grid.threshold                 # (Z, Y, X)
    assert occ[:, :, 8:].all() and not occ[:, :, :8].any()
    assert grid.fraction() == pytest.approx(0.5)
    # Later updates keep a decaying maximum: an emptied cell fades, it does not vanish at once.
    before = grid.numpy().copy()
    grid.update(lambda_field(0.0), seed=2, decay=0.5)
    np.testing.assert_allclose(grid.numpy(), 0.5 * before, rtol=1e-6)


def test_sampled_density_is_the_field_now_not_the_running_maximum():
    """What sparse levels allocate from: the field's density at jittered points of each cell
    now. A cell that training emptied reads 0 at once, where the running maximum keeps it
    occupied for many refreshes."""
    grid = half_space_grid()                            # x > 0 occupied
    grid.update(lambda_field(0.0), seed=2)              # the field emptied everywhere
    assert (grid.numpy()[:, :, 8:] > grid.threshold).all()          # still remembered
    assert not grid.sampled(lambda_field(0.0), seed=3).any()
    # Of the half-space field, the largest of 4 points per cell: the occupied half exactly.
    now = grid.sampled(half_space_field(), seed=4)
    assert (now[:, :, 8:] > grid.threshold).all() and not now[:, :, :8].any()
    assert np.array_equal(grid.sampled(half_space_field(), seed=4), now)     # seeded


def lambda_field(sigma):
    class Const:
        def density(self, x):
            return dr.full(mi.Float, sigma, dr.width(x[0]))
    return Const()


def test_samples_skip_the_empty_region():
    o, d, _ = axis_rays()
    vol = OccupiedVolume(Foreground(Rays(o, d)), half_space_grid(), bins=128)
    n = 16
    u = stratified(vol.lo, vol.hi, n)
    ray, = _ray_index(16, n)
    x = npf(vol.inputs(ray, vol.parameter(ray, u))[0], n)
    bin_width = 1.9 / 128            # chords here are at most 1.9 long (|o| <= 0.95)
    assert (x > -bin_width).all()
    # Uniform in occupied length: equal steps in x.
    steps = np.diff(x, axis=1)
    np.testing.assert_allclose(steps, np.broadcast_to(steps[:, :1], steps.shape), atol=2 * bin_width)


def _ray_index(n_rays, n):
    from mi_nerfpp.core.sampling import flat_index
    return flat_index(n_rays, n)[0],


def test_occupied_quadrature_matches_the_closed_form():
    """Midpoint samples in occupied length: opacity = 1 - exp(-σ (L_occ + ε L_empty)(1 - 1/2n))."""
    o, d, yz = axis_rays()
    fg = Foreground(Rays(o, d))
    vol = OccupiedVolume(fg, half_space_grid(), bins=128)
    n = 32
    shading = render_volume(vol, half_space_field(), n, 0).shading
    x_exit = np.sqrt(1.0 - (yz ** 2).sum(axis=1))       # chord ends on the unit sphere
    L_occ, L_empty = x_exit, 0.9
    # Bins are looked up at their midpoints: the bin that straddles x = 0 counts as one or the other.
    bin_width = (npf(fg.hi) - npf(fg.lo)) / 128
    expected = 1.0 - np.exp(-SIGMA * (L_occ + EMPTY_WEIGHT * L_empty) * (1 - 0.5 / n))
    np.testing.assert_allclose(npf(shading.opacity), expected, atol=SIGMA * bin_width.max())
    np.testing.assert_allclose(npf(shading.rgb, 16), np.outer(COLOR, npf(shading.opacity)), atol=1e-5)


def test_occupancy_converges_with_far_fewer_samples():
    """Against a 4096-sample reference without skipping, 16 + 16 samples in occupied space are
    over three times as accurate as the same budget spread over the whole chord."""
    o, d, _ = axis_rays()
    field = half_space_field()
    ref = render_rays(Rays(o, d), field, None, Sampling(4096, 1, 0)).composite.opacity
    grid = half_space_grid(64)
    occ = render_rays(Rays(o, d), field, None, Sampling(16, 1, 16),
                      RenderOptions(occupancy={'fg': grid})).composite.opacity
    plain = render_rays(Rays(o, d), field, None, Sampling(16, 1, 16)).composite.opacity
    err_occ = np.abs(npf(occ) - npf(ref)).max()
    err_plain = np.abs(npf(plain) - npf(ref)).max()
    assert err_occ < 3e-3 and 3 * err_occ < err_plain


def test_empty_grid_renders_nothing_in_the_foreground():
    o, d, _ = axis_rays()
    grid = OccupancyGrid('ball', 8)
    grid.update(lambda_field(0.0), seed=0)
    res = render_rays(Rays(o, d), AnalyticField(50.0, (1.0, 1.0, 1.0)), None, Sampling(16, 1, 16),
                      RenderOptions(occupancy={'fg': grid}))
    # The field is dense everywhere, but every cell is marked empty: only ε of it is seen.
    assert npf(res.composite.opacity).max() < 1.0 - np.exp(-50.0 * EMPTY_WEIGHT * 2.0) + 1e-6


def test_checkpoint_keeps_the_occupancy(tmp_path):
    from mi_nerfpp.files.checkpoint import load_checkpoint, save_checkpoint
    from mi_nerfpp.core.model import NeRFPPModel
    tiny = dict(kind='grid', resolutions=[4, 8], channels=3, hidden=8, dir_octaves=1)
    model = NeRFPPModel.create(fg_config=dict(tiny, domain='ball'),
                               bg_config=dict(tiny, domain='inverted_sphere'))
    model.enable_occupancy(8, 0.02)
    model.update_occupancy(seed=3)
    save_checkpoint(tmp_path / 'm.npz', model)
    loaded, _, _ = load_checkpoint(tmp_path / 'm.npz')
    assert sorted(loaded.occupancy) == ['bg', 'fg']
    for k, grid in model.occupancy.items():
        assert loaded.occupancy[k].config == grid.config
        np.testing.assert_array_equal(loaded.occupancy[k].numpy(), grid.numpy())
    o, d, _ = axis_rays()
    a = render_rays(Rays(o, d), model.fg, model.bg, Sampling(8, 8, 8),
                    RenderOptions(occupancy=model.occupancy))
    b = render_rays(Rays(o, d), loaded.fg, loaded.bg, Sampling(8, 8, 8),
                    RenderOptions(occupancy=loaded.occupancy))
    np.testing.assert_allclose(npf(a.composite.rgb, 16), npf(b.composite.rgb, 16), atol=1e-6)


@pytest.mark.parametrize('domain,bins', [('ball', 128), ('inverted_sphere', 64), ('ball', 32)])
def test_occupied_length_coordinate_matches_a_float64_reference(domain, bins):
    """``parameter(u)`` of random rays through a random occupancy grid equals the inverse of the
    occupied-length CDF computed in float64 from the bins' occupancy (equal bins, empty ones
    weighing EMPTY_WEIGHT), within float32 rounding of the ray parameter."""
    from mi_nerfpp.core.sampling import flat_index
    rng = np.random.default_rng(4)
    n, m = 300, 24
    base, grid = random_volume(domain, n, rng)
    vol = OccupiedVolume(base, grid, bins)
    # The reference's bins: occupied where the grid's cell of the bin's midpoint is.
    lo, hi = npf(base.lo), npf(base.hi)
    ray, k = flat_index(n, bins)
    mid = F(((lo[:, None] + (np.arange(bins) + 0.5) / bins * (hi - lo)[:, None])).ravel())
    occupied = npf(grid.occupied(base.inputs(ray, mid)), bins).astype(bool)
    assert 0.05 < occupied.mean() < 0.95
    width = np.maximum((hi - lo) / bins, 1e-12)
    mass = width[:, None] * np.where(occupied, 1.0, EMPTY_WEIGHT)
    cdf = np.concatenate([np.zeros((n, 1)), np.cumsum(mass, 1)], 1)
    np.testing.assert_allclose(npf(vol.total), cdf[:, -1], rtol=1e-5)
    u = rng.uniform(size=(n, m))
    u[:, 0], u[:, -1] = 0.0, 1.0              # both ends of the occupied length
    got = npf(vol.parameter(flat_index(n, m)[0], F(u)), m)
    for r in range(n):
        t = u[r] * cdf[r, -1]
        b = np.clip(np.searchsorted(cdf[r], t, side='right') - 1, 0, bins - 1)
        ref = lo[r] + (b + np.clip((t - cdf[r, b]) / mass[r, b], 0, 1)) / bins * (hi[r] - lo[r])
        np.testing.assert_allclose(got[r], ref, atol=2e-4, rtol=0)


def test_refreshes_with_new_seeds_reuse_their_kernels():
    """A refresh's seed reaches its kernels as an input, not a constant: a refresh with a seed
    never used before compiles nothing (as a literal, each refresh compiled its kernels anew,
    ~100 ms every 16 training steps)."""
    import random
    m = tiny_model()
    m.enable_occupancy(16, 0.3)
    m.update_occupancy(1)                    # the first refresh takes the field's density as is
    m.update_occupancy(2)                    # the next ones keep a running maximum
    dr.sync_thread()
    flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()                  # clear
        m.update_occupancy(random.SystemRandom().randrange(10 ** 6, 2 ** 31))
        dr.sync_thread()
        jit = [k for k in dr.kernel_history() if k['type'] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, flag)
    assert jit and all(k['cache_hit'] for k in jit), jit


@pytest.mark.parametrize('domain', ['ball', 'inverted_sphere'])
def test_samples_placed_per_ray_equal_the_wavefront(domain):
    """Samples placed in one loop per ray (how renders and training place them) are the
    wavefront's exactly: stratified coarse samples with jitter, then fine samples by inverse CDF,
    through the occupied-length inverse of a random occupancy grid."""
    from mi_nerfpp.core.render import _placed
    from mi_nerfpp.core.sampling import (FineSampler, flat_index, inverse_cdf, stratified,
                                         stratified_sample, uniforms)
    rng = np.random.default_rng(9)
    n, n_c, n_f = 200, 16, 8
    vol = OccupiedVolume(*random_volume(domain, n, rng), 128 if domain == 'ball' else 64)
    seed = mi.UInt32(rng.integers(0, 2 ** 32 - 1, n, dtype=np.uint64).astype(np.uint32))
    xi_c, xi_f = uniforms(seed, n_c, 0), uniforms(seed, n_f, 1)

    v_c, t_c = _placed(vol, n, n_c, lambda ray, k: stratified_sample(vol.lo, vol.hi, ray, k,
                                                                     n_c, xi_c))
    ref_v = stratified(vol.lo, vol.hi, n_c, xi_c)
    np.testing.assert_array_equal(npf(v_c), npf(ref_v))
    np.testing.assert_array_equal(npf(t_c), npf(vol.parameter(flat_index(n, n_c)[0], ref_v)))

    w = F(rng.uniform(size=n * n_c) ** 4)
    v_f, t_f = _placed(vol, n, n_f, FineSampler(v_c, w, vol.lo, vol.hi, n_c, n_f, xi_f).sample)
    ref_f = inverse_cdf(v_c, w, vol.lo, vol.hi, n_c, n_f, xi_f)
    np.testing.assert_array_equal(npf(v_f), npf(ref_f))
    np.testing.assert_array_equal(npf(t_f), npf(vol.parameter(flat_index(n, n_f)[0], ref_f)))
    assert np.all(np.diff(npf(t_f, n_f), axis=1) >= 0)


def test_integrator_without_skipping_samples_whole_rays():
    """``skip_empty=false``: the integrator ignores the model's occupancy grids and samples
    every interval with the counts of a model without grids (64 + 64 + 128): its render equals
    that of the model with no grids at all, while with skipping (the default) grids that mark
    everything empty change the render (the background's last interval alone shows)."""
    from tests.helpers import scene_dict

    def scene(model, **params):
        desc = scene_dict(jitter=False, **params)
        for k in ('fg_samples', 'bg_samples', 'fine_samples'):     # the model's unless given
            if k not in params:
                desc['integrator'].pop(k)
        out = mi.load_dict(desc)
        out.integrator().set_model(model)
        return out

    def render(model, **params):
        return np.array(mi.render(scene(model, **params), spp=1))

    m = tiny_model()
    m.enable_occupancy(8, 0.3)
    for grid in m.occupancy.values():
        grid.density = dr.zeros(mi.Float, dr.width(grid.density))
        grid.fresh = False
    skipped = render(m)
    whole = render(m, skip_empty=False)
    integrator = scene(m, skip_empty=False).integrator()
    assert (integrator.sampling.fg_samples, integrator.sampling.bg_samples,
            integrator.sampling.fine_samples) == (64, 64, 128)
    bare = tiny_model()                      # the same fields, no occupancy grids
    reference = render(bare, fg_samples=64, bg_samples=64, fine_samples=128)
    np.testing.assert_allclose(whole, reference, rtol=1e-5, atol=1e-6)
    assert np.abs(skipped - reference).max() > 1e-2      # the grids did change the default
