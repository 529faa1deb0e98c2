"""Hostile and careless input: every command ends with one clear line and status 1, options
and XML parameters are checked where they are read, and nothing that holds a result is lost."""
import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from mi_nerfpp import cli
from mi_nerfpp.data import DatasetError, load_dataset
from mi_nerfpp.data.images import read_image
from mi_nerfpp.exr import write_exr

TINY = ['--iterations', '2', '--batch-rays', '32', '--samples', '4', '4', '4',
        '--grid-levels', '4', '8', '--preview-every', '0', '--checkpoint-every', '0']


def run_cli(capsys, *argv):
    """Run a command in-process through the command-line boundary: (status, stdout, stderr)."""
    try:
        status = cli.main([str(a) for a in argv])
    except SystemExit as e:      # argparse errors and the commands' own exits
        status = e.code if isinstance(e.code, int) else 1
        if not isinstance(e.code, int) and e.code is not None:
            print(e.code, file=sys.stderr)
    out, err = capsys.readouterr()
    return status, out, err


def one_clear_line(err):
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and 'Traceback' not in err, err
    return lines[0]


# ----------------------------------------------------------------------------- optimize options

@pytest.mark.parametrize('option, message', [
    (['--batch-rays', '0'], '--batch-rays must be at least 1, got 0'),
    (['--downscale', '0'], '--downscale must be at least 1, got 0'),
    (['--samples', '0', '0', '0'], '--samples must be at least 1, got 0'),
    (['--grid-levels', '0'], '--grid-levels must be one or more resolutions of at least 2'),
    (['--lr-grid', 'nan'], '--lr-grid must be a positive finite number, got nan'),
    (['--lr-mlp', '-0.01'], '--lr-mlp must be a positive finite number, got -0.01'),
    (['--checkpoint-every', '-5'], '--checkpoint-every must be 0 or more, got -5'),
    (['--minutes', '-1'], '--minutes must be a positive number of minutes, got -1.0'),
    (['--minutes', 'nan'], '--minutes must be a positive number of minutes, got nan'),
    (['--adam-beta2', '1'], '--adam-beta2 must be a number in (0, 1), got 1.0'),
    (['--fg-warp', '1'], '--fg-warp must be a radius in [0, 1), got 1.0'),
    (['--bg-s-ratio', '0'], '--bg-s-ratio must be one number in (0, 1], or one per background grid level, got 0.0'),
    (['--bg-s-ratio', '0.5', '0.5', '0.5'], 'one per background grid level, got 0.5 0.5 0.5'),
    (['--bg-grid-levels', '1'], '--bg-grid-levels must be one or more resolutions of at least 2'),
])
def test_bad_optimize_options_are_refused(capsys, tmp_path, option, message):
    status, _, err = run_cli(capsys, 'optimize', tmp_path, '--out', tmp_path / 'run', *option)
    assert status == 1
    assert message in one_clear_line(err)
    assert not (tmp_path / 'run').exists()


def test_out_naming_an_existing_file_is_refused(capsys, capture, tmp_path):
    (tmp_path / 'file').write_text('precious')
    status, _, err = run_cli(capsys, 'optimize', capture, '--out', tmp_path / 'file', *TINY)
    assert status == 1 and 'is an existing file, not a folder' in one_clear_line(err)
    assert (tmp_path / 'file').read_text() == 'precious'


def test_out_in_a_place_that_cannot_be_written_is_refused_before_training(capsys, capture):
    status, _, err = run_cli(capsys, 'optimize', capture, '--out', '/sys/mi-nerfpp-run', *TINY)
    line = one_clear_line(err)
    assert status == 1 and '/sys/mi-nerfpp-run' in line and 'choose a writable place' in line


def _train(capsys, capture, out, *extra):
    return run_cli(capsys, 'optimize', capture, '--out', out, *TINY, *extra)


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


def test_a_failed_save_says_so_and_keeps_the_previous_checkpoint(capture, tmp_path, monkeypatch):
    from mi_nerfpp import checkpoint
    from mi_nerfpp.config import TrainConfig
    from mi_nerfpp.train import Trainer, TrainingError
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


