"""Training end to end on a tiny capture rendered by the tests: PSNR rises, runs resume."""
import json
import os
import subprocess
import sys

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.files.checkpoint import load_checkpoint
from mi_nerfpp.data import load_dataset
from mi_nerfpp.training import priors
from mi_nerfpp.training.evaluate import evaluate_split
from mi_nerfpp.training.config import TrainConfig, per_volume
from mi_nerfpp.training.options import values
from mi_nerfpp.training.error_map import ErrorMap
from mi_nerfpp.training.errors import TrainingError
from mi_nerfpp.training.train import Trainer
from tests.helpers import one_thread, straight_and_resumed

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SMALL = dict(batch_rays=512, fg_samples=16, bg_samples=16, fine_samples=16,
             checkpoint_every=0, preview_every=0)


@pytest.fixture(scope='module')
def dataset(capture):
    return load_dataset(capture)


def test_training_raises_held_out_psnr_well_above_untrained(dataset, tmp_path):
    tr = Trainer(dataset, str(tmp_path), TrainConfig.from_options(iterations=200, **SMALL))
    before = evaluate_split(tr.model, tr.test, str(tmp_path / 'before'))['psnr']
    assert tr.run()
    after = evaluate_split(tr.model, tr.test, str(tmp_path / 'after'))['psnr']
    assert after > before + 6.0, (before, after)
    assert after > 18.0, after
    assert os.path.exists(tmp_path / 'after' / 'test_000.exr')


def _params(model):
    return {k: np.array(v) for k, v in model.parameters().items()}


def test_resume_continues_where_the_run_stopped(dataset, tmp_path):
    # Same batches, same optimizer moments, same occupancy grid and priors: on one thread the
    # resumed run ends bit for bit where the straight run does (see tests.helpers.one_thread).
    straight, resumed = straight_and_resumed(
        dataset, tmp_path, TrainConfig.from_options(iterations=12, error_rays=0.8, **SMALL),
        stop_at=6)
    a, b = _params(straight.model), _params(resumed.model)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    _, meta, state = load_checkpoint(tmp_path / 'b' / 'model.npz')
    assert meta['iteration'] == 12 and any(k.startswith('adam.m/') for k in state)
    # The error map that draws the rays resumes with the run.
    assert straight.error_map is not None and straight.error_map.visited.any()
    np.testing.assert_array_equal(straight.error_map.error, resumed.error_map.error)
    np.testing.assert_array_equal(state['error_map'], resumed.error_map.error)


def test_the_error_map_draws_rays_where_the_error_is(dataset, tmp_path):
    # After a short run the map holds each tile's training error (squared, encoded colours);
    # the tiles it rates worst get more of the next batches' rays than uniform draws would.
    tr = Trainer(dataset, str(tmp_path),
                 TrainConfig.from_options(iterations=60, error_rays=0.8, **SMALL))
    tr.run()
    m = tr.error_map
    assert m.visited.mean() > 0.9
    seen = m.error[m.visited]
    assert 1e-5 < np.median(seen) < 0.05 and seen.max() > 2 * np.median(seen)
    worst = m.visited & (m.error >= np.quantile(seen, 0.9))
    index, tiles = m.draw(np.random.default_rng(0), 20_000, 1)
    assert np.all(index < tr.rays.size)
    drawn = np.isin(tiles, np.flatnonzero(worst)).mean()
    uniform = ErrorMap(*m.shape, m.tile, 0.0).probabilities()[worst].sum()
    assert drawn == pytest.approx(m.probabilities()[worst].sum(), abs=0.015)
    assert drawn > 1.5 * uniform, (drawn, uniform)
    off = Trainer(dataset, str(tmp_path / 'off'),
                  TrainConfig.from_options(iterations=1, error_rays=0, **SMALL))
    assert off.error_map is None
    # Not given: uniform.
    chosen = Trainer(dataset, str(tmp_path / 'chosen'),
                     TrainConfig.from_options(iterations=1, **SMALL))
    assert chosen.error_map is None and chosen.cfg.schedule.error_rays == 0.0


