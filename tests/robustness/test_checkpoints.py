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
