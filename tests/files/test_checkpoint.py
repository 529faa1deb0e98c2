"""Checkpoint format: round trip, rendering from a file, and clear errors."""
import json
import os

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.files.checkpoint import VERSION, CheckpointError, load_checkpoint, save_checkpoint
from mi_nerfpp.core.frame import Normalization
from mi_nerfpp.core.model import NeRFPPModel
from tests.helpers import TINY_GRID, scene_dict, tiny_model
from tests.robustness.common import error_line


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
    with pytest.raises(CheckpointError, match="invalid config: the ball field entry 'kind' must be "
                       "'grid', 'nerf' or 'vanilla', got 'hashgrid'"):
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
        assert str(z['format']) == 'mi-nerfpp-checkpoint' and int(z['version']) == VERSION == 4
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



# --------------------------------------------------------------------- render settings

def test_checkpoint_carries_the_render_settings_and_the_integrator_reads_them(tmp_path):
    import dataclasses

    from mi_nerfpp.core.render import Sampling
    m = tiny_model(seed=4)
    m.sampling = Sampling(fg_samples=5, bg_samples=6, fine_samples=3, near=0.02)
    path = tmp_path / 'm.npz'
    save_checkpoint(path, m)
    assert load_checkpoint(path)[0].render_settings == m.render_settings
    assert m.render_settings.background and m.render_settings.composite == 'linear'
    bare = scene_dict()
    bare['integrator'] = {'type': 'nerfpp', 'checkpoint': str(path)}   # no sample counts
    scene = mi.load_dict(bare)
    assert scene.integrator().sampling == m.sampling and scene.integrator().background
    # It renders what the same counts given in the XML render.
    explicit = mi.load_dict(scene_dict(checkpoint=str(path), fg_samples=5, bg_samples=6,
                                       fine_samples=3, near=0.02))
    np.testing.assert_array_equal(np.array(mi.render(scene, seed=0)),
                                  np.array(mi.render(explicit, seed=0)))
    # XML parameters override the model's settings one by one, for a model set from Python too.
    bare['integrator'].update(fine_samples=9, background=False)
    integrator = mi.load_dict(bare).integrator()
    assert integrator.sampling == dataclasses.replace(m.sampling, fine_samples=9)
    assert integrator.background is False
    integrator.set_model(tiny_model(background=False))
    assert integrator.sampling == Sampling(fine_samples=9)      # the new model's, overridden
    handed = mi.load_dict({'type': 'nerfpp'})
    handed.set_model(tiny_model(background=False))
    assert handed.background is False                           # a bounded model: no background


def _as_before_render_settings(path, flat_config):
    """Rewrite a checkpoint as written before the render settings and the config groups: no
    ``sampling`` in the model config, the training config flat in ``meta``."""
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    config = json.loads(str(arrays['config']))
    del config['sampling']
    config['meta']['config'] = flat_config
    arrays['config'] = np.array(json.dumps(config))
    np.savez(path, **arrays)


def test_old_checkpoints_render_with_the_sample_counts_of_their_training(tmp_path):
    from mi_nerfpp.core.render import Sampling
    path = tmp_path / 'm.npz'
    save_checkpoint(path, tiny_model())
    _as_before_render_settings(path, {'model': 'nerf', 'fg_samples': 12, 'bg_samples': 4,
                                      'fine_samples': 6})
    # The NeRF baseline rendered both volumes' budget in its one volume.
    assert load_checkpoint(path)[0].sampling == Sampling(16, 4, 12)
    save_checkpoint(path, tiny_model())
    _as_before_render_settings(path, None)      # no training config: the render defaults
    assert load_checkpoint(path)[0].sampling == Sampling()


