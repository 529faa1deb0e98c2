"""Checkpoints: only finite state is ever written, a diverging run stops (one line naming the
likely option) before its state is used or saved and keeps the last good checkpoint, a failed
save keeps the previous one, and a damaged file is refused by name."""
import errno
import os

import numpy as np
import pytest

from mi_nerfpp.files.checkpoint import (CheckpointError, NonFiniteStateError, load_checkpoint,
                                        save_checkpoint)
from mi_nerfpp.training.config import TrainConfig
from mi_nerfpp.data import load_dataset
from tests.helpers import tiny_model
from tests.robustness.common import TINY, error_line, one_clear_line, run_cli


def _train(capsys, capture, out, *extra):
    return run_cli(capsys, 'optimize', capture, '--out', out, *TINY, *extra)


@pytest.mark.parametrize('prior', ['--distortion'])
def test_a_prior_that_blows_the_grids_up_stops_before_saving(capsys, capture, tmp_path, prior):
    """--tv 1e30 (a prior since removed) saved NaN grids over the checkpoint, then segfaulted: the loss of the step
    was finite, its update was not. Now the step's guard stops the run at once."""
    out = tmp_path / 'run'
    status, _, err = _train(capsys, capture, out, prior, '1e30', '--checkpoint-every', '1')
    assert status == 1 and error_line(err, 'optimize') == (
        f'the parameters became NaN or infinite (the loss was still finite) at iteration 1; '
        f'stopping before it is used or saved: nothing was saved before. Most likely {prior} '
        f'1e+30 (above the default): lower it, then train again')
    assert not out.exists()                 # nothing was written: the folder is gone again


def test_a_sparsity_that_blows_up_stops_naming_it(capsys, capture, tmp_path):
    out = tmp_path / 'run'
    status, _, err = _train(capsys, capture, out, '--sparsity', '1e30', '--iterations', '20',
                            '--checkpoint-every', '1')
    line = error_line(err, 'optimize')
    assert status == 1 and line.startswith('the parameters became NaN or infinite')
    assert line.endswith('Most likely --sparsity 1e+30 (above the default): lower it, then '
                         'resume with --resume')
    _, meta, _ = load_checkpoint(out / 'model.npz')          # the last good one: finite
    assert (f'the last good checkpoint ({out / "model.npz"}, iteration {meta["iteration"]}) '
            f'is kept') in line


def test_resuming_a_good_run_with_a_blowing_prior_keeps_its_checkpoint(capsys, capture,
                                                                       tmp_path):
    out = tmp_path / 'run'
    assert _train(capsys, capture, out)[0] == 0
    good = (out / 'model.npz').read_bytes()
    status, _, err = _train(capsys, capture, out, '--resume', '--iterations', '4',
                            '--distortion', '1e30', '--checkpoint-every', '1')
    assert status == 1 and error_line(err, 'optimize') == (
        f'the parameters became NaN or infinite (the loss was still finite) at iteration 3; '
        f'stopping before it is used or saved: the last good checkpoint '
        f'({out / "model.npz"}, iteration 2) is kept. Most likely --distortion 1e+30 (above the '
        f'default): lower it, then resume with --resume')
    assert (out / 'model.npz').read_bytes() == good
    assert load_checkpoint(out / 'model.npz')[1]['iteration'] == 2


def test_save_refuses_non_finite_state_and_leaves_the_file(tmp_path):
    path = tmp_path / 'model.npz'
    model = tiny_model()
    save_checkpoint(path, model)
    good = path.read_bytes()
    with pytest.raises(NonFiniteStateError, match=r'^state/adam\.v/fg\.grid0 hold NaN or '
                                                  r'infinite values$'):
        save_checkpoint(path, model, state={'adam.v/fg.grid0': np.array([1.0, np.inf])})
    params = model.parameters()
    bad = np.array(params['fg.grid0'].numpy())
    bad[0, 0, 0, 0] = np.nan
    import mitsuba as mi
    model.set_parameters({'fg.grid0': mi.TensorXf(bad)})
    with pytest.raises(NonFiniteStateError, match=r'^param/fg\.grid0 hold NaN'):
        save_checkpoint(path, model)
    assert path.read_bytes() == good and os.listdir(tmp_path) == ['model.npz']


