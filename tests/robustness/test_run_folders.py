"""Run folders: one writer at a time (a lock taken before anything is written, released by the
operating system when its process dies), a run folder never mixes two runs (--overwrite moves
the old run's outputs aside before the new one writes, and finishes a replacement cut short),
and nothing that holds a result is lost."""
import json
import os
import shutil
import signal

import numpy as np
import pytest

from mi_nerfpp.files.checkpoint import load_checkpoint
from mi_nerfpp.files.atomic import LOCK_NAME
from mi_nerfpp.training.config import TrainConfig
from tests.robustness.common import TINY, Training, one_clear_line, run_cli


def _train(capsys, capture, out, *extra):
    return run_cli(capsys, 'optimize', capture, '--out', out, *TINY, *extra)


def _in_use(line, out):
    """Whether ``line`` is the refusal of a run folder that another process holds."""
    return (line.startswith(f'error: optimize: {out}: this run folder (--out) is in use by '
                            f'another mi-nerfpp process (pid ')
            and line.endswith('); wait for it to end or stop it, or choose another one'))


def test_a_second_run_into_a_folder_in_use_is_refused(capsys, capture, tmp_path):
    """Two runs with the same --out both passed the run-folder check; the second removed the
    first one's checkpoint temporary as "stale". Now the second is refused, whatever its
    options, and the first trains on and saves."""
    out = tmp_path / 'run'
    first = Training(capture, out)
    try:
        first.wait_for_steps(1)
        holder = (out / LOCK_NAME).read_text()
        assert holder.startswith(f'pid {first.proc.pid} on ') and 'optimize' in holder
        stray = out / '.model.0123456789abcdef.tmp.npz'     # as if the first were saving
        stray.write_bytes(b'half a checkpoint')
        for extra in ([], ['--resume'], ['--overwrite']):
            status, _, err = _train(capsys, capture, out, *extra)
            line = one_clear_line(err)
            assert status == 1 and _in_use(line, out), line
            assert f'pid {first.proc.pid} on ' in line
        assert stray.exists()                 # the holder's files are left alone
        stray.unlink()
        status, err = first.stop(signal.SIGTERM)
    finally:
        first.kill()
    assert status == 143 and 'checkpoint saved' in err
    # The lock went with its process: the run can be continued.
    assert _train(capsys, capture, out, '--resume', '--iterations',
                  str(load_checkpoint(out / 'model.npz')[1]['iteration'] + 1))[0] == 0


def test_the_lock_of_a_killed_process_is_not_stale(capsys, capture, tmp_path):
    out = tmp_path / 'run'
    first = Training(capture, out)
    try:
        first.wait_for_steps(1)
        first.proc.send_signal(signal.SIGKILL)          # no chance to release anything
        first.proc.wait(60)
    finally:
        first.kill()
    assert (out / LOCK_NAME).exists()
    assert _train(capsys, capture, out)[0] == 0         # nothing saved: a new run may start


def test_evaluate_is_refused_while_a_run_trains_in_the_folder(capsys, capture, tmp_path):
    """evaluate writes test/, metrics.json and render.xml: not while a run trains there."""
    out = tmp_path / 'run'
    assert _train(capsys, capture, out)[0] == 0
    metrics = (out / 'metrics.json').read_bytes()
    training = Training(capture, out, '--resume')
    try:
        training.wait_for_steps(3)
        status, _, err = run_cli(capsys, 'evaluate', out)
        line = one_clear_line(err)
        assert status == 1 and line.startswith(f'error: evaluate: {out}: this run folder is in '
                                               f'use by another mi-nerfpp process (pid ')
    finally:
        training.kill()
    assert (out / 'metrics.json').read_bytes() == metrics


def test_an_interrupted_overwrite_leaves_no_output_of_the_old_run(capsys, capture, tmp_path):
    """--overwrite of a finished run, interrupted: the new model.npz sat beside the old run's
    metrics.json, test/ and render.xml. Now the old outputs go before the new run writes."""
    out = tmp_path / 'run'
    assert _train(capsys, capture, out, '--preview-every', '1')[0] == 0
    assert {'metrics.json', 'test', 'render.xml', 'training.png', 'preview'} <= set(
        os.listdir(out))
    (out / 'sfm').mkdir()                                # an input cache: kept
    (out / 'optimize.log').write_text('a sweep log\n')   # a sweep's log: kept
    second = Training(capture, out, '--overwrite', '--seed', '5')
    try:
        second.wait_for_steps(1)
        status, err = second.stop(signal.SIGINT)
    finally:
        second.kill()
    assert status == 130 and 'checkpoint saved' in err
    assert sorted(os.listdir(out)) == [LOCK_NAME, 'model.npz', 'optimize.log', 'sfm']
    assert load_checkpoint(out / 'model.npz')[1]['config']['schedule']['seed'] == 5


