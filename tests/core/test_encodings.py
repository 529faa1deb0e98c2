"""Grid levels (:mod:`mi_nerfpp.core.encodings`): one interface for the dense, plane and sparse
kinds, summed by the grid field in order; the field's stored config maps onto them and back."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.core.encodings import (DenseLevels, PlaneLevels, SparseLevels, level_weight)
from mi_nerfpp.core.fields import (GRID_CONFIG, ColorNetwork, GridField, grid_default,
                                   grid_field, make_field)
from mi_nerfpp.core.geometry import ball_warp, grid_coordinates
from tests.helpers import field_inputs


def test_level_weight():
    w = level_weight(mi.Float([0.0, 0.5, 1.0, 1.25, 1.5, 2.0, 3.0]), 1.0)
    np.testing.assert_allclose(np.array(w), [1, 1, 1, 0.75, 0.5, 0, 0])


def _levels(domain, rng):
    """One level set of each kind, with random contents (planes and bricks start at zero)."""
    blocks = (4, 4, 4) if domain == 'ball' else (4, 4, 8)
    dense = DenseLevels(domain, (4, 8), channels=3, init=0.5, rng=dr.rng(seed=2))
    planes = PlaneLevels(domain, (8,), channels=3)
    sparse = SparseLevels(domain, (16,), channels=3, blocks=blocks)
    sparse.allocate({'sparse0': np.arange(0, int(np.prod(blocks)), 2)})
    for lv in (planes, sparse):
        for k, v in lv.params.items():
            lv.params[k] = mi.TensorXf(rng.normal(size=v.shape).astype(np.float32))
        lv.bind()
    return [dense, planes, sparse]


@pytest.mark.parametrize('domain, warp', [('ball', 0.0), ('ball', 0.4), ('inverted_sphere', 0.0)])
def test_the_field_sums_its_levels_in_order(domain, warp):
    """Density logit = bias + Σ channel 0 of every level of every kind; features = the other
    channels, level after level, kind after kind. Dense and plane levels index the warped
    ball, sparse levels the point itself; footprints weigh each level by its own cells."""
    rng = np.random.default_rng(0)
    levels = _levels(domain, rng)
    field = GridField(domain, levels, network=ColorNetwork(hidden=8), density_bias=-1.0,
                      warp_radius=warp, antialias=True)
    assert field.params['plane0xy'] is levels[1].params['plane0xy']    # one dict, the field's
    x = field_inputs(domain)
    plain = grid_coordinates(domain, x)
    warped = grid_coordinates(domain, ball_warp(x, warp)) if domain == 'ball' else plain
    density, features = field._lookup(x)
    expected, expected_features = np.full(dr.width(x[0]), -1.0), []
    for lv in levels:
        for g in lv.lookup(warped if lv.warped else plain):
            expected = expected + np.array(g[0])
            expected_features += [np.array(v) for v in g[1:]]
    np.testing.assert_allclose(np.array(density), expected, rtol=1e-6, atol=1e-6)
    assert len(features) == len(expected_features) == (2 + 1 + 1) * 2     # 4 levels, 2 each
    for a, b in zip(features, expected_features):
        np.testing.assert_allclose(np.array(a), b, rtol=1e-6, atol=1e-6)
    # A footprint of 1.5 sparse texels: the sparse level weighs 0.5, coarser levels 1.
    if warp == 0.0:
        width = dr.full(mi.Float, 1.5 * levels[2].cell_size(0), dr.width(x[0]))
        weighted = field._lookup(x, width)[0]
        sparse0 = np.array(levels[2].lookup(plain)[0][0])
        np.testing.assert_allclose(np.array(weighted), expected - 0.5 * sparse0,
                                   rtol=1e-5, atol=1e-5)


def test_every_stored_entry_has_one_home_and_its_default():
    """Every entry of a grid field's stored config is taken by one class (:data:`GRID_CONFIG`),
    whose default is the entry's default, and the config round-trips through
    :func:`grid_field`."""
    field = grid_field('inverted_sphere', sparse=(16,), sparse_blocks=(4, 8, 16),
                       appearance_dims=2)
    assert set(field.config) - {'kind', 'domain'} == set(GRID_CONFIG)
    plain = grid_field('ball').config
    for entry in set(plain) - {'kind', 'domain'}:
        value = plain[entry]
        assert (list(value) if isinstance(value, (list, tuple)) else value) == \
            (list(grid_default(entry)) if isinstance(grid_default(entry), tuple)
             else grid_default(entry)), entry
    again = make_field(field.config)
    assert again.config == field.config and sorted(again.params) == sorted(field.params)


def test_levels_that_do_not_fit_together_are_refused():
    a = DenseLevels('ball', (4,), channels=3)
    with pytest.raises(ValueError, match='same channels'):
        GridField('ball', [a, PlaneLevels('ball', (8,), channels=4)])
    with pytest.raises(ValueError, match='one level set of each kind'):
        GridField('ball', [a, DenseLevels('ball', (8,), channels=3)])
    with pytest.raises(ValueError, match='domain'):
        GridField('ball', [DenseLevels('inverted_sphere', (4,), channels=3)])
    with pytest.raises(ValueError, match='invalid field config.*unexpected grid field'):
        make_field({'kind': 'grid', 'domain': 'ball', 'resolution': [8]})
    with pytest.raises(KeyError, match="no sparse level 'sparse3'"):
        grid_field('ball').set_bricks({'sparse3': np.arange(2)})
