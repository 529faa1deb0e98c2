"""Checkpoint format: round trip, rendering from a file, and clear errors."""
import json
import os

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.checkpoint import VERSION, CheckpointError, load_checkpoint, save_checkpoint
from mi_nerfpp.frame import Normalization
from mi_nerfpp.model import NeRFPPModel
from tests.helpers import TINY_GRID, scene_dict, tiny_model


def test_round_trip_preserves_parameters_config_and_normalization(tmp_path):
    m = tiny_model(seed=3)
    m.normalization, m.color_space = Normalization(np.array([1.0, 2.0, -3.0]), 0.5), 'linear'
    path = tmp_path / 'model.npz'
    save_checkpoint(path, m, meta={'iteration': 7}, state={'adam.t': np.array(7)})
    m2, meta, state = load_checkpoint(path)
    assert meta == {'iteration': 7} and int(state['adam.t']) == 7
    assert m2.config == m.config
    for k, v in m.parameters().items():
        np.testing.assert_array_equal(np.array(v), np.array(m2.parameters()[k]))
    assert os.listdir(tmp_path) == ['model.npz']    # no temporary file left behind


def test_render_from_checkpoint_equals_render_from_model(tmp_path):
    m = tiny_model(seed=5)
    path = tmp_path / 'm.npz'
    save_checkpoint(path, m)
    a = mi.load_dict(scene_dict(checkpoint=str(path)))
    b = mi.load_dict(scene_dict())
    b.integrator().set_model(m)
    np.testing.assert_array_equal(np.array(mi.render(a, seed=0)), np.array(mi.render(b, seed=0)))


def test_pure_mlp_models_round_trip(tmp_path):
    for kind in ('nerf', 'vanilla'):
        m = NeRFPPModel.create(field=kind, seed=1)
        save_checkpoint(tmp_path / f'{kind}.npz', m)
        m2, _, _ = load_checkpoint(tmp_path / f'{kind}.npz')
        assert m2.fg.kind == kind and m2.bg.config == m.bg.config


def test_missing_file_names_the_path(tmp_path):
    with pytest.raises(CheckpointError, match='nope.npz: checkpoint not found'):
        load_checkpoint(tmp_path / 'nope.npz')


def test_garbage_file_is_rejected(tmp_path):
    p = tmp_path / 'bad.npz'
    p.write_bytes(b'this is not a zip archive')
    with pytest.raises(CheckpointError, match='bad.npz: not a mi-nerfpp checkpoint'):
        load_checkpoint(p)


def test_foreign_npz_is_rejected(tmp_path):
    p = tmp_path / 'other.npz'
    np.savez(p, weights=np.zeros(3))
    with pytest.raises(CheckpointError, match="other.npz: not a mi-nerfpp checkpoint"):
        load_checkpoint(p)


def _rewrite(path, **changes):
    z = dict(np.load(path, allow_pickle=False))
    z.update(changes)
    np.savez(path, **z)


def test_config_parameter_mismatch_names_the_parameter(tmp_path):
    p = tmp_path / 'm.npz'
    save_checkpoint(p, tiny_model())
    cfg = json.loads(str(np.load(p)['config']))
    cfg['fg']['resolutions'] = [4, 16]          # grid1 in the file is 8^3, config now says 16^3
    _rewrite(p, config=np.array(json.dumps(cfg)))
    with pytest.raises(CheckpointError, match=r"m.npz: parameter 'fg.grid1' has shape"):
        load_checkpoint(p)


