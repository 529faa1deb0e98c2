"""Plane levels of the grid field (``--grid-planes``): three planes over the coordinate pairs,
summed. Closed forms of the lookup, their start at zero, gradients against central
differences, and the round trips through config, checkpoint and a training step."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.core import budget

from mi_nerfpp.files.checkpoint import load_checkpoint, save_checkpoint
from mi_nerfpp.training.config import TrainConfig
from mi_nerfpp.core.fields import grid_field, make_field
from mi_nerfpp.core.model import NeRFPPModel
from mi_nerfpp.training.optim import is_grid
from tests.helpers import TINY_GRID, field_inputs

AXES = {'xy': (0, 1), 'xz': (0, 2), 'yz': (1, 2)}


def _bilinear(plane, u, v, periodic_u):
    """Cell-centred bilinear interpolation of ``plane`` (H, W, C) at texture coordinates
    ``(u, v)`` in [0, 1]: u along W (periodic or clamped at the cell centres), v along H
    (clamped)."""
    h, w = plane.shape[:2]
    if not periodic_u:
        u = np.clip(u, 0.5 / w, 1 - 0.5 / w)
    v = np.clip(v, 0.5 / h, 1 - 0.5 / h)
    x, y = u * w - 0.5, v * h - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x1 = x0 + 1
    if periodic_u:
        x0, x1 = x0 % w, x1 % w
    else:
        x0, x1 = np.clip(x0, 0, w - 1), np.clip(x1, 0, w - 1)
    y1 = np.clip(y0 + 1, 0, h - 1)
    y0 = np.clip(y0, 0, h - 1)
    return ((plane[y0, x0] * (1 - fx) + plane[y0, x1] * fx) * (1 - fy)
            + (plane[y1, x0] * (1 - fx) + plane[y1, x1] * fx) * fy)


@pytest.mark.parametrize('domain', ['ball', 'inverted_sphere'])
def test_a_plane_level_is_the_sum_of_three_bilinear_planes(domain):
    """Closed form: with the dense levels at zero, density logit and features are the sums of
    the three planes' bilinear lookups at the coordinate pairs (longitude periodic, colatitude
    and s clamped to the cell centres in the background)."""
    from mi_nerfpp.core.geometry import grid_coordinates
    field = grid_field(domain, resolutions=(4,), channels=3, planes=(8,), density_bias=0.0)
    rng = np.random.default_rng(2)
    values = {k: rng.normal(size=v.shape).astype(np.float32) for k, v in field.params.items()
              if k.startswith('plane')}
    field.set_parameters(dict({k: mi.TensorXf(v) for k, v in values.items()},
                              grid0=dr.zeros(mi.TensorXf, field.params['grid0'].shape)))
    x = field_inputs(domain)
    coords = np.array([np.array(c) for c in grid_coordinates(domain, x)], dtype=np.float64)
    expected = 0.0
    for axes, (a, b) in AXES.items():
        expected = expected + _bilinear(values[f'plane0{axes}'].astype(np.float64), coords[a],
                                        coords[b], periodic_u=domain != 'ball' and a == 0)
    sigma, features = field.features(x)
    np.testing.assert_allclose(np.log(np.array(sigma)), expected[:, 0], rtol=1e-4, atol=1e-4)
    for c in range(2):
        # features: the dense level's two (zero), then the plane level's two
        np.testing.assert_allclose(np.array(features[2 + c]), expected[:, 1 + c], rtol=1e-4,
                                   atol=1e-4)
        np.testing.assert_array_equal(np.array(features[c]), 0.0)


def test_the_background_planes_are_periodic_in_longitude_only():
    field = grid_field('inverted_sphere', resolutions=(4,), channels=2, planes=(8,))
    rng = np.random.default_rng(4)
    field.set_parameters({k: mi.TensorXf(rng.normal(size=v.shape).astype(np.float32))
                          for k, v in field.params.items() if k.startswith('plane')})
    # Directions just either side of the seam (longitude 0 = 1) have nearly equal density.
    eps = 1e-4
    from mi_nerfpp.core.geometry import direction_to_equirect
    u, _ = direction_to_equirect(mi.Vector3f(1.0, 0.0, 0.0))
    assert abs(float(u[0]) % 1.0) < 1e-6 or abs(float(u[0]) - 0.5) < 1e-6
    d = [mi.Float(c) for c in np.array([[np.cos(t), 0.3, np.sin(t)] for t in (-eps, eps)]).T]
    n = np.sqrt(np.array(d[0]) ** 2 + 0.09 + np.array(d[2]) ** 2)
    x = [mi.Float(np.array(c) / n) for c in d] + [mi.Float([0.5, 0.5])]
    sigma = np.array(field.density(x))
    np.testing.assert_allclose(sigma[0], sigma[1], rtol=1e-2)


@pytest.mark.parametrize('domain', ['ball', 'inverted_sphere'])
def test_plane_levels_start_at_zero_and_change_nothing(domain):
    """A new field's plane levels add nothing: density and dense features are those of the
    same field without planes (same seed), and the planes' features are zero."""
    x = field_inputs(domain)
    with_planes = grid_field(domain, resolutions=(4, 8), channels=3, planes=(16,), seed=7)
    without = grid_field(domain, resolutions=(4, 8), channels=3, seed=7)
    sigma, features = with_planes.features(x)
    sigma_ref, features_ref = without.features(x)
    np.testing.assert_array_equal(np.array(sigma), np.array(sigma_ref))
    for a, b in zip(features, features_ref):
        np.testing.assert_array_equal(np.array(a), np.array(b))
    for f in features[len(features_ref):]:
        np.testing.assert_array_equal(np.array(f), 0.0)