def test_a_replacement_cut_short_is_finished_before_the_next_run(capsys, capture, tmp_path):
    out = tmp_path / 'run'
    assert _train(capsys, capture, out)[0] == 0
    # As if killed half-way through --overwrite: model.npz moved aside, the rest not yet.
    (out / '.replaced').mkdir()
    os.rename(out / 'model.npz', out / '.replaced' / 'model.npz')
    status, stdout, _ = _train(capsys, capture, out, '--seed', '7')
    assert status == 0
    assert (f'{out}: finishing the replacement of an earlier run that was cut short (removing '
            f'metrics.json, render.xml, training.png, test)') in stdout
    assert not (out / '.replaced').exists()
    assert json.loads((out / 'metrics.json').read_text())['config']['schedule']['seed'] == 7


def test_outputs_of_a_run_without_its_model_are_not_mixed_in(capsys, capture, tmp_path):
    """A folder with metrics.json (or test/, ...) but no model.npz holds the remains of another
    run: training there is refused unless --overwrite, and a sweep does not take it as
    finished."""
    out = tmp_path / 'run'
    assert _train(capsys, capture, out)[0] == 0
    os.remove(out / 'model.npz')
    status, _, err = _train(capsys, capture, out)
    assert status == 1 and one_clear_line(err) == (
        f'error: optimize: {out} holds outputs of an earlier run (metrics.json, render.xml, '
        f'training.png, test) without its model.npz: remove them with --overwrite, or choose '
        f'another --out')
    from mi_nerfpp.jobs.sweep import finished
    assert not finished(out)
    assert _train(capsys, capture, out, '--overwrite')[0] == 0 and finished(out)


# ----------------------------------------------------------------------------- the folder

def test_out_naming_an_existing_file_is_refused(capsys, capture, tmp_path):
    (tmp_path / 'file').write_text('precious')
    status, _, err = _train(capsys, capture, tmp_path / 'file')
    assert status == 1 and 'is an existing file, not a folder' in one_clear_line(err)
    assert (tmp_path / 'file').read_text() == 'precious'


def test_out_in_a_place_that_cannot_be_written_is_refused_before_training(capsys, capture):
    status, _, err = _train(capsys, capture, '/sys/mi-nerfpp-run')
    line = one_clear_line(err)
    assert status == 1 and '/sys/mi-nerfpp-run' in line and 'choose a writable place' in line


def test_a_run_refused_for_its_data_writes_nothing(capsys, tmp_path):
    (tmp_path / 'data').mkdir()
    status, _, err = _train(capsys, tmp_path / 'data', tmp_path / 'run')
    assert status == 1 and one_clear_line(err).startswith('error: optimize: ')
    assert not (tmp_path / 'run').exists()


def test_training_again_into_a_run_folder_keeps_the_run_unless_told(capsys, capture, tmp_path):
    out = tmp_path / 'run'
    assert _train(capsys, capture, out)[0] == 0
    before = (out / 'model.npz').read_bytes(), (out / 'metrics.json').read_bytes()
    status, _, err = _train(capsys, capture, out)
    assert status == 1
    assert 'already holds a trained run' in one_clear_line(err) and '--overwrite' in err
    assert ((out / 'model.npz').read_bytes(), (out / 'metrics.json').read_bytes()) == before
    assert _train(capsys, capture, out, '--overwrite', '--seed', '3')[0] == 0
    assert json.loads((out / 'metrics.json').read_text())['config']['schedule']['seed'] == 3


def test_resume_on_other_data_is_refused_naming_the_difference(capsys, capture, tmp_path):
    out = tmp_path / 'run'
    assert _train(capsys, capture, out)[0] == 0
    status, _, err = _train(capsys, capture, out, '--resume', '--downscale', '2')
    line = one_clear_line(err)
    assert status == 1 and 'cannot be resumed' in line and 'training rays' in line


def test_train_only_dataset_does_not_claim_test_outputs(capsys, capture, tmp_path):
    data = tmp_path / 'data'
    shutil.copytree(os.path.join(capture, 'train'), data / 'train')
    status, out, _ = _train(capsys, data, tmp_path / 'run')
    assert status == 0
    written = [line for line in out.splitlines() if line.startswith('written to')]
    assert written and 'test/' not in written[0] and 'render.xml' not in written[0]
    assert 'preview/' not in written[0]
    assert not (tmp_path / 'run' / 'test').exists()


def test_stray_temporary_checkpoints_are_removed(capsys, capture, tmp_path):
    out = tmp_path / 'run'
    out.mkdir()
    stray = out / '.model.0123456789abcdef.tmp.npz'
    stray.write_bytes(b'half a checkpoint')
    assert _train(capsys, capture, out)[0] == 0
    assert not stray.exists() and (out / 'model.npz').exists()


def test_resume_of_a_checkpoint_from_before_linear_compositing(capsys, capture, tmp_path):
    """A pre-issue-11 sRGB checkpoint (no 'composite' entry: it summed encoded colours) is not
    resumed: that compositing was removed (docs/experiments.md)."""
    out = tmp_path / 'run'
    assert _train(capsys, capture, out)[0] == 0
    path = out / 'model.npz'
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    config = json.loads(str(arrays['config']))
    del config['composite']
    arrays['config'] = np.array(json.dumps(config))
    np.savez(path, **arrays)
    status, _, err = _train(capsys, capture, out, '--resume')
    line = one_clear_line(err)
    assert status == 1 and 'was trained with --composite srgb, which this version no ' \
        'longer has' in line


