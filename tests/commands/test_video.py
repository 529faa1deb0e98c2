"""`python -m mi_nerfpp video`: frames as files, resumed after an interruption."""
import os
import sys

from mi_nerfpp.commands.cli import main
from mi_nerfpp.output.video import frame_files

VIDEO = ['--frames', '3', '--res', '24x18']


def test_video_resumes_skipping_written_frames(tiny_run, tmp_path, capsys):
    out = str(tmp_path / 'orbit.gif')
    frames = str(tmp_path / 'orbit_frames')
    assert main(['video', tiny_run, '-o', out, '--exr'] + VIDEO) == 0
    files = [p for i in range(3) for p in frame_files(frames, i, exr=True)]
    assert all(os.path.getsize(p) > 0 for p in files)
    written = {p: os.stat(p).st_mtime_ns for p in files}
    os.remove(frame_files(frames, 1)[0])              # as if interrupted before frame 1's PNG
    os.remove(out)
    assert main(['video', tiny_run, '-o', out, '--exr'] + VIDEO) == 0
    for p in files:
        assert os.path.exists(p)
        if '00001' not in p:
            assert os.stat(p).st_mtime_ns == written[p], p          # not rendered again
    assert os.path.getsize(out) > 0
    capsys.readouterr()
    # Frames of another job are not mixed in.
    assert main(['video', tiny_run, '-o', out, '--frames', '3', '--res', '32x24']) == 1
    err = capsys.readouterr().err
    assert 'holds the frames of another video' in err and 'size' in err


def test_ray_option_without_ray_says_how_to_install(tiny_run, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, 'ray', None)       # as where the extra is not installed
    assert main(['video', tiny_run, '-o', str(tmp_path / 'v.gif'), '--ray'] + VIDEO) == 1
    assert "pip install -e '.[cluster]'" in capsys.readouterr().err


def test_video_of_another_aspect_ratio_keeps_square_pixels(tiny_run, tmp_path):
    # The capture is 4:3; a 16:9 video shows less above and below, with square pixels.
    out = tmp_path / 'wide.gif'
    assert main(['video', tiny_run, '-o', str(out), '--frames', '2', '--res', '32x18']) == 0
    import imageio.v3 as iio
    assert iio.imread(out).shape[1:3] == (18, 32)


def test_video_without_skipping_renders_whole_rays(tiny_run, tmp_path, capsys):
    """``--no-skip-empty`` renders through an integrator that ignores the occupancy grids (the
    frames differ from the default's), and its frames are another video's."""
    import imageio.v3 as iio
    import numpy as np

    from mi_nerfpp.jobs.cluster import FrameWorker
    whole = FrameWorker(os.path.join(tiny_run, 'model.npz'), look={'skip_empty': False}).load()
    assert whole.scene.integrator().skip_empty is False
    assert whole.scene.integrator().sampling.bg_samples == 64
    out = {}
    for name, extra in (('skipped', []), ('whole', ['--no-skip-empty'])):
        out[name] = str(tmp_path / f'{name}.gif')
        assert main(['video', tiny_run, '-o', out[name]] + extra + VIDEO) == 0
    a = iio.imread(frame_files(str(tmp_path / 'skipped_frames'), 0)[0]).astype(int)
    b = iio.imread(frame_files(str(tmp_path / 'whole_frames'), 0)[0]).astype(int)
    assert np.abs(a - b).max() > 0
    capsys.readouterr()
    assert main(['video', tiny_run, '-o', out['whole']] + VIDEO) == 1
    assert 'skip_empty' in capsys.readouterr().err


def test_video_renders_a_training_images_appearance_on_request(tiny_run, tmp_path, capsys):
    """``--appearance-image N`` reaches the integrator of the frames (and makes them another
    video's); a model without an appearance per training image refuses it in one line."""
    from mi_nerfpp.files.checkpoint import save_checkpoint
    from mi_nerfpp.jobs.cluster import FrameWorker
    from tests.core.test_appearance import embedded_model
    path = str(tmp_path / 'embedded.npz')
    save_checkpoint(path, embedded_model())
    worker = FrameWorker(path, look={'appearance_image': 2}).load()
    assert worker.scene.integrator().appearance_image == 2
    assert main(['video', tiny_run, '-o', str(tmp_path / 'a.gif'), '--appearance-image', '0']
                + VIDEO) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and '--appearance-image is 0 but the model has no appearance' in err[0]