def test_a_failed_save_says_so_and_keeps_the_previous_checkpoint(capture, tmp_path, monkeypatch):
    from mi_nerfpp.files import checkpoint
    from mi_nerfpp.training.errors import TrainingError
    from mi_nerfpp.training.train import Trainer
    cfg = TrainConfig.from_options(iterations=4, batch_rays=32, fg_samples=4, bg_samples=4, fine_samples=4,
                      grid_levels=(4, 8), checkpoint_every=2, preview_every=0)
    trainer = Trainer(load_dataset(capture), str(tmp_path), cfg)
    trainer.cfg.schedule.iterations = 2
    assert trainer.run()
    good = (tmp_path / 'model.npz').read_bytes()

    def disk_full(file, **arrays):        # the disk fills up half-way through the write
        file.write(b'PK partial')
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    monkeypatch.setattr(checkpoint.np, 'savez', disk_full)
    trainer.cfg.schedule.iterations = 4
    with pytest.raises(TrainingError) as e:
        trainer.run()
    message = str(e.value)
    assert 'cannot save the checkpoint' in message and 'No space left on device' in message
    assert 'iteration 4' in message and 'previous checkpoint (iteration 2) is intact' in message
    assert (tmp_path / 'model.npz').read_bytes() == good
    assert [p.name for p in tmp_path.iterdir()] == ['model.npz']


@pytest.mark.parametrize('content, message', [
    (b'', 'not a mi-nerfpp checkpoint: the file is empty (0 bytes)'),
    (b'PK\x03\x04 half a zip', 'not a mi-nerfpp checkpoint (.npz archive): '),
    (None, 'not a mi-nerfpp checkpoint (.npz archive): a NumPy array file, not an .npz archive'),
])
def test_evaluate_on_a_damaged_checkpoint_is_one_line(capsys, tmp_path, content, message):
    """evaluate on a 0-byte model.npz was numpy's EOFError traceback."""
    run = tmp_path / 'run'
    run.mkdir()
    path = run / 'model.npz'
    if content is None:
        with open(path, 'wb') as f:
            np.save(f, np.zeros(3))
    else:
        path.write_bytes(content)
    status, _, err = run_cli(capsys, 'evaluate', run)
    line = one_clear_line(err)
    assert status == 1 and line.startswith(f'error: evaluate: {path}: {message}')
    assert sorted(os.listdir(run)) == ['model.npz']


def test_a_checkpoint_whose_version_is_not_a_number_is_refused(tmp_path):
    path = tmp_path / 'model.npz'
    np.savez(path, format=np.array('mi-nerfpp-checkpoint'), version=np.array(['x', 'y']))
    with pytest.raises(CheckpointError, match="no integer 'version' entry"):
        load_checkpoint(path)


@pytest.fixture(scope='module')
def error_map_run(capture, tmp_path_factory):
    """A tiny run trained with the error map (``--error-rays 0.5``): its folder."""
    from mi_nerfpp.commands.cli import main
    out = tmp_path_factory.mktemp('error_map') / 'run'
    assert main(['optimize', str(capture), '--out', str(out), *TINY, '--error-rays', '0.5']) == 0
    return out


def _damaged_copy(run, tmp_path, change):
    import shutil
    copy = tmp_path / 'run'
    shutil.copytree(run, copy)
    arrays = dict(np.load(copy / 'model.npz'))
    change(arrays)
    np.savez(copy / 'model.npz', **arrays)
    return copy


def _set(name, value):
    return lambda arrays: arrays.__setitem__(f'state/{name}', value(arrays[f'state/{name}']))