def test_old_checkpoints_with_grouped_training_configs_render_with_their_sample_counts(
        tmp_path):
    from mi_nerfpp.core.render import SKIPPING, Sampling
    path = tmp_path / 'm.npz'
    save_checkpoint(path, tiny_model())
    _as_before_render_settings(path, {'model': {'kind': 'nerfpp'},
                                      'sampling': {'fg_samples': 8, 'fine_samples': 2}})
    assert load_checkpoint(path)[0].sampling == Sampling(8, SKIPPING.bg_samples, 2)
    save_checkpoint(path, tiny_model())
    _as_before_render_settings(path, {'model': {'kind': 'nerf'}, 'sampling': {}})
    assert load_checkpoint(path)[0].sampling == Sampling.of_model(
        'nerf', SKIPPING.fg_samples, SKIPPING.bg_samples, SKIPPING.fine_samples)


# The training config of a checkpoint written before the config groups (flat, as
# ``dataclasses.asdict`` of the flat TrainConfig of c93a164 stored it), with TINY_RUN's values.
FLAT_TINY_RUN = {
    "iterations": 5, "minutes": None, "model": "nerfpp", "field": "grid", "bg_field": "grid",
    "batch_rays": 256, "fg_samples": 8, "bg_samples": 8, "fine_samples": 8, "lr_grid": 0.1,
    "lr_mlp": 0.005, "lazy_adam": False, "adam_beta2": 0.999, "lr_final": 0.1,
    "color_loss": "charbonnier", "distortion": 0.01, "distortion_scope": "ray",
    "opacity_entropy": 0.0, "entropy_start": 0.0, "sparsity": [0.01],
    "sparsity_start": [0.15, 0.5], "near_gradient": 0.5, "tv": 0.0, "tv_cells": 16384,
    "density_bias": 0.0, "occupancy": True, "occupancy_res": 64, "occupancy_threshold": 0.3,
    "occupancy_every": 16, "grid_levels": [32, 128], "fg_warp": 0.0, "bg_grid_levels": None,
    "bg_s_ratio": [0.5], "coarse_to_fine": [], "grid_channels": 4, "dir_octaves": 2,
    "color_layers": 1, "color_width": 32, "seed": 0, "freeze": True, "checkpoint_every": 0,
    "preview_every": 0, "downscale": 1, "background": [1.0, 1.0, 1.0], "composite": "linear",
    "appearance": False, "lr_appearance": 0.02, "appearance_prior": 0.001,
    "refine_poses": False, "lr_poses": 0.001, "poses_start": 0.02}   # (today's default)


def test_a_checkpoint_with_a_flat_training_config_loads_evaluates_and_resumes(
        tiny_run, capture, tmp_path, capsys):
    import shutil

    from mi_nerfpp.commands.cli import main
    from mi_nerfpp.training.config import TrainConfig
    from mi_nerfpp.core.render import Sampling
    from mi_nerfpp.jobs.run import evaluate_run, open_run
    from tests.helpers import TINY_RUN
    run = tmp_path / 'old'
    shutil.copytree(tiny_run, run)
    trained = json.loads((run / 'metrics.json').read_text())
    _as_before_render_settings(run / 'model.npz', FLAT_TINY_RUN)
    model, meta, cfg, _ = open_run(str(run))
    assert model.sampling == Sampling(8, 8, 8) and model.render_settings.background
    assert cfg == TrainConfig.from_stored(trained['config'])       # the same run's config
    assert cfg.schedule.iterations == 5 and cfg.schedule.batch_rays == 256
    # Evaluated again: the same render settings, the same held-out scores.
    again = evaluate_run(str(run))
    assert again['test']['psnr'] == pytest.approx(trained['test']['psnr'], abs=1e-3)
    assert again['config'] == trained['config']
    # Resumed with other model options: refused, naming the flag; with the same: continued.
    longer = ['7' if before == '--iterations' else a for before, a in zip([''] + TINY_RUN, TINY_RUN)]
    assert main(['optimize', capture, '--out', str(run), '--resume', '--field', 'nerf']
                + longer) == 1
    assert "--field: the checkpoint's weights have 'grid'" in capsys.readouterr().err
    assert main(['optimize', capture, '--out', str(run), '--resume'] + longer) == 0
    model, meta, _ = load_checkpoint(run / 'model.npz')
    assert meta['iteration'] == 7 and meta['config']['schedule']['iterations'] == 7
    assert model.sampling == Sampling(8, 8, 8)