def test_missing_parameter_and_bad_kind_and_nan(tmp_path):
    p = tmp_path / 'm.npz'
    save_checkpoint(p, tiny_model())
    z = dict(np.load(p))
    del z['param/bg.grid0']
    np.savez(p, **z)
    with pytest.raises(CheckpointError, match=r"missing \['bg.grid0'\]"):
        load_checkpoint(p)

    save_checkpoint(p, tiny_model())
    cfg = json.loads(str(np.load(p)['config']))
    cfg['fg']['kind'] = 'hashgrid'
    _rewrite(p, config=np.array(json.dumps(cfg)))
    with pytest.raises(CheckpointError, match="invalid config: unknown field kind 'hashgrid'"):
        load_checkpoint(p)

    save_checkpoint(p, tiny_model())
    g = np.load(p)['param/fg.grid0'].copy()
    g[0, 0, 0, 0] = np.nan
    _rewrite(p, **{'param/fg.grid0': g})
    with pytest.raises(CheckpointError, match="'fg.grid0' contains NaN"):
        load_checkpoint(p)


def test_integrator_reports_bad_checkpoint_path(tmp_path):
    with pytest.raises(Exception, match="missing.npz' not found \\(looked for "):
        mi.load_dict(scene_dict(checkpoint=str(tmp_path / 'missing.npz')))


def test_parameters_are_float32_arrays_without_pickle(tmp_path):
    p = tmp_path / 'm.npz'
    save_checkpoint(p, tiny_model())
    with np.load(p, allow_pickle=False) as z:
        assert str(z['format']) == 'mi-nerfpp-checkpoint' and int(z['version']) == VERSION == 3
        params = [k for k in z.files if k.startswith('param/')]
        assert params and all(z[k].dtype == np.float32 for k in params)
    assert TINY_GRID['kind'] == 'grid' and dr.width(tiny_model().fg.params['grid0'].array) > 0


def test_version_1_files_with_top_level_center_and_scale_are_still_read(tmp_path):
    m = tiny_model(seed=2)
    m.normalization = Normalization((1.0, -2.0, 0.5), 0.25)
    p = tmp_path / 'v1.npz'
    save_checkpoint(p, m)
    cfg = json.loads(str(np.load(p)['config']))
    cfg.update(cfg.pop('normalization'))        # the version 1 layout
    _rewrite(p, config=np.array(json.dumps(cfg)), version=np.array(1))
    m2, _, _ = load_checkpoint(p)
    assert m2.normalization == m.normalization
    for k, v in m.parameters().items():
        np.testing.assert_array_equal(np.array(v), np.array(m2.parameters()[k]))



def test_version_2_grid_fields_keep_their_per_sample_colour(tmp_path):
    """Files written before deferred colour (version 2) hold grid fields whose MLP coloured every
    sample: they load as ``color='sample'`` and render as such; version 3 files say which."""
    m = tiny_model(seed=4)
    path = tmp_path / 'm.npz'
    save_checkpoint(path, m)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    config = json.loads(str(arrays['config']))
    assert config['fg']['color'] == 'deferred' and config['bg']['color'] == 'deferred'
    for key in ('fg', 'bg'):
        del config[key]['color']
    arrays['config'], arrays['version'] = np.array(json.dumps(config)), np.array(2)
    old = tmp_path / 'old.npz'
    np.savez(old, **arrays)
    m2, _, _ = load_checkpoint(old)
    assert m2.fg.color_mode == 'sample' and m2.bg.color_mode == 'sample'
    assert not m2.fg.deferred
    for k, v in m.parameters().items():
        np.testing.assert_array_equal(np.array(v), np.array(m2.parameters()[k]))
    # It renders as the same parameters in fields that colour every sample.
    per_sample = NeRFPPModel.create(seed=4, fg_config=dict(TINY_GRID, domain='ball', color='sample'),
                                    bg_config=dict(TINY_GRID, domain='inverted_sphere',
                                                   color='sample'))
    per_sample.set_parameters(m.parameters())
    a = mi.load_dict(scene_dict(checkpoint=str(old)))
    b = mi.load_dict(scene_dict())
    b.integrator().set_model(per_sample)
    np.testing.assert_array_equal(np.array(mi.render(a, seed=0)), np.array(mi.render(b, seed=0)))