def test_interrupt_saves_a_checkpoint(dataset, tmp_path):
    tr = Trainer(dataset, str(tmp_path), TrainConfig.from_options(iterations=50, **SMALL))

    def stop_at_7(trainer, loss, psnr):
        if trainer.iteration == 7:
            raise KeyboardInterrupt

    assert tr.run(on_step=stop_at_7) is False
    _, meta, _ = load_checkpoint(tmp_path / 'model.npz')
    assert meta['iteration'] == 7


def test_nan_loss_stops_and_keeps_last_good_checkpoint(dataset, tmp_path):
    tr = Trainer(dataset, str(tmp_path),
                 TrainConfig.from_options(iterations=20, **dict(SMALL, checkpoint_every=4)))

    def poison(trainer, loss, psnr):
        if trainer.iteration == 6:
            k = 'fg.color.rest.layers.1.bias'
            bad = mi.TensorXf(np.full(trainer.opt[k].shape, np.nan, np.float32))
            trainer.opt[k] = bad

    with pytest.raises(TrainingError, match=r'loss became nan at iteration 7.*iteration 4'):
        tr.run(on_step=poison)
    model, meta, _ = load_checkpoint(tmp_path / 'model.npz')   # finite (the loader checks)
    assert meta['iteration'] == 4


def test_nerf_baseline_has_one_volume_in_a_larger_sphere(dataset, tmp_path):
    tr = Trainer(dataset, str(tmp_path),
                 TrainConfig.from_options(iterations=2, model='nerf', **SMALL))
    assert tr.model.bg is None
    radii = [np.linalg.norm(c.center) for c in tr.train.cameras]
    assert max(radii) == pytest.approx(1 / 8, rel=1e-6)
    assert tr.model.normalization.scale == pytest.approx(dataset.normalization.scale * 1.1 / 8)
    assert tr.model.sampling.fg_samples == 32 and tr.model.sampling.fine_samples == 32
    # --near-gradient is a length of NeRF++'s frame: shrunk with the baseline's cameras.
    assert tr.near_gradient == pytest.approx(tr.cfg.losses.near_gradient * 1.1 / 8)
    tr.run()
    nerfpp = Trainer(dataset, str(tmp_path / 'nerfpp'),
                     TrainConfig.from_options(iterations=1, **SMALL))
    assert nerfpp.near_gradient == tr.cfg.losses.near_gradient


def test_resume_with_other_model_options_is_refused_naming_the_difference(dataset, tmp_path):
    Trainer(dataset, str(tmp_path), TrainConfig.from_options(iterations=1, **SMALL)).run()
    for change, flag in ((dict(field='nerf'), '--field'), (dict(bg_field='vanilla'), '--bg-field'),
                         (dict(grid_levels=(32, 64)), '--grid-levels'),
                         (dict(model='nerf'), '--model')):
        with pytest.raises(TrainingError, match=f"cannot be resumed.*{flag}: the checkpoint"
                                                 f"('s weights)? has?"):
            Trainer(dataset, str(tmp_path),
                    TrainConfig.from_options(iterations=2, **SMALL, **change), resume=True)
    # Options that do not shape the model may change.
    tr = Trainer(dataset, str(tmp_path),
                 TrainConfig.from_options(iterations=2, **dict(SMALL, lr_mlp=1e-3)), resume=True)
    assert tr.iteration == 1