@pytest.mark.parametrize('retired, words', [({'tv': 0.01}, '--tv 0.01'),
                                            ({'coarse_to_fine': [0.3, 0.6]},
                                             '--coarse-to-fine 0.3 0.6'),
                                            ({'composite': 'srgb'}, '--composite srgb')])
def test_a_run_trained_with_a_removed_option_evaluates_but_is_not_resumed(
        tiny_run, capture, tmp_path, capsys, retired, words):
    """Options measured and not kept were removed (docs/experiments.md); a run that used one
    still evaluates with its weights, and ``--resume`` refuses it in one line naming the option
    and the commit that still has it. At their off values they were resumed above."""
    import shutil

    from mi_nerfpp.commands.cli import main
    from mi_nerfpp.jobs.run import evaluate_run
    from mi_nerfpp.training.config import RETIRED_AFTER
    run = tmp_path / 'old'
    shutil.copytree(tiny_run, run)
    trained = json.loads((run / 'metrics.json').read_text())
    with np.load(run / 'model.npz') as z:
        arrays = {k: z[k] for k in z.files}
    config = json.loads(str(arrays['config']))
    if 'composite' in retired:       # an sRGB model of before linear compositing
        config['color_space'], config['composite'] = 'srgb', 'srgb'
    else:
        config['meta']['config']['losses' if 'tv' in retired else 'schedule'].update(retired)
    arrays['config'] = np.array(json.dumps(config))
    np.savez(run / 'model.npz', **arrays)
    again = evaluate_run(str(run))
    if 'composite' not in retired:    # (decoded otherwise: another image, as trained then)
        assert again['test']['psnr'] == pytest.approx(trained['test']['psnr'], abs=1e-3)
    assert main(['optimize', capture, '--out', str(run), '--resume', '--iterations', '7']) == 1
    err = capsys.readouterr().err
    assert error_line(err, "optimize") == (
        f'{run / "model.npz"} was trained with {words}, which this version no longer has '
        f'(measured and not kept: docs/experiments.md): resume it with mi-nerfpp at commit '
        f'{RETIRED_AFTER} or before, or evaluate and render it as it is')


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


def test_the_background_may_colour_every_sample_while_the_foreground_defers(tmp_path):
    """``--bg-color`` (default: per sample) is the background's colour mode apart from the
    foreground's ``--color`` (default: deferred). The fields get their own modes, a checkpoint
    keeps them, and a checkpoint stored before the option (its background coloured as its
    ``--color``) refuses to resume as another."""
    from mi_nerfpp.training.config import TrainConfig
    config = TrainConfig()
    m = config.model
    assert config.field_config(m.field, 'ball')['color'] == 'deferred'
    assert config.field_config(m.bg_field, 'inverted_sphere')['color'] == 'sample'
    other = TrainConfig.from_options(color='sample', bg_color='deferred')
    assert other.field_config(m.field, 'ball')['color'] == 'sample'
    assert other.field_config(m.bg_field, 'inverted_sphere')['color'] == 'deferred'
    model = NeRFPPModel.create(seed=1, fg_config=dict(TINY_GRID, domain='ball'),
                               bg_config=dict(TINY_GRID, domain='inverted_sphere', color='sample'))
    path = tmp_path / 'm.npz'
    save_checkpoint(path, model)
    loaded, _, _ = load_checkpoint(path)
    assert loaded.fg.deferred and not loaded.bg.deferred
    stored = TrainConfig.from_options(bg_color='deferred').to_dict()
    del stored['model']['bg_color']
    assert TrainConfig.from_options(bg_color='deferred').resume_conflicts(stored) == []
    assert config.resume_conflicts(stored) == [
        "--bg-color: the checkpoint has 'deferred', this run asks for 'sample'"]


