"""Field structures of paper §3: where the view direction enters, and with which encoding."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.core.fields import MLPField, grid_field, make_field
from tests.helpers import field_inputs


def _eval(field, n=64, seed=0):
    """σ and rgb at the same points seen along two different directions."""
    rng = np.random.default_rng(seed)
    x = [mi.Float(v) for v in rng.uniform(-0.8, 0.8, (3, n)).astype(np.float32)]
    out = []
    for d in rng.normal(size=(2, 3)):
        d = d / np.linalg.norm(d)
        sigma, rgb = field(x, mi.Vector3f(*[mi.Float(float(c)) for c in d]), dr.zeros(mi.UInt32, n))
        out.append((np.array(sigma), np.array(rgb)))
    return out


FIELDS = {
    'nerf': lambda: MLPField('ball', 'nerf', depth=2, width=16),
    'vanilla': lambda: MLPField('ball', 'vanilla', depth=2, width=16),
    'grid': lambda: grid_field('ball', resolutions=(4, 8), channels=3, hidden=8),
    'grid, vanilla colour': lambda: grid_field('ball', resolutions=(4, 8), channels=3, hidden=8,
                                               color_layers=3, dir_octaves=10),
}


@pytest.mark.parametrize('kind', FIELDS)
def test_density_depends_on_position_only_and_colour_on_direction(kind):
    (s1, c1), (s2, c2) = _eval(FIELDS[kind]())
    np.testing.assert_array_equal(s1, s2)
    assert np.abs(c1 - c2).max() > 1e-4


def test_direction_encoding_and_depth_of_each_structure():
    nerf = MLPField('ball', 'nerf', depth=3, width=16)
    vanilla = MLPField('ball', 'vanilla', depth=3, width=16)
    def rest_layers(field, net):
        return len([k for k in field.params if k.startswith(f'{net}.rest') and 'weights' in k])
    # NeRF-MLP: γ^4(d) = 27 inputs into a head of one hidden layer (width/2) and the output.
    assert nerf.params['head.ray.layers.0.weights'].shape == (8, 27)
    assert rest_layers(nerf, 'head') == 1
    # Vanilla: γ^10(x) and γ^10(d) (63 inputs each) at the first layer of a colour MLP of
    # 3 hidden layers (the first, 2 more, then the output).
    assert vanilla.params['color.ray.layers.0.weights'].shape == (16, 63)
    assert vanilla.params['color.sample.layers.0.weights'].shape == (16, 63)
    assert rest_layers(vanilla, 'color') == 3
    # σ comes from a trunk over γ^10(x) alone in both.
    assert nerf.params['trunk.layers.0.weights'].shape[1] == 63
    assert vanilla.params['trunk.layers.0.weights'].shape[1] == 63
    assert vanilla.params['trunk.layers.6.weights'].shape == (1, 16)


def test_grid_colour_layers_round_trip_through_config():
    f = grid_field('inverted_sphere', resolutions=(4,), channels=3, hidden=8, color_layers=2,
                   dir_octaves=10)
    g = make_field(f.config)
    assert g.config == f.config
    assert set(g.params) == set(f.params)
    assert g.params['color.ray.layers.0.weights'].shape == (8, 63)
    with pytest.raises(ValueError, match='color_layers'):
        grid_field('ball', color_layers=0)


def test_background_grid_cells_along_s_follow_s_ratio():
    """The inverted-sphere grid is 2R x R x max(s_ratio R, 4) (longitude, colatitude, s); the ratio
    round-trips through the config, and configs written before it existed read as 0.5."""
    f = grid_field('inverted_sphere', resolutions=(8, 64), channels=3, hidden=8, s_ratio=0.125)
    assert tuple(f.params['grid0'].shape) == (4, 8, 16, 3)      # at least 4 cells along s
    assert tuple(f.params['grid1'].shape) == (8, 64, 128, 3)
    again = make_field(f.config)
    assert again.dense.s_ratio == 0.125 and tuple(again.params['grid1'].shape) == (8, 64, 128, 3)
    old = {k: v for k, v in f.config.items() if k != 's_ratio'}
    assert make_field(old).dense.s_ratio == 0.5
    with pytest.raises(ValueError, match='s_ratio'):
        grid_field('inverted_sphere', resolutions=(8,), s_ratio=0)


def test_background_grid_takes_one_s_ratio_per_level():
    """Per-level ratios: a fine angular level with few cells along s over a coarse level
    resolved in depth; they round-trip through the config, and a list of the wrong length is
    refused."""
    f = grid_field('inverted_sphere', resolutions=(16, 64), channels=3, hidden=8,
                   s_ratio=[0.5, 1 / 16])
    assert tuple(f.params['grid0'].shape) == (8, 16, 32, 3)
    assert tuple(f.params['grid1'].shape) == (4, 64, 128, 3)
    again = make_field(f.config)
    assert again.dense.s_ratio == [0.5, 0.0625]
    assert tuple(again.params['grid1'].shape) == (4, 64, 128, 3)
    with pytest.raises(ValueError, match='one per level'):
        grid_field('inverted_sphere', resolutions=(16, 64), s_ratio=[0.5])


def test_density_gradient_reaches_the_sample_positions_through_the_grid():
    """Groundwork for camera pose refinement: Dr.Jit differentiates Texture3f lookups with
    respect to the lookup coordinates, so a loss on the density reaches the points (and through
    them the rays). Checked against central differences away from cell boundaries."""
    from tests.helpers import tiny_model
    field = tiny_model().fg
    points = np.array([[0.1, 0.3, -0.27], [-0.2, 0.05, 0.4], [0.33, -0.41, 0.12]])
    x = [mi.Float(points[:, k]) for k in range(3)]
    dr.enable_grad(x)
    dr.backward(dr.sum(field.density(x)))
    ad = np.stack([np.array(dr.grad(c)) for c in x], axis=1)
    h = 1e-3
    for k in range(3):
        plus, minus = points.copy(), points.copy()
        plus[:, k] += h
        minus[:, k] -= h
        fd = (np.array(field.density([mi.Float(plus[:, j]) for j in range(3)]))
              - np.array(field.density([mi.Float(minus[:, j]) for j in range(3)]))) / (2 * h)
        np.testing.assert_allclose(ad[:, k], fd, rtol=0.02, atol=2e-4)
    assert np.abs(ad).max() > 1e-3          # not trivially zero


# ----------------------------------------------------------------------------- footprints


@pytest.mark.parametrize('domain, warp', [('ball', 0.0), ('ball', 0.4), ('inverted_sphere', 0.0)])
def test_a_footprint_within_the_finest_cell_is_the_point_lookup(domain, warp):
    """``antialias`` with footprints no wider than the finest level's cell: every level keeps
    its weight of 1, so density and features are those of the point lookup, bit for bit."""
    extra = {'warp_radius': warp} if domain == 'ball' else {}
    field = grid_field(domain, resolutions=(4, 16), channels=3, antialias=True, seed=3, **extra)
    x = field_inputs(domain)
    n = dr.width(x[0])
    # Footprints up to the finest cell, in the domain's units; the warp magnifies the centre
    # by at most BALL_WARP_SHARE / warp, so shrink them by that much there.
    from mi_nerfpp.core.geometry import BALL_WARP_SHARE
    magnify = BALL_WARP_SHARE / warp if warp else 1.0
    width = mi.Float(np.linspace(0.0, 1.0, n).astype(np.float32)) * (
        field.dense.cell_size(1) / magnify)
    sigma_p, feat_p = field.features(x)
    sigma_f, feat_f = field.features(x, width)
    np.testing.assert_array_equal(np.array(sigma_f), np.array(sigma_p))
    for a, b in zip(feat_f, feat_p):
        np.testing.assert_array_equal(np.array(a), np.array(b))
    # Without antialias the footprint is ignored whatever its size.
    field.antialias = False
    np.testing.assert_array_equal(np.array(field.density(x, width * 100.0)),
                                  np.array(field.density(x)))


@pytest.mark.parametrize('domain', ['ball', 'inverted_sphere'])
def test_a_wide_footprint_weighs_each_level_by_how_well_its_cells_resolve_it(domain):
    """Closed form: at a footprint of 1.5 fine cells the fine level weighs 0.5 and the coarse
    level 1 (its cells are 4x wider); from 2 fine cells to one coarse cell the fine level is gone. The
    same as the point lookup of a field whose fine grid is scaled by that weight."""
    field = grid_field(domain, resolutions=(4, 16), channels=3, antialias=True, seed=5)
    x = field_inputs(domain)
    n = dr.width(x[0])
    for multiple, weight in ((1.5, 0.5), (2.0, 0.0), (3.5, 0.0)):
        width = dr.full(mi.Float, field.dense.cell_size(1) * multiple, n)
        sigma, features = field.features(x, width)
        reference = grid_field(domain, resolutions=(4, 16), channels=3, seed=5)
        reference.set_parameters({'grid1': field.params['grid1'] * weight})
        sigma_ref, features_ref = reference.features(x)
        np.testing.assert_allclose(np.array(sigma), np.array(sigma_ref), rtol=1e-5,
                                   err_msg=f"footprint of {multiple} fine cells")
        for a, b in zip(features, features_ref):
            np.testing.assert_allclose(np.array(a), np.array(b), rtol=1e-5, atol=1e-7)
    # At 16 fine cells (4 coarse cells) no level is left: density from the bias alone.
    width = dr.full(mi.Float, field.dense.cell_size(1) * 16.0, n)
    np.testing.assert_allclose(np.array(field.density(x, width)),
                               np.exp(field.density_bias), rtol=1e-6)


def test_antialias_round_trips_through_the_config():
    field = grid_field('ball', resolutions=(4, 8), channels=3, antialias=True)
    again = make_field(field.config)
    assert again.antialias and field.config['antialias'] is True
    assert make_field({k: v for k, v in field.config.items() if k != 'antialias'}).antialias \
        is False    # a field stored before footprints looks up points


@pytest.mark.parametrize('layers', [1, 2])
def test_per_sample_colour_for_training_equals_the_render_network(layers):
    """A per-sample colour network evaluated with its weights differentiated (training: tensor
    mode, the ray's share of the first layer gathered for every row at once) gives the render's
    colours (packed cooperative vectors, row by row) and weight gradients equal to central
    finite differences."""
    from mi_nerfpp.core.fields import positional_encoding
    field = grid_field('inverted_sphere', resolutions=(4, 8), channels=3, hidden=8,
                       color_layers=layers, dir_octaves=1, color='sample')
    net = field.color_net
    n_feat = field.params['color.sample.layers.0.weights'].shape[1]
    rng = np.random.default_rng(1)
    n_rays, per_ray = 5, 7
    features = [mi.Float(v) for v in rng.normal(size=(n_feat, n_rays * per_ray)).astype(np.float32)]
    d = rng.normal(size=(3, n_rays))
    d = mi.Vector3f(*[mi.Float(v) for v in (d / np.linalg.norm(d, axis=0)).astype(np.float32)])
    ray = mi.UInt32(np.repeat(np.arange(n_rays), per_ray).astype(np.uint32))
    encoded = positional_encoding([d.x, d.y, d.z], field.network.dir_octaves)
    coef = rng.normal(size=3)

    def colors():
        return np.array([np.array(c) for c in net(features, encoded, ray)])
    rendered = colors()
    keys = ['color.sample.layers.0.weights', 'color.ray.layers.0.weights',
            'color.ray.layers.0.bias']
    for key in keys:
        dr.enable_grad(field.params[key])
    out = net(features, encoded, ray)
    np.testing.assert_allclose(np.array([np.array(c) for c in out]), rendered, rtol=1e-5,
                               atol=1e-6)
    dr.backward(sum((float(c) * dr.sum(o) for c, o in zip(coef, out)), mi.Float(0.0)))
    for key in keys:
        grad = np.array(dr.grad(field.params[key])).ravel()
        base = np.array(dr.detach(field.params[key])).astype(np.float64)
        shape = base.shape
        for i in rng.choice(base.size, 3, replace=False):
            values = []
            for h in (1e-3, -1e-3):
                moved = base.ravel().copy()
                moved[i] += h
                field.params[key] = mi.TensorXf(moved.astype(np.float32).reshape(shape))
                values.append(float(np.sum(coef[:, None] * colors())))
            field.params[key] = mi.TensorXf(base.astype(np.float32).reshape(shape))
            assert grad[i] == pytest.approx((values[0] - values[1]) / 2e-3, rel=2e-2, abs=2e-3), \
                (key, i)