@pytest.mark.parametrize('change, damage', [
    (_set('error_map', lambda v: np.where(np.arange(v.size) == 0, np.nan, v)),
     'state/error_map holds NaN, infinite, zero or negative tile errors'),
    (_set('error_map', lambda v: -v), 'state/error_map holds NaN, infinite, zero or negative'),
    (_set('error_map', lambda v: np.full(v.size, 'a')), 'state/error_map is not a list of '
                                                        'numbers'),
    (_set('error_map.visited', lambda v: v[:3]), 'state/error_map.visited is not 64 flags'),
    (_set('error_map.reference', lambda v: np.zeros_like(v)),
     'state/error_map.reference is not a list of positive finite numbers'),
    (_set('error_map.updates', lambda v: np.array([1, 2])),
     'state/error_map.updates is not a whole number of 0 or more'),
], ids=['nan', 'negative', 'text', 'visited-shape', 'reference-zero', 'updates-shape'])
def test_a_damaged_error_map_is_refused_on_resume(capsys, capture, error_map_run, tmp_path,
                                                  change, damage):
    """A stored error map of another shape, NaN or negative values ended with NumPy's text, 'a
    bug' (TypeError) or was trained on (issue 63): now one line naming the file and the entry."""
    run = _damaged_copy(error_map_run, tmp_path, change)
    status, _, err = _train(capsys, capture, run, '--resume', '--iterations', '4',
                            '--error-rays', '0.5')
    line = error_line(err, 'optimize')
    assert status == 1 and line.startswith(f'{run / "model.npz"}: its error map is damaged: '
                                           f'{damage}'), line
    assert line.endswith('restore it from a copy, or train the model again, or resume with '
                         '--error-rays 0')


@pytest.mark.parametrize('bricks, message', [
    (lambda b: b + 0.4, 'bricks/fg.sparse0 is not a list of whole brick indices (shape (4,), '
                        'float64)'),
    (lambda b: b.astype(str), 'bricks/fg.sparse0 is not a list of whole brick indices (shape '
                              '(4,), <U21)'),
    (lambda b: np.ones(b.size, bool), 'bricks/fg.sparse0 is not a list of whole brick indices'),
    (lambda b: b.reshape(2, 2), 'bricks/fg.sparse0 is not a list of whole brick indices (shape '
                                '(2, 2), int64)'),
    (lambda b: b[:3], 'bricks/fg.sparse0 lists 3 bricks, its parameter param/fg.sparse0 holds 4'),
    (lambda b: np.array([0, 5, 21, 64]), 'bricks/fg.sparse0: brick indices must be distinct and '
                                         'in [0, 64)'),
    (lambda b: np.array([0, 5, 21, -1]), 'bricks/fg.sparse0: brick indices must be distinct'),
    (lambda b: np.array([0, 5, 5, 21]), 'bricks/fg.sparse0: brick indices must be distinct'),
], ids=['float', 'text', 'bool', 'two-dimensional', 'count', 'out-of-range', 'negative',
        'duplicate'])
def test_damaged_sparse_bricks_are_refused_by_name(tmp_path, bricks, message):
    """Float or text brick lists were read as indices and the model rendered; the others said
    'invalid config' or NumPy's text (issue 63): one CheckpointError naming the entry."""
    from mi_nerfpp.core.fields import grid_field
    from mi_nerfpp.core.model import NeRFPPModel
    model = NeRFPPModel(grid_field('ball', resolutions=(4,), channels=4, sparse=(16,),
                                   sparse_blocks=(4, 4, 4), seed=1), None)
    model.set_bricks({'fg.sparse0': np.array([0, 5, 21, 63])})
    path = tmp_path / 'model.npz'
    save_checkpoint(path, model)
    arrays = dict(np.load(path))
    arrays['bricks/fg.sparse0'] = bricks(arrays['bricks/fg.sparse0'])
    np.savez(path, **arrays)
    with pytest.raises(CheckpointError) as e:
        load_checkpoint(path)
    assert str(e.value).startswith(f'{path}: {message}'), str(e.value)
    assert str(e.value).endswith('restore it from a copy, or train the model again')