def test_every_older_readable_version_has_one_migration_step():
    """The migration chain has one step per version before today's, so that an older file's
    config is brought to today's layout step by step (a new version appends its step)."""
    from mi_nerfpp.files.checkpoint import MIGRATIONS, READABLE_VERSIONS, migrate_config
    assert sorted(MIGRATIONS) == list(range(1, VERSION))
    assert READABLE_VERSIONS == tuple(range(1, VERSION + 1))
    today = tiny_model().config
    assert migrate_config(today, VERSION) == json.loads(json.dumps(today))   # nothing to do


def _as_version(model, version, flat_training=None):
    """The arrays of ``model``'s checkpoint rewritten as a file of an older ``version``: no
    colour mode or antialiasing in its grid fields before 3, top-level center and scale in 1,
    and (``flat_training``) a flat training config in ``meta``."""
    path_config = dict(model.config, meta={'config': flat_training} if flat_training else {})
    config = json.loads(json.dumps(path_config))
    del config['sampling']
    if version < 3:
        for key in ('fg', 'bg'):
            for entry in ('color', 'antialias'):
                config[key].pop(entry)
    if version < 2:
        config.update(config.pop('normalization'))
    return config


@pytest.mark.parametrize('version', [1, 2])
def test_migrated_configs_describe_the_weights_of_older_files(version):
    from mi_nerfpp.files.checkpoint import migrate_config
    model = tiny_model()
    config = migrate_config(_as_version(model, version), version)
    assert config['normalization'] == model.normalization.to_config()
    for key in ('fg', 'bg'):        # before version 3: colour every sample, no antialiasing
        assert config[key]['color'] == 'sample' and config[key]['antialias'] is False


def _rewrite_run_as(run, version, flat=True):
    """Turn the checkpoint of a run folder into one of an older ``version`` whose training
    config is flat (written before the option groups) and knows neither --color, --bg-color
    nor --antialias."""
    path = run / 'model.npz'
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    stored = json.loads(str(arrays['config']))
    training = {}
    for values in stored['meta']['config'].values():
        training.update(values)
    for name in ('color', 'bg_color', 'antialias', 'grid_planes', 'bg_grid_planes'):
        training.pop(name)
    for key in ('fg', 'bg'):
        for entry in ('color', 'antialias', 'planes'):
            stored[key].pop(entry)
    if version < 2:
        stored.update(stored.pop('normalization'))
    stored['meta']['config'] = training if flat else stored['meta']['config']
    arrays['config'], arrays['version'] = np.array(json.dumps(stored)), np.array(version)
    np.savez(path, **arrays)


@pytest.mark.parametrize('version', [1, 2])
def test_resuming_an_older_run_records_the_config_of_its_weights(tiny_run, capture, tmp_path,
                                                                   capsys, version):
    """A run of an older version, resumed with today's defaults, is refused naming each option
    its weights differ in, the value to resume with and why (the file's version); resumed with
    those, its recorded config describes the weights, and the next resume is told the same."""
    import shutil

    from mi_nerfpp.commands.cli import main
    from mi_nerfpp.jobs.run import open_run
    from tests.helpers import TINY_RUN
    run = tmp_path / 'old'
    shutil.copytree(tiny_run, run)
    _rewrite_run_as(run, version)
    model, _, cfg, _ = open_run(str(run))          # read: the config of its weights
    assert (cfg.model.color, cfg.model.bg_color, cfg.model.antialias) == ('sample', 'sample',
                                                                          False)
    longer = ['7' if before == '--iterations' else a for before, a in zip([''] + TINY_RUN, TINY_RUN)]
    assert main(['optimize', capture, '--out', str(run), '--resume'] + longer) == 1
    err = capsys.readouterr().err
    assert "--color: the checkpoint's weights have 'sample', this run asks for 'deferred' " \
           "(resume with --color sample)" in err
    assert "--antialias: the checkpoint's weights have False, this run asks for True " \
           "(resume with --no-antialias)" in err
    assert f'(a version {version} checkpoint)' in err and 'colour MLP at every sample' in err
    assert '--bg-color' not in err          # the background coloured every sample, as asked
    assert main(['optimize', capture, '--out', str(run), '--resume', '--color', 'sample',
                 '--no-antialias'] + longer) == 0
    model, meta, _ = load_checkpoint(run / 'model.npz')
    recorded = meta['config']['model']
    assert (recorded['color'], recorded['bg_color'], recorded['antialias']) == (
        model.fg.color_mode, model.bg.color_mode, model.fg.antialias) == ('sample', 'sample',
                                                                          False)
    capsys.readouterr()
    assert main(['optimize', capture, '--out', str(run), '--resume', '--iterations', '8']
                + longer[2:]) == 1
    err = capsys.readouterr().err          # today's file: no version note
    assert "--color: the checkpoint's weights have 'sample'" in err and 'version' not in err


