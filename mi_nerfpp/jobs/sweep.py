"""Many training runs: one per capture and option set, each in its own run folder.

A :class:`SweepJob` is one run: a dataset, a :class:`~mi_nerfpp.training.config.TrainConfig` and the
run folder ``OUT/<dataset>`` (or ``OUT/<dataset>_<set>`` for an option set). :func:`run_job`
trains it with :func:`mi_nerfpp.jobs.run.optimize`, its progress written to ``optimize.log`` in the
run folder, and returns the row of the sweep's table; it never raises for a failed run (the
row says why), so that the other runs go on. A run interrupted before (``model.npz`` without
``metrics.json``: a killed worker, which Ray retries) is resumed; a finished one is reported
as it is unless the job says ``overwrite``. The ``sweep`` command runs the jobs here or as Ray
tasks (:func:`mi_nerfpp.jobs.cluster.run_tasks`).
"""
from __future__ import annotations

import os
import re
import time
from dataclasses import dataclass

from mi_nerfpp.core import budget
from mi_nerfpp.errors import error_line
from mi_nerfpp.files.readers import read_json
from mi_nerfpp.jobs import run
from mi_nerfpp.jobs.cluster import set_threads
from mi_nerfpp.training.config import TrainConfig


@dataclass
class SweepJob:
    """One run of a sweep: ``name`` (its folder's), the option set as given (``options``, ''
    for none), the dataset folder ``data``, the run folder ``out`` and the ``config``."""
    name: str
    options: str
    data: str
    out: str
    config: TrainConfig
    overwrite: bool = False


def slug(text):
    """An option set as part of a folder name: ``--field nerf`` -> ``field-nerf``."""
    return re.sub(r'[^A-Za-z0-9.]+', '-', text).strip('-')


def make_jobs(datasets, option_sets, out, overwrite=False) -> list[SweepJob]:
    """One job per dataset folder and option set. ``option_sets``: ``[(text, options)]``, the
    option set as given and its options by name (all of them, see
    :meth:`~mi_nerfpp.training.config.TrainConfig.from_options`); every config is checked here, its
    sizes too (:func:`mi_nerfpp.core.budget.plan` on this machine; each run plans again where it
    runs), so bad options stop the sweep before any run (ValueError naming the flag)."""
    names = [os.path.basename(os.path.normpath(d)) for d in datasets]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ValueError(f'several datasets are named {", ".join(twice)}: their run folders '
                         f'would collide; sweep folders with distinct names')
    configs = []
    for text, options in option_sets:
        config = TrainConfig.from_options(**options)
        budget.check(budget.plan(config.sizing()))
        configs.append((text, config))
    jobs = []
    for data, name in zip(datasets, names):
        for text, config in configs:
            label = f'{name}_{slug(text)}' if text else name
            jobs.append(SweepJob(label, text, os.path.abspath(data),
                                 os.path.abspath(os.path.join(out, label)), config, overwrite))
    return jobs


def run_job(job: SweepJob, threads=None) -> dict:
    """Train ``job`` (``threads``: Dr.Jit's CPU threads, on a Ray worker) and return its row:
    name, options, run folder, status (``ok``, ``finished before`` or ``failed`` with the
    ``error``), held-out PSNR/SSIM, iterations, training and wall seconds."""
    row = {'name': job.name, 'options': job.options, 'out': job.out}
    metrics_path = os.path.join(job.out, 'metrics.json')
    start = time.perf_counter()
    try:
        if threads:
            set_threads(threads)
        os.makedirs(job.out, exist_ok=True)
        done = finished(job.out) and not job.overwrite
        if not done:
            _train(job)
        metrics = read_json(metrics_path, what='metrics file', remedy='evaluate the run again '
                            f'(mi-nerfpp evaluate {job.out})')
        test = metrics.get('test', {})
        row.update(status='finished before' if done else 'ok', psnr=test.get('psnr'),
                   ssim=test.get('ssim'), iterations=metrics.get('iterations'),
                   train_seconds=metrics.get('train_seconds'))
    except Exception as e:
        row.update(status='failed', error=error_line(e))
    row['wall_seconds'] = round(time.perf_counter() - start, 2)
    return row


def finished(out) -> bool:
    """Whether the run folder ``out`` holds a finished run: its model and the metrics of its
    evaluation (:mod:`mi_nerfpp.jobs.run` never leaves metrics beside another run's model)."""
    return all(os.path.isfile(os.path.join(out, name)) for name in ('model.npz', 'metrics.json'))


def _train(job):
    """The job's run, its progress and outcome (or error) written to ``optimize.log``."""
    # Resume a run a killed worker left (Ray retries the task), not one finished.
    resume = os.path.exists(os.path.join(job.out, 'model.npz')) and not job.overwrite
    # surrogateescape: a path of non-UTF-8 bytes in a line is written as its bytes.
    with open(os.path.join(job.out, 'optimize.log'), 'a', errors='surrogateescape') as log:
        try:
            result = run.optimize(job.data, job.config, job.out, resume=resume,
                                  overwrite=job.overwrite, observer=run.LogObserver(log))
        except Exception as e:
            log.write(f'error: {error_line(e)}\n')
            raise
        if not result.finished:
            raise RuntimeError(f'training was interrupted at iteration '
                               f'{result.trainer.iteration} (see {job.out}/optimize.log)')
        lines, warnings = run.summary(result)
        log.write('\n'.join(lines + warnings) + '\n')


def failed(job: SweepJob, error) -> dict:
    """The row of a job whose task failed outside :func:`run_job` (its worker died for good)."""
    return {'name': job.name, 'options': job.options, 'out': job.out, 'status': 'failed',
            'error': f'the task failed: {error}'}