@pytest.mark.parametrize('domain', ['ball', 'inverted_sphere'])
def test_plane_gradients_match_central_differences(domain):
    """d(Σ σ)/d(plane entries), by Dr.Jit's AD of the texture lookups, against central
    differences of the density at a few entries that the points reach."""
    field = grid_field(domain, resolutions=(4,), channels=2, planes=(8,), density_bias=-1.0,
                       seed=1)
    rng = np.random.default_rng(3)
    base = {k: rng.normal(scale=0.3, size=v.shape).astype(np.float32)
            for k, v in field.params.items() if k.startswith('plane')}
    x = field_inputs(domain, n=64)

    def total(values, grad=False):
        tensors = {k: mi.TensorXf(v) for k, v in values.items()}
        if grad:
            for t in tensors.values():
                dr.enable_grad(t)
        field.set_parameters(tensors)
        t = dr.sum(field.density(x))
        return t, tensors
    loss, tensors = total(base, grad=True)
    dr.backward(loss)
    checked = 0
    for key, tensor in tensors.items():
        grad = np.array(dr.grad(tensor)).reshape(base[key].shape)
        for idx in np.argwhere(np.abs(grad[..., 0]) > 1e-2)[:3]:
            at = (*idx, 0)
            h = 1e-2
            plus, minus = dict(base), dict(base)
            plus[key], minus[key] = base[key].copy(), base[key].copy()
            plus[key][at] += h
            minus[key][at] -= h
            fd = (float(total(plus)[0][0]) - float(total(minus)[0][0])) / (2 * h)
            np.testing.assert_allclose(grad[at], fd, rtol=1e-2, err_msg=f'{key}{at}')
            checked += 1
    assert checked >= 6          # every plane has entries the points reach


def test_plane_levels_round_trip_through_config_and_checkpoint(tmp_path):
    fg = dict(TINY_GRID, domain='ball', planes=[8])
    bg = dict(TINY_GRID, domain='inverted_sphere', planes=[8])
    model = NeRFPPModel.create(seed=2, fg_config=fg, bg_config=bg)
    rng = np.random.default_rng(0)
    model.set_parameters({k: mi.TensorXf(rng.normal(size=v.shape).astype(np.float32))
                          for k, v in model.parameters().items() if 'plane' in k})
    assert make_field(model.fg.config).planes.resolutions == [8]
    path = tmp_path / 'model.npz'
    save_checkpoint(path, model, meta={})
    again, _, _ = load_checkpoint(path)
    assert again.config == model.config
    x = field_inputs('ball')
    np.testing.assert_array_equal(np.array(again.fg.density(x)), np.array(model.fg.density(x)))
    # A field stored before plane levels has none.
    old = {k: v for k, v in model.fg.config.items() if k != 'planes'}
    assert make_field(old).planes.resolutions == []


def test_plane_options_reach_the_fields_and_the_learning_rates():
    cfg = TrainConfig.from_options(grid_levels=(16, 32), grid_planes=(64,), bg_grid_planes=(32,))
    assert cfg.field_config('grid', 'ball')['planes'] == [64]
    assert cfg.field_config('grid', 'inverted_sphere')['planes'] == [32]
    # The memory plan counts the planes' entries: 3·64² in the ball, 2·32² + 3·32·16 behind.
    sizing = cfg.sizing()
    assert budget.grid_plane_entries(sizing, 'ball') == [3 * 64 * 64 * 4]
    assert budget.grid_plane_entries(sizing, 'inverted_sphere') == [(2 * 32 * 32 + 3 * 32 * 16) * 4]
    field = make_field(cfg.field_config('grid', 'inverted_sphere'))
    entries = sum(np.prod(v.shape) for k, v in field.params.items() if k.startswith('plane'))
    assert entries == budget.grid_plane_entries(sizing, 'inverted_sphere')[0]
    assert is_grid('fg.plane0xy') and is_grid('bg.grid1') and is_grid('fg.sparse0')
    assert not is_grid('fg.color.rest.0')
    with pytest.raises(Exception, match='grid_planes|grid-planes'):
        TrainConfig.from_options(grid_planes=(1,))


def test_a_training_step_updates_the_planes(capture, tmp_path):
    from mi_nerfpp.data import load_dataset
    from mi_nerfpp.training.train import Trainer
    cfg = TrainConfig.from_options(iterations=3, batch_rays=256, grid_levels=(8, 16),
                                   grid_planes=(32,), checkpoint_every=0, preview_every=0)
    tr = Trainer(load_dataset(capture), str(tmp_path), cfg)
    tr.run()
    planes = {k: np.array(v) for k, v in tr.model.parameters().items() if 'plane' in k}
    assert len(planes) == 6 and all(np.isfinite(v).all() for v in planes.values())
    assert all(np.abs(v).max() > 0 for v in planes.values())      # every plane learned