def test_optimize_options_come_from_train_config():
    import argparse
    import dataclasses

    from mi_nerfpp.commands.cli import build_parser
    from mi_nerfpp.training.options import groups, options_of
    args = build_parser().parse_args(['optimize'])
    cfg = TrainConfig.from_options(**values(args, TrainConfig))
    assert dataclasses.asdict(cfg) == dataclasses.asdict(TrainConfig())
    args = build_parser().parse_args(['optimize', '--samples', '8', '9', '10', '--grid-levels',
                                      '16', '--background', '0,0.5,1', '--lr-final', '0.5'])
    cfg = TrainConfig.from_options(**values(args, TrainConfig))
    s = cfg.sampling
    assert (s.fg_samples, s.bg_samples, s.fine_samples) == (8, 9, 10)
    assert cfg.model.grid_levels == (16,) and cfg.data.background == (0.0, 0.5, 1.0)
    assert cfg.optimizer.lr_final == 0.5
    optimize = build_parser()._subparsers._group_actions[0].choices['optimize']
    helps = {a.dest: a.help for a in optimize._actions if isinstance(a, argparse.Action)}
    for _, f in options_of(TrainConfig):
        assert f.metadata.get('help'), f.name            # every option documents itself
    assert f'(default: {TrainConfig().schedule.batch_rays})' in helps['batch_rays']
    # --help shows one section per group of the config, each with its options.
    sections = {g.title: [a.dest for a in g._group_actions] for g in optimize._action_groups}
    for name, sub, meta in groups(TrainConfig):
        assert sections[meta['group']], name
    assert 'batch_rays' in sections['schedule'] and 'lr_mlp' in sections['optimizer']
    assert '_joint__samples' in sections['sampling'] and 'model' in sections['model']
    args = build_parser().parse_args(['optimize', '--no-occupancy'])   # booleans switch both ways
    assert TrainConfig.from_options(**values(args, TrainConfig)).sampling.occupancy is False
    # An option left to the capture (None) still switches both ways.
    for name in ('appearance', 'refine_poses'):
        flag = '--' + name.replace('_', '-')
        for words, value in (([], None), ([flag], True), (['--no-' + flag[2:]], False)):
            args = build_parser().parse_args(['optimize'] + words)
            model = TrainConfig.from_options(**values(args, TrainConfig)).model
            assert getattr(model, name) is value, words
    with pytest.raises(SystemExit):
        build_parser().parse_args(['optimize', '--iterations', '3', '--minutes', '1'])


def test_config_round_trips_through_its_stored_form_and_flat_options():
    cfg = TrainConfig.from_options(model='nerf', fine_samples=3, sparsity=0.02,
                                   pyramid=[0.5], eval_at=(5, 2))
    assert cfg.model.kind == 'nerf' and cfg.losses.sparsity == (0.02,)
    assert cfg.schedule.pyramid == (0.5,) and cfg.output.eval_at == (2, 5)
    stored = cfg.to_dict()
    assert stored['model']['kind'] == 'nerf' and stored['sampling']['fine_samples'] == 3
    assert TrainConfig.from_stored(stored) == cfg
    assert TrainConfig.from_stored(cfg.options()) == cfg         # a flat (older) config
    assert cfg.replace(seed=4).schedule.seed == 4 and cfg.schedule.seed == 0
    with pytest.raises(TypeError, match='unknown training options: no_such'):
        TrainConfig.from_options(no_such=1)


def test_resume_without_checkpoint_is_an_error(dataset, tmp_path):
    with pytest.raises(TrainingError, match='no checkpoint at'):
        Trainer(dataset, str(tmp_path), TrainConfig.from_options(iterations=2, **SMALL),
                resume=True)