@pytest.mark.parametrize('held', [True, False])
def test_lock_folder_refuses_a_second_holder(tmp_path, held):
    from mi_nerfpp.files.atomic import FolderInUseError, lock_folder
    lock = lock_folder(tmp_path / 'f', what='folder')
    if not held:
        lock.release()
        lock_folder(tmp_path / 'f').release()          # free again
        return
    import subprocess
    import sys
    code = ('from mi_nerfpp.files.atomic import lock_folder, FolderInUseError\n'
            f'try:\n    lock_folder({str(tmp_path / "f")!r})\n'
            'except FolderInUseError as e:\n    print(e)\n')
    child = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True)
    assert 'is in use by another mi-nerfpp process (pid ' + str(os.getpid()) in child.stdout
    # This process may take its own lock again (a run prepared, then resumed here); the lock
    # stays until its last holder releases it.
    again = lock_folder(tmp_path / 'f')
    lock.release()
    child = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True)
    assert 'is in use by another mi-nerfpp process (pid ' + str(os.getpid()) in child.stdout
    again.release()
    again.release()                                    # a second release does nothing
    child = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True)
    assert child.returncode == 0 and child.stdout == ''            # free for another process
    assert FolderInUseError.__mro__[1] is RuntimeError


def test_a_lock_file_that_is_a_link_is_refused_and_its_target_kept(capsys, capture, tmp_path):
    """A ``.mi-nerfpp.lock`` that links to a user's file: the lock is never written through it
    (issue 49, item 7); the command ends in one line naming the link, and the file is intact."""
    from mi_nerfpp.files.atomic import LOCK_NAME, lock_folder
    out = tmp_path / 'run'
    out.mkdir()
    precious = tmp_path / 'notes.txt'
    precious.write_text('my notes\n')
    (out / LOCK_NAME).symlink_to(precious)
    with pytest.raises(ValueError, match='is a symbolic link .*remove the link'):
        lock_folder(out)
    status, _, err = _train(capsys, capture, out)
    line = one_clear_line(err)
    assert status == 1 and 'lock file of this run folder (--out) is a symbolic link' in line
    assert precious.read_text() == 'my notes\n'
    (out / LOCK_NAME).unlink()
    (out / LOCK_NAME).mkdir()                    # not a regular file either
    with pytest.raises(ValueError, match='is a folder: remove it'):
        lock_folder(out)


def test_a_full_disk_names_the_file_being_written(tmp_path):
    """"No space left on device" named no path (issue 49, item 6): a write that fails inside
    an atomic write is given the file it was writing, and the line says what to do."""
    import errno as errno_module

    from mi_nerfpp.errors import error_line
    from mi_nerfpp.files.atomic import atomic_write_path
    target = tmp_path / 'model.npz'
    with pytest.raises(OSError) as info:
        with atomic_write_path(target) as tmp:
            open(tmp, 'w').close()
            raise OSError(errno_module.ENOSPC, os.strerror(errno_module.ENOSPC))
    assert error_line(info.value) == (f'{target}: No space left on device: free space on that '
                                      f'disk or write somewhere else (--out)')
    assert os.listdir(tmp_path) == []                   # the temporary file is gone


def test_a_resume_that_changes_the_sparse_allocation_after_it_took_effect_is_refused(
        capsys, capture, tmp_path):
    """A resumed run recorded a new --sparse-entries / --sparse-at while its model kept the
    bricks chosen with the old ones (no allocation ahead to apply them). Now that is refused,
    naming the values to resume with; with an allocation still ahead the new values are taken."""
    out = tmp_path / 'run'
    sparse = ['--occupancy-res', '8', '--grid-sparse', '16', '--sparse-at', '0.1']
    assert _train(capsys, capture, out, *sparse, '--iterations', '4')[0] == 0
    status, _, err = _train(capsys, capture, out, *sparse, '--iterations', '6', '--resume',
                            '--sparse-entries', '1000')
    entries = TrainConfig().schedule.sparse_entries          # (the default it was trained with)
    assert status == 1 and one_clear_line(err) == (
        f'error: optimize: {out / "model.npz"}: its sparse levels were allocated with '
        f'--sparse-entries {entries}, and no allocation is ahead of this run to take other '
        f'values: resume with --sparse-entries {entries} (other values need a new run, or a '
        f'--sparse-at fraction still ahead)')
    assert _train(capsys, capture, out, *sparse[:4], '--sparse-at', '0.1', '0.9',
                  '--sparse-entries', '1000', '--iterations', '8', '--resume')[0] == 0
    stored = load_checkpoint(out / 'model.npz')[1]['config']['schedule']
    assert stored['sparse_entries'] == 1000 and stored['sparse_at'] == [0.1, 0.9]
