"""A training run through the library (mi_nerfpp.jobs.run): what it reports, writes and plots."""
import os

import numpy as np
import pytest

from mi_nerfpp.jobs import run
from mi_nerfpp.training.config import TrainConfig


class Recorder(run.RunObserver):
    """Keeps every event of a run."""

    def __init__(self):
        self.events = []

    def notice(self, text):
        self.events.append(('notice', text))

    def started(self, trainer, inputs):
        self.events.append(('started', trainer.iteration))

    def step(self, trainer, loss, psnr):
        self.events.append(('step', trainer.iteration))

    def evaluated(self, point):
        self.events.append(('evaluated', point))

    def preview(self, trainer, path):
        self.events.append(('preview', path))

    def trained(self, trainer, finished):
        self.events.append(('trained', finished))

    def track(self, iterable, desc='', unit='it', leave=True):
        self.events.append(('track', desc))
        return iterable

    def of(self, kind):
        return [e[1] for e in self.events if e[0] == kind]


def test_a_run_reports_to_its_observer_writes_its_files_and_prints_nothing(
        capture, tmp_path, capsys, monkeypatch):
    import matplotlib.figure
    figures = []
    monkeypatch.setattr(matplotlib.figure.Figure, 'savefig',
                        lambda fig, path, **kw: figures.append((fig, path)))
    cfg = TrainConfig.from_options(iterations=12, batch_rays=256, fg_samples=8, bg_samples=8,
                                   fine_samples=8, checkpoint_every=0, preview_every=6,
                                   eval_at=(1e-4,))
    observer = Recorder()
    out = str(tmp_path / 'run')
    result = run.optimize(capture, cfg, out, observer=observer)
    assert capsys.readouterr() == ('', '')                  # the library prints nothing
    assert result.finished and result.trainer.iteration == 12
    assert observer.of('started') == [0] and observer.of('step') == list(range(1, 13))
    assert observer.of('trained') == [True] and observer.of('track') == ['evaluate test']
    previews = observer.of('preview')
    assert previews == [os.path.join(out, 'preview', f'iter_{i:06d}.png') for i in (6, 12)]
    assert all(os.path.exists(p) for p in previews)
    # The evaluation after 1e-4 minutes: done after the first step, recorded in metrics.json.
    (point,) = observer.of('evaluated')
    assert point['minutes'] == 1e-4 and point['iteration'] == 1
    assert os.path.exists(os.path.join(out, 'test_at_0.0001min', 'test_000.exr'))
    assert result.metrics['progress'] == [point] and result.progress == [point]
    # (what the run chose from the capture: the resolution, no level in bricks in either
    # volume (a cell of the 128 level spans under two pixels at 32x24) and uniform rays, no
    # per-photo appearance and no pose refinement for a rendered capture)
    assert result.metrics['config'] == cfg.replace(downscale=1, grid_sparse=(),
                                                   bg_grid_sparse=(), error_rays=0.0,
                                                   appearance=False,
                                                   refine_poses=False).to_dict()
    # training.png: the loss named as it is computed, the held-out PSNR as points.
    (fig, path), = figures
    assert path == os.path.join(out, 'training.png')
    loss_ax, psnr_ax = fig.axes
    assert 'Charbonnier' in loss_ax.get_ylabel() and 'MSE' not in loss_ax.get_ylabel()
    (points,) = [line for line in psnr_ax.get_lines() if line.get_marker() == 'o']
    np.testing.assert_allclose(points.get_xdata(), [60e-4, result.metrics['train_seconds']])
    np.testing.assert_allclose(points.get_ydata(), [point['psnr'],
                                                    result.metrics['test']['psnr']])
    lines, warnings = run.summary(result)
    assert lines[0].startswith('trained 12 iterations') and f'written to {out}/' in lines[-2]


def test_prepare_refuses_a_run_folder_that_holds_a_run(capture, tmp_path):
    (tmp_path / 'model.npz').write_bytes(b'a run')
    with pytest.raises(ValueError, match='already holds a trained run'):
        run.prepare(capture, TrainConfig(), str(tmp_path))
    with pytest.raises(ValueError, match='exclude each other'):
        run.prepare(capture, TrainConfig(), str(tmp_path), resume=True, overwrite=True)


def test_default_job_takes_the_default_budget_unless_one_is_given(monkeypatch):
    from mi_nerfpp.training.config import DEFAULT_JOB_EVAL_AT, DEFAULT_JOB_MINUTES
    monkeypatch.setattr(run, 'default_capture', lambda progress: 'the capture')
    data, options = run.default_job({'iterations': None, 'minutes': None, 'eval_at': None})
    assert data == 'the capture'
    assert options == {'iterations': None, 'minutes': DEFAULT_JOB_MINUTES,
                       'eval_at': DEFAULT_JOB_EVAL_AT}
    _, options = run.default_job({'iterations': 3, 'minutes': None, 'eval_at': None})
    assert options == {'iterations': 3, 'minutes': None, 'eval_at': None}
    _, options = run.default_job({'iterations': None, 'minutes': None, 'eval_at': ()})
    assert options['minutes'] == DEFAULT_JOB_MINUTES and options['eval_at'] == ()


def test_allocation_lines_say_when_the_entries_held_a_level_back():
    allocations = [{'iteration': 10, 'level': 'fg.sparse0', 'bricks': 100, 'of': 4096,
                    'occupied': 100, 'entries': 102400},
                   {'iteration': 30, 'level': 'fg.sparse0', 'bricks': 150, 'of': 4096,
                    'occupied': 200, 'entries': 153600},
                   {'iteration': 30, 'level': 'bg.sparse0', 'bricks': 80, 'of': 2048,
                    'occupied': 80, 'entries': 2000000}]
    assert run.allocation_lines(allocations) == [
        'sparse level fg.sparse0: 150 bricks (0.2 M entries) of the 200 the occupancy grid '
        'asked for: --sparse-entries held it back',
        'sparse level bg.sparse0: 80 bricks (2.0 M entries) where the training rays take '
        'their colour from, of 2,048']