def test_optimize_command_end_to_end(capture, tmp_path):
    out = tmp_path / 'run'
    cmd = [sys.executable, os.path.join(ROOT, 'optimize.py'), capture, '--out', str(out),
           '--iterations', '30', '--batch-rays', '256', '--samples', '8', '8', '8',
           '--preview-every', '15']
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert 'held-out views: PSNR' in r.stdout
    metrics = json.loads((out / 'metrics.json').read_text())
    assert metrics['iterations'] == 30 and len(metrics['test']['views']) == 4
    assert np.isfinite(metrics['test']['psnr']) and metrics['train_samples_per_second'] > 0
    assert (out / 'preview' / 'iter_000030.png').exists() and (out / 'training.png').exists()
    assert (out / 'test' / 'test_000.exr').exists()
    # The soft-alpha score is that of the written mattes, and the warning follows it.
    from mi_nerfpp.files.exr import read_exr
    from mi_nerfpp.training.metrics import SOFT_ALPHA_WARNING, soft_alpha_fraction
    for view in metrics['test']['views']:
        fg_a = read_exr(str(out / 'test' / f'test_{view["view"]:03d}.exr'))['fg.A']
        assert view['soft_alpha'] == pytest.approx(soft_alpha_fraction(fg_a))
    soft = metrics['test']['soft_alpha']
    assert soft == pytest.approx(np.mean([v['soft_alpha'] for v in metrics['test']['views']]))
    assert ('the foreground matte is soft' in r.stderr) == (soft > SOFT_ALPHA_WARNING), (soft, r.stderr[-2000:])
    # The written scene renders as is, from anywhere.
    r = subprocess.run([sys.executable, '-m', 'mi_nerfpp', 'render', str(out / 'render.xml'),
                        '-o', str(tmp_path / 'v.exr')], capture_output=True, text=True,
                       timeout=300, cwd=str(tmp_path))
    assert r.returncode == 0, r.stderr[-3000:]
    # evaluate re-runs the same evaluation (deterministic sample placement).
    (out / 'metrics.json').unlink()
    r = subprocess.run([sys.executable, '-m', 'mi_nerfpp', 'evaluate', str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    again = json.loads((out / 'metrics.json').read_text())
    assert again['test']['psnr'] == pytest.approx(metrics['test']['psnr'], abs=1e-3)
    assert again['iterations'] == 30
    for path, extra in (('orbit.gif', ['--frames', '3']), ('path.mp4', ['--path', 'test'])):
        r = subprocess.run([sys.executable, '-m', 'mi_nerfpp', 'video', str(out), '-o',
                            str(tmp_path / path)] + extra, capture_output=True, text=True,
                           timeout=300)
        assert r.returncode == 0, r.stderr[-3000:]
        assert (tmp_path / path).stat().st_size > 0
    import imageio.v3 as iio
    frames = iio.imread(tmp_path / 'orbit.gif')
    assert frames.shape[0] == 3 and frames.shape[1:3] == (24, 32)
    r = subprocess.run([sys.executable, '-m', 'mi_nerfpp', 'video', str(out), '--res', '32by24'],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and 'resolution must be WxH' in r.stderr, r.stderr[-2000:]


def test_optimize_reports_bad_dataset(tmp_path):
    (tmp_path / 'empty').mkdir()
    r = subprocess.run([sys.executable, os.path.join(ROOT, 'optimize.py'), str(tmp_path / 'empty'),
                        '--iterations', '1'], capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and 'empty' in r.stderr
    r = subprocess.run([sys.executable, os.path.join(ROOT, 'optimize.py'), str(tmp_path / 'nope'),
                        '--iterations', '1'], capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and 'nope: dataset folder not found' in r.stderr


@pytest.mark.parametrize('field', ['nerf', 'vanilla'])
def test_pure_mlp_fields_train(dataset, tmp_path, field):
    tr = Trainer(dataset, str(tmp_path),
                 TrainConfig.from_options(iterations=3, field=field, **SMALL))
    before = _params(tr.model)
    losses = []
    tr.run(on_step=lambda t, loss, psnr: losses.append(loss))
    after = _params(tr.model)
    assert tr.model.fg.kind == field and len(losses) == 3 and all(np.isfinite(losses))
    assert all(not np.array_equal(before[k], after[k]) for k in before if 'trunk' in k)


def test_sparsity_prior_reaches_each_volume_only_after_its_start(dataset, tmp_path):
    import drjit as dr
    tr = Trainer(dataset, str(tmp_path),
                 TrainConfig.from_options(iterations=10, sparsity_start=(0.5, 0.0), **SMALL))

    def touched():
        tr.model.set_parameters({k: tr.opt[k] for k in tr.opt.keys()})
        points = tr._step_inputs(tr.progress())['draws']['sparsity']
        dr.backward(tr.sparsity.loss((tr.model.fg, tr.model.bg), points))
        out = {vol: any(np.any(np.array(dr.grad(tr.opt[k])) != 0)
                        for k in tr.opt.keys() if k.startswith(vol + '.'))
               for vol in ('fg', 'bg')}
        for k in tr.opt.keys():
            dr.clear_grad(tr.opt[k])
        return out

    assert touched() == {'fg': False, 'bg': True}       # progress 0: the foreground is exempt
    tr.iteration = 5                                     # half the run
    assert touched() == {'fg': True, 'bg': True}
    assert TrainConfig.from_options(sparsity_start=0.3).losses.sparsity_start == (0.3,)
    with pytest.raises(ValueError, match='--sparsity-start must be one fraction'):
        TrainConfig.from_options(sparsity_start=(0.1, 0.2, 0.3))


def test_sparsity_prior_weighs_each_volume_by_its_own_weight(dataset, tmp_path):
    tr = Trainer(dataset, str(tmp_path),
                 TrainConfig.from_options(iterations=10, sparsity=(0.02, 0.005),
                                          sparsity_start=(0.0,), **SMALL))
    assert tr.cfg.losses.sparsity == (0.02, 0.005)
    points = tr._step_inputs(0.0)['draws']['sparsity']
    assert all(u is not None for u in points)
    fields = (tr.model.fg, tr.model.bg)

    def loss(weights):
        return float(priors.Sparsity(per_volume(weights), (0.0, 0.0)).loss(fields, points)
                     .array[0])

    fg, bg = loss((1.0, 0.0)), loss((0.0, 1.0))
    assert fg > 0 and bg > 0
    assert loss((0.02, 0.005)) == pytest.approx(0.02 * fg + 0.005 * bg, rel=1e-5)
    assert loss((0.01,)) == pytest.approx(0.01 * (fg + bg), rel=1e-5)
    # A volume whose weight is 0 draws no points (and costs nothing).
    tr.sparsity = priors.Sparsity((0.01, 0.0), (0.0, 0.0))
    assert tr._step_inputs(0.0)['draws']['sparsity'][1] is None
    for bad in ((0.01, 0.01, 0.01), (-0.01,), (0.01, float('nan'))):
        with pytest.raises(ValueError, match='--sparsity must be one finite number >= 0, or two'):
            TrainConfig.from_options(sparsity=bad)


@pytest.mark.parametrize('extra', [dict(sparsity_start=(0.5,)),
                                   dict(refine_poses=True, poses_start=0.5, appearance=True,
                                        sparsity_start=(0.0, 0.5),
                                        occupancy_every=3)])
def test_frozen_step_replays_the_traced_step(dataset, tmp_path, extra):
    """A frozen step (recorded once, replayed) computes what tracing every step computes:
    each step's learning rate and random draws reach the replay, and a prior that starts
    half-way (or pose refinement) records the step anew instead of replaying the old one.
    On one thread (``one_thread``), so that the two runs' gradient sums agree in the last bits."""
    # At full size throughout: each level of the image pyramid records the step anew too.
    cfg = dict(iterations=8, seed=3, pyramid=(), **SMALL, **extra)
    runs = {}
    with one_thread():
        for freeze in (False, True):
            tr = Trainer(dataset, str(tmp_path / str(freeze)),
                         TrainConfig.from_options(freeze=freeze, **cfg))
            losses = [tr.step()[0] for _ in range(8)]
            runs[freeze] = losses, _params(tr.model)
    # Recorded once, once more when Dr.Jit makes the first step's constants opaque, and once
    # when the prior or the pose refinement starts: not every step (8).
    assert tr._compute.n_recordings <= 3
    (traced, p_traced), (frozen, p_frozen) = runs[False], runs[True]
    assert len(set(traced)) == 8                        # the steps differ from each other
    np.testing.assert_allclose(frozen, traced, rtol=1e-4)
    for k in p_traced:
        np.testing.assert_allclose(p_frozen[k], p_traced[k], rtol=1e-3, atol=1e-5, err_msg=k)


def test_owned_arrays_do_not_share_numpy_memory():
    """What a frozen step may release is a copy, never a view of a NumPy buffer (whose
    release Dr.Jit cannot record): writing to the source after the copy changes nothing."""
    import drjit as dr
    import mitsuba as mi
    from mi_nerfpp.core.arrays import owned
    a = np.zeros((64, 1024), np.float32)        # page-aligned: the case NumPy may lend out
    t, f = owned(a), owned(a.ravel(), mi.Float)
    a[:] = 7.0
    assert t.shape == (64, 1024) and dr.all(t.array == 0.0) and dr.all(f == 0.0)
    np.testing.assert_array_equal(owned(np.arange(6, dtype=np.uint32), mi.UInt32), np.arange(6))


def _interrupt_in_a_loop_body():
    """A Ctrl-C that lands in Python code which Dr.Jit calls (here a loop body): Dr.Jit
    re-raises it wrapped in a RuntimeError."""
    def body(i):
        raise KeyboardInterrupt('signal 15')
    dr.while_loop((mi.UInt32(0),), lambda i: i < 3, body)


@pytest.mark.parametrize('where', ['recorded', 'recorded_loop', 'occupancy_loop'])
def test_ctrl_c_while_a_step_is_recorded_saves_a_checkpoint(dataset, tmp_path, monkeypatch,
                                                             where):
    """drjit.freeze wraps an exception raised while it records the step in a RuntimeError, and
    a Dr.Jit loop wraps one raised in its body (so inside a recording it arrives wrapped twice):
    a Ctrl-C there, or in the occupancy refresh before the recorded part, must still stop the
    run like a Ctrl-C anywhere else (checkpoint saved), and the run must go on from it."""
    import mi_nerfpp.training.train as train_module
    calls = []

    def once(original, interrupt):
        def wrapped(*args, **kwargs):
            calls.append(1)
            if len(calls) == 1:
                interrupt()
            return original(*args, **kwargs)
        return wrapped

    def ctrl_c():
        raise KeyboardInterrupt

    if where == 'occupancy_loop':
        from mi_nerfpp.core.model import NeRFPPModel as NeRFPP
        monkeypatch.setattr(NeRFPP, 'update_occupancy',
                            once(NeRFPP.update_occupancy, _interrupt_in_a_loop_body))
    else:
        from mi_nerfpp.training import priors
        monkeypatch.setattr(priors, 'ray_distortion', once(
            priors.ray_distortion, ctrl_c if where == 'recorded' else _interrupt_in_a_loop_body))
    tr = Trainer(dataset, str(tmp_path), TrainConfig.from_options(iterations=4, **SMALL))
    assert tr.run() is False
    assert os.path.exists(tmp_path / 'model.npz') and tr.iteration == 0
    resumed = Trainer(dataset, str(tmp_path), TrainConfig.from_options(iterations=4, **SMALL),
                      resume=True)
    assert resumed.run() is True and resumed.iteration == 4


def test_ctrl_c_in_a_preview_loop_body_saves_a_checkpoint(dataset, tmp_path):
    """A Ctrl-C that lands in a loop body of ``on_preview`` (a preview render, the viewer's
    callback) arrives wrapped in Dr.Jit's RuntimeError outside the step: the run stops as
    interrupted, with its checkpoint, rather than failing with 'signal 15'."""
    tr = Trainer(dataset, str(tmp_path),
                 TrainConfig.from_options(iterations=4, **dict(SMALL, preview_every=1)))
    assert tr.run(on_preview=lambda trainer: _interrupt_in_a_loop_body()) is False
    assert os.path.exists(tmp_path / 'model.npz') and tr.iteration >= 1


def test_the_command_line_reports_a_wrapped_ctrl_c_as_interrupted(monkeypatch, capsys):
    """The command line's status for a Ctrl-C that Dr.Jit re-raised wrapped is 130, not an
    error line."""
    from mi_nerfpp.commands import cli, evaluate
    monkeypatch.setattr(evaluate, 'run', lambda args: _interrupt_in_a_loop_body())
    assert cli.main(['evaluate', 'nowhere']) == 130
    assert 'interrupted' in capsys.readouterr().err


def test_neutral_grids_start_at_zero(dataset, tmp_path):
    """``--grid-init 0`` starts the grid levels at zero (the default at noise of 0.1), the
    colour MLP the same."""
    zero = Trainer(dataset, str(tmp_path / 'zero'),
                   TrainConfig.from_options(grid_init=0.0, **SMALL))
    noisy = Trainer(dataset, str(tmp_path / 'noisy'), TrainConfig.from_options(**SMALL))
    for k in zero.opt.keys():
        a, b = np.array(zero.opt[k]), np.array(noisy.opt[k])
        if k.split('.')[-1].startswith('grid'):
            assert not a.any() and 0.08 < b.std() < 0.12, k
        else:
            np.testing.assert_array_equal(a, b, err_msg=k)