@pytest.mark.parametrize('sig', [signal.SIGTERM, signal.SIGINT])
def test_sigterm_and_sigint_save_a_checkpoint(capture, tmp_path, sig):
    out = tmp_path / 'run'
    proc = subprocess.Popen([sys.executable, '-m', 'mi_nerfpp', 'optimize', capture, '--out',
                             str(out), '--iterations', '100000', '--batch-rays', '32',
                             '--samples', '4', '4', '4', '--grid-levels', '4', '8',
                             '--preview-every', '0', '--checkpoint-every', '0'],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # The resolution chosen is announced first, then the dataset is loaded.
        assert 'training at the images\' own resolution' in proc.stdout.readline()
        assert 'run folder' in proc.stdout.readline()
        time.sleep(4.0)                                      # some iterations are done
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    import re
    stopped = re.search(r'interrupted at iteration (\d+): checkpoint saved to (\S+); continue '
                        r'with --resume', err)
    assert stopped, err
    from mi_nerfpp.checkpoint import load_checkpoint
    _, meta, _ = load_checkpoint(out / 'model.npz')
    assert meta['iteration'] == int(stopped.group(1))


# ----------------------------------------------------------------------------- data

def test_jpg_exif_orientation_is_applied(tmp_path):
    from PIL import Image
    pixels = np.zeros((8, 12, 3), np.uint8)
    pixels[:4, :6] = 255                                # a white top-left quadrant
    image = Image.fromarray(pixels)
    exif = image.getexif()
    exif[0x0112] = 3                                    # orientation 3: rotated 180 degrees
    image.save(tmp_path / 'x.jpg', exif=exif, quality=100)
    read = read_image(tmp_path / 'x.jpg')
    assert read.shape == (8, 12, 3)
    assert read[6, 9].min() > 0.9 and read[1, 1].max() < 0.1     # now bottom-right


def test_nan_pixel_in_a_training_exr_names_the_file(tmp_path):
    channels = {c: np.full((4, 5), 0.5, np.float32) for c in 'RGB'}
    channels['G'][2, 3] = np.nan
    channels = {k: v for k, v in channels.items()}
    path = tmp_path / 'img.exr'
    import OpenEXR
    with OpenEXR.File({'type': OpenEXR.scanlineimage}, channels) as f:   # write_exr refuses NaN
        f.write(str(path))
    with pytest.raises(DatasetError, match=r'img\.exr: 1 pixel\(s\) are NaN or infinite '
                                           r'\(the first at x=3, y=2\)'):
        read_image(path)


def _llff(root, poses, size=(6, 4)):
    (root / 'images').mkdir(parents=True)
    from PIL import Image
    for i in range(len(poses) if hasattr(poses, '__len__') else 2):
        Image.fromarray(np.full((size[1], size[0], 3), 128, np.uint8)).save(
            root / 'images' / f'{i:03d}.png')


def test_garbage_poses_bounds_gets_a_clear_message(capsys, tmp_path):
    data = tmp_path / 'llff'
    _llff(data, [0, 1])
    (data / 'poses_bounds.npy').write_bytes(b'this is not numpy at all' * 10)
    with pytest.raises(DatasetError, match='not a NumPy array file .*N x 17 float array'):
        load_dataset(str(data))
    np.save(data / 'poses_bounds.npy', np.array([{'a': 1}], dtype=object), allow_pickle=True)
    status, _, err = run_cli(capsys, 'optimize', data, '--out', tmp_path / 'run', *TINY)
    assert status == 1 and 'poses_bounds.npy: not a NumPy array file' in one_clear_line(err)


def test_one_pixel_images_are_refused_before_training(tmp_path):
    data = tmp_path / 'llff'
    poses = np.zeros((2, 17))
    for i in range(2):
        pose = np.zeros((3, 5))
        pose[:, :3] = np.eye(3)
        pose[:, 3] = [i, 0, 0]
        pose[:, 4] = [1, 1, 1.0]
        poses[i, :15] = pose.ravel()
    _llff(data, poses, size=(1, 1))
    np.save(data / 'poses_bounds.npy', poses)
    with pytest.raises(DatasetError, match='image is 1x1 pixels .* at least 3x3'):
        load_dataset(str(data))


# ----------------------------------------------------------------------------- video

@pytest.mark.parametrize('option, message', [(['--frames', '0'], "--frames: expects a whole "
                                              "number of at least 1, got '0'"),
                                             (['--res', '0x0'], 'resolution must be positive')])
def test_video_bad_counts(capsys, tmp_path, option, message):
    status, _, err = run_cli(capsys, 'video', tmp_path, *option)
    assert status == 2 and message in err


# ----------------------------------------------------------------------------- scene XML

SCENE = """<scene version="3.0.0">
    <integrator type="nerfpp">
        {integrator}
    </integrator>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 0, 0.5" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler>
        <film type="hdrfilm"><integer name="width" value="{w}"/><integer name="height" value="{h}"/></film>
    </sensor>
</scene>
"""


def render_xml(capsys, tmp_path, integrator='', spp=1, w=4, h=3):
    scene = tmp_path / 'scene' / 'scene.xml'
    scene.parent.mkdir(exist_ok=True)
    scene.write_text(SCENE.format(integrator=integrator, spp=spp, w=w, h=h))
    return run_cli(capsys, 'render', scene, '-o', tmp_path / 'out.exr')


@pytest.mark.parametrize('integrator, message', [
    ('<integer name="fg_sample" value="8"/>', "nerfpp: unknown parameter(s) fg_sample"),
    ('<string name="fg_samples" value="abc"/>',
     "nerfpp: parameter 'fg_samples' must be given as <integer name=\"fg_samples\""),
    ('<integer name="fg_samples" value="0"/>', "parameter 'fg_samples' must be >= 1, got 0"),
    ('<integer name="fg_samples" value="-3"/>', "parameter 'fg_samples' must be >= 1, got -3"),
    ('<integer name="chunk_rays" value="0"/>', "parameter 'chunk_rays' must be >= 1, got 0"),
    ('<float name="near" value="nan"/>', "parameter 'near' is NaN"),
])
def test_bad_integrator_parameters(capsys, tmp_path, integrator, message):
    status, _, err = render_xml(capsys, tmp_path, integrator)
    line = one_clear_line(err)
    assert status == 1 and message in line and 'scene.xml' in line
    assert not (tmp_path / 'out.exr').exists()


def test_missing_checkpoint_shows_where_it_was_looked_for(capsys, tmp_path):
    status, _, err = render_xml(capsys, tmp_path, '<string name="checkpoint" value="m.npz"/>')
    line = one_clear_line(err)
    assert status == 1 and "checkpoint 'm.npz' not found" in line
    assert str(tmp_path / 'scene' / 'm.npz') in line


def test_sample_count_zero_is_refused_not_a_crash(capsys, tmp_path):
    status, _, err = render_xml(capsys, tmp_path, spp=0)
    assert status == 1 and 'sample_count 0' in one_clear_line(err)


def test_film_beyond_the_budget_is_refused_before_allocating(capsys, tmp_path):
    t0 = time.perf_counter()
    status, _, err = render_xml(capsys, tmp_path, w=20000, h=20000)
    line = one_clear_line(err)
    assert status == 1 and '20000x20000 film' in line and 'max_samples=16777216' in line
    assert time.perf_counter() - t0 < 30
    status, _, err = render_xml(capsys, tmp_path, '<integer name="max_samples" value="10"/>')
    assert status == 1 and 'more than max_samples=10' in one_clear_line(err)


def test_malformed_scene_file_is_one_line(capsys, tmp_path):
    scene = tmp_path / 'bad.xml'
    scene.write_text('<scene version="3.0.0"><integrator type="nerfpp">')
    status, _, err = run_cli(capsys, 'render', scene, '-o', tmp_path / 'out.exr')
    assert status == 1 and one_clear_line(err).startswith('error: render: ')


def test_render_output_that_is_a_folder_is_refused(capsys, tmp_path):
    scene = tmp_path / 'scene.xml'
    scene.write_text(SCENE.format(integrator='', spp=1, w=4, h=3))
    status, _, err = run_cli(capsys, 'render', scene, '-o', tmp_path)
    assert status == 1 and 'is a folder: give a file name' in one_clear_line(err)


def test_resume_with_another_compositing_space_is_refused(capsys, capture, tmp_path):
    out = tmp_path / 'run'
    assert _train(capsys, capture, out, '--composite', 'srgb')[0] == 0
    from mi_nerfpp.checkpoint import load_checkpoint
    assert load_checkpoint(out / 'model.npz')[0].composite == 'srgb'
    status, _, err = _train(capsys, capture, out, '--resume')
    line = one_clear_line(err)
    assert status == 1 and "--composite: the checkpoint has 'srgb', this run asks for " \
        "'linear'" in line
    assert _train(capsys, capture, out, '--resume', '--composite', 'srgb',
                  '--iterations', '3')[0] == 0


def test_resume_of_a_checkpoint_from_before_linear_compositing(capsys, capture, tmp_path):
    """A pre-issue-11 sRGB checkpoint (no 'composite' entry) resumes only as 'srgb'."""
    import json
    out = tmp_path / 'run'
    assert _train(capsys, capture, out, '--composite', 'srgb')[0] == 0
    path = out / 'model.npz'
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    config = json.loads(str(arrays['config']))
    del config['composite'], config['meta']['config']['model']['composite']
    arrays['config'] = np.array(json.dumps(config))
    np.savez(path, **arrays)
    status, _, err = _train(capsys, capture, out, '--resume')
    line = one_clear_line(err)
    assert status == 1 and "--composite: the checkpoint composites in 'srgb'" in line