def test_an_option_stored_in_another_group_keeps_its_value_and_unknown_ones_are_said(
        tiny_run, capture, tmp_path, capsys):
    """A grouped training config whose option sits in another group than today's is read by
    the option's name; an entry no option of this version names is announced on resume, not
    dropped silently; the weights decide what shapes the model whatever the config says."""
    import shutil

    from mi_nerfpp.commands.cli import main
    from mi_nerfpp.training.config import TrainConfig
    from tests.helpers import TINY_RUN
    stored = TrainConfig.from_options(color='sample', batch_rays=77).to_dict()
    stored['data']['color'] = stored['model'].pop('color')        # moved between groups
    stored['schedule']['batch_rays'] = stored['schedule'].pop('batch_rays')
    stored['losses']['future_prior'] = 0.5
    assert TrainConfig.stored_options(stored)['color'] == 'sample'
    assert TrainConfig.from_stored(stored).model.color == 'sample'
    assert TrainConfig.unknown_stored(stored) == ['losses.future_prior']
    run = tmp_path / 'moved'
    shutil.copytree(tiny_run, run)
    path = run / 'model.npz'
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    config = json.loads(str(arrays['config']))
    training = config['meta']['config']
    training['sampling']['grid_levels'] = training['model'].pop('grid_levels')
    training['model']['color'] = 'sample'        # contradicts the weights: they decide
    training['losses']['future_prior'] = 0.5
    arrays['config'] = np.array(json.dumps(config))
    np.savez(path, **arrays)
    longer = ['7' if before == '--iterations' else a for before, a in zip([''] + TINY_RUN, TINY_RUN)]
    levels = TrainConfig().model.grid_levels
    assert main(['optimize', capture, '--out', str(run), '--resume', '--grid-levels',
                 *[str(2 * r) for r in levels]] + longer) == 1
    err = capsys.readouterr().err
    assert f'--grid-levels: the checkpoint has {list(levels)!r}' in err
    assert main(['optimize', capture, '--out', str(run), '--resume'] + longer) == 0
    assert ('losses.future_prior, which this version of mi-nerfpp does not know'
            in capsys.readouterr().out)
    assert load_checkpoint(path)[1]['config']['model']['color'] == 'deferred'


def test_a_config_stored_by_15f237e_with_the_background_sparse_levels_unset_loads():
    """15f237e stored ``bg_grid_sparse: None`` for "as ``--grid-sparse``" (the run folders of
    gt_plaza measured that day): such a config opens with the foreground's sparse levels in the
    background, as it trained, instead of failing on the None."""
    from mi_nerfpp.training.config import TrainConfig
    stored = TrainConfig().to_dict()
    stored['model'].update(grid_sparse=[256], bg_grid_sparse=None)
    assert TrainConfig.from_stored(stored).model.bg_grid_sparse == (256,)
    stored['model'].update(grid_sparse=[])
    assert TrainConfig.from_stored(stored).model.bg_grid_sparse == ()
