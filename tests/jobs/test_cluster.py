"""Ray (mi_nerfpp/jobs/cluster.py) on a local cluster this module starts: frames on actors equal the
single-process frames, a worker killed with SIGKILL loses no frame, sweep runs captures as tasks."""
import json
import os
import shutil
import signal

import numpy as np
import pytest

ray = pytest.importorskip('ray')

import imageio.v3 as iio  # noqa: E402

from mi_nerfpp.commands.cli import build_parser, main  # noqa: E402
from mi_nerfpp.jobs.cluster import FramePool, FrameWorker  # noqa: E402
from mi_nerfpp.commands.video import cameras_of  # noqa: E402
from mi_nerfpp.files.exr import read_exr  # noqa: E402
from mi_nerfpp.output.video import frame_files, pending_frames, prepare_frames_dir  # noqa: E402
from tests.helpers import TINY_RUN  # noqa: E402

VIDEO = ['--frames', '6', '--res', '24x18', '--exr']


@pytest.fixture(scope='module')
def cluster():
    ray.init(num_cpus=2, include_dashboard=False, configure_logging=False)
    yield
    ray.shutdown()


def assert_same_frames(a, b, count):
    for i in range(count):
        exr_a, exr_b = read_exr(frame_files(a, i, exr=True)[1]), read_exr(frame_files(b, i, exr=True)[1])
        assert set(exr_a) == set(exr_b) and exr_a['R'].shape == (18, 24)
        for name in exr_a:
            np.testing.assert_allclose(exr_a[name], exr_b[name], rtol=1e-4, atol=1e-5,
                                       err_msg=f'frame {i} {name}')
        png_a, png_b = iio.imread(frame_files(a, i)[0]), iio.imread(frame_files(b, i)[0])
        assert np.abs(png_a.astype(int) - png_b.astype(int)).max() <= 1


def test_ray_frames_equal_single_process_frames(tiny_run, cluster, tmp_path):
    here, there = tmp_path / 'here.mp4', tmp_path / 'ray.mp4'
    assert main(['video', tiny_run, '-o', str(here)] + VIDEO) == 0
    assert main(['video', tiny_run, '-o', str(there), '--ray', 'auto', '--workers', '2']
                + VIDEO) == 0
    assert here.stat().st_size > 0 and there.stat().st_size > 0
    assert_same_frames(tmp_path / 'here_frames', tmp_path / 'ray_frames', 6)


def test_ray_frames_of_a_tracked_camera_carry_its_frame_numbers(tiny_run, cluster, tmp_path):
    """``video --path shot.chan --frame-range 1002-1004 --ray``: the Ray workers write
    ``shot.1002`` .. ``shot.1004`` (the file's numbers, nothing else), equal to the frames of
    one process."""
    from mi_nerfpp.jobs import export
    from mi_nerfpp.jobs.run import open_run
    dataset = open_run(tiny_run)[3]
    chan = tmp_path / 'shot.chan'
    export.write_chan(str(chan), dataset.train.cameras[:5])     # frames 1-5
    with open(chan) as f:                                       # renumbered 1001-1005
        lines = [str(1000 + int(line.split()[0])) + line[line.index(' '):] for line in f]
    chan.write_text(''.join(lines))
    shot = ['--path', str(chan), '--frame-range', '1002-1004', '--res', '24x18', '--exr']
    for where, extra in (('here', []), ('there', ['--ray', 'auto', '--workers', '2'])):
        assert main(['video', tiny_run, '-o', str(tmp_path / f'{where}.gif'), '--frames-dir',
                     str(tmp_path / where)] + shot + extra) == 0
    names = [f'shot.{n}.{ext}' for n in (1002, 1003, 1004) for ext in ('exr', 'png')]
    for where in ('here', 'there'):
        assert sorted(n for n in os.listdir(tmp_path / where) if not n.endswith('.json')) \
            == names
    for number in (1002, 1003, 1004):
        a = read_exr(tmp_path / 'here' / f'shot.{number}.exr')
        b = read_exr(tmp_path / 'there' / f'shot.{number}.exr')
        assert set(a) == set(b) and a['R'].shape == (18, 24)
        for name in a:
            np.testing.assert_allclose(a[name], b[name], rtol=1e-4, atol=1e-5,
                                       err_msg=f'frame {number} {name}')


def test_killed_worker_still_yields_every_frame(tiny_run, cluster, tmp_path):
    args = build_parser().parse_args(['video', tiny_run, '--frames', '8', '--res', '24x18'])
    checkpoint, cameras, job = cameras_of(args)
    frames, reference = tmp_path / 'video_frames', tmp_path / 'reference'
    for folder in (frames, reference):
        prepare_frames_dir(str(folder), job)
    FrameWorker(checkpoint).render_frames(dict(enumerate(cameras)), str(reference), exr=True)

    pool = FramePool(checkpoint, workers=2, cpus=1)
    pids = pool.pids()
    killed = []

    def kill_a_worker(count):             # after the first chunk, while the job goes on
        if not killed:
            os.kill(pids[0], signal.SIGKILL)
            killed.append(pids[0])

    try:
        pool.render_frames(cameras, range(8), str(frames), exr=True, chunk=1, on_frames=kill_a_worker)
        assert killed and pool.pids()[0] != pids[0]     # Ray restarted the killed worker
    finally:
        pool.close()
    assert pending_frames(str(frames), 8, exr=True) == []
    assert_same_frames(frames, reference, 8)
    # The command resumes the finished job: nothing to render, no temporary left, the video.
    assert main(['video', tiny_run, '--frames', '8', '--res', '24x18', '--exr', '-o',
                 str(tmp_path / 'video.mp4')]) == 0
    assert not [n for n in os.listdir(frames) if n.startswith('.')]
    assert (tmp_path / 'video.mp4').stat().st_size > 0


def test_sweep_trains_captures_as_tasks_and_tabulates(capture, cluster, tmp_path, capsys):
    for name in ('garden', 'plaza'):
        shutil.copytree(capture, tmp_path / 'captures' / name)
    (tmp_path / 'captures' / 'broken').mkdir()
    runs = tmp_path / 'runs'
    status = main(['sweep'] + [str(tmp_path / 'captures' / n) for n in ('garden', 'broken', 'plaza')]
                  + ['--out', str(runs), '--ray', 'auto'] + TINY_RUN)
    assert status == 1                      # one capture failed, the others finished
    out = capsys.readouterr().out
    rows = {r['name']: r for r in json.loads((runs / 'sweep.json').read_text())}
    assert [r for r in rows] == ['garden', 'broken', 'plaza']
    assert rows['broken']['status'] == 'failed' and 'broken' in rows['broken']['error']
    for name in ('garden', 'plaza'):
        metrics = json.loads((runs / name / 'metrics.json').read_text())
        assert rows[name]['status'] == 'ok' and metrics['iterations'] == 5
        assert (runs / name / 'model.npz').exists() and (runs / name / 'optimize.log').exists()
        line = next(line for line in out.splitlines() if line.startswith(name + ' '))
        assert f"{metrics['test']['psnr']:.2f}" in line and ' ok' in line
    assert 'broken' in out and '2 of 3 runs finished' in out
