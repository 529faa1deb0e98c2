"""``python -m mi_nerfpp sweep DATA...``: one ``optimize`` run per capture and option set.

Every dataset folder is trained with the optimize options given here (the same options as
``optimize``), once per ``--set`` when option sets are given, each in its own run folder
(``OUT/<dataset>`` or ``OUT/<dataset>_<set>``) with its output in ``optimize.log`` there. With
``--ray`` the runs are Ray tasks on a cluster (:mod:`mi_nerfpp.cluster`), else they run one
after the other here. A failed run is reported in the table and the others go on; a run
interrupted before (``model.npz`` without ``metrics.json``) is resumed, a finished one is
reported as it is (``--overwrite`` trains it again). One table of held-out PSNR/SSIM and
times at the end, also written to ``OUT/sweep.json``.
"""
from __future__ import annotations

import argparse
import os
import re
import shlex
import time


def add_parser(sub):
    from ..options import add_options
    from ..train import TrainConfig
    from . import positive_int
    from .video import add_ray_options
    p = sub.add_parser('sweep', help='train many captures (or option sets), optionally on a '
                       'Ray cluster, and tabulate held-out PSNR/SSIM', description=__doc__)
    p.add_argument('data', nargs='+', help='dataset folders, one run each')
    p.add_argument('--out', default='runs', help='folder of the run folders (default: runs)')
    p.add_argument('--set', dest='option_sets', action='append', metavar='"OPTIONS"',
                   help='an option set: optimize options for one run per dataset on top of the '
                        'options given here, e.g. --set "--field nerf" or --set=--no-occupancy '
                        '(repeat for several)')
    p.add_argument('--overwrite', action='store_true', help='train finished runs again')
    add_ray_options(p, 'run each training as a Ray task')
    p.add_argument('--task-cpus', type=positive_int, default=1,
                   help='with --ray: CPUs (Dr.Jit threads) of each run (default 1)')
    add_options(p, TrainConfig)
    p.set_defaults(func=run)
    return p


def option_parser(defaults: dict):
    """A parser of optimize's training options only, starting from ``defaults``."""
    from ..options import add_options
    from ..train import TrainConfig
    p = argparse.ArgumentParser(prog='sweep --set', add_help=False)
    add_options(p, TrainConfig)
    p.set_defaults(**{a.dest: defaults[a.dest] for a in p._actions if a.dest in defaults})
    return p


def slug(text):
    return re.sub(r'[^A-Za-z0-9.]+', '-', text).strip('-')


def jobs_of(args):
    """One job per dataset and option set: its name, run folder and optimize arguments."""
    from ..options import values
    from ..train import TrainConfig
    names = [os.path.basename(os.path.normpath(d)) for d in args.data]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ValueError(f'several datasets are named {", ".join(twice)}: their run folders '
                         f'would collide; sweep folders with distinct names')
    jobs = []
    for data, name in zip(args.data, names):
        for options in args.option_sets or ['']:
            parsed = option_parser(vars(args)).parse_args(shlex.split(options))
            TrainConfig(**values(parsed, TrainConfig))     # bad options: stop before any run
            label = f'{name}_{slug(options)}' if options else name
            optimize = argparse.Namespace(data=os.path.abspath(data), out=os.path.abspath(
                os.path.join(args.out, label)), eval_at=None, overwrite=args.overwrite,
                resume=False, **vars(parsed))
            jobs.append({'name': label, 'options': options, 'args': optimize})
    return jobs


def optimize_one(job, threads=None):
    """Run ``optimize`` for one job (output to ``optimize.log`` in its run folder); a result
    row, failures included."""
    import json
    from contextlib import redirect_stderr, redirect_stdout

    from ..cli import error_line
    from . import optimize

    args = job['args']
    row = {'name': job['name'], 'options': job['options'], 'out': args.out}
    metrics_path = os.path.join(args.out, 'metrics.json')
    start = time.perf_counter()
    try:
        if threads:
            from ..cluster import set_threads
            set_threads(threads)
        os.makedirs(args.out, exist_ok=True)
        done = os.path.exists(metrics_path) and not args.overwrite
        if not done:
            # Resume a run a killed worker left (Ray retries the task), not one finished.
            args.resume = os.path.exists(os.path.join(args.out, 'model.npz')) and \
                not args.overwrite
            with open(os.path.join(args.out, 'optimize.log'), 'a') as log, \
                    redirect_stdout(log), redirect_stderr(log):
                status = optimize.run(args)
            if status:
                raise RuntimeError(f'optimize ended with status {status} (see '
                                   f'{args.out}/optimize.log)')
        with open(metrics_path) as f:
            metrics = json.load(f)
        test = metrics.get('test', {})
        row.update(status='finished before' if done else 'ok', psnr=test.get('psnr'),
                   ssim=test.get('ssim'), iterations=metrics.get('iterations'),
                   train_seconds=metrics.get('train_seconds'))
    except (Exception, SystemExit) as e:
        message = str(e.code) if isinstance(e, SystemExit) else error_line(e)
        row.update(status='failed', error=message.removeprefix('error: '))
    row['wall_seconds'] = round(time.perf_counter() - start, 2)
    return row


def failed(job, error):
    return {'name': job['name'], 'options': job['options'], 'out': job['args'].out,
            'status': 'failed', 'error': f'the task failed: {error}'}


def table(rows):
    """The sweep's results as a text table."""
    def number(value, fmt):
        return format(value, fmt) if value is not None else '-'
    head = ('run', 'PSNR dB', 'SSIM', 'iterations', 'train min', 'wall min', 'status')
    lines = [(r['name'], number(r.get('psnr'), '.2f'), number(r.get('ssim'), '.3f'),
              number(r.get('iterations'), 'd'),
              number(r['train_seconds'] / 60 if r.get('train_seconds') is not None else None,
                     '.1f'),
              number(r['wall_seconds'] / 60 if r.get('wall_seconds') is not None else None,
                     '.1f'),
              r['status'] + (f": {r['error']}" if r.get('error') else '')) for r in rows]
    widths = [max(len(x[i]) for x in [head] + lines) for i in range(len(head) - 1)]
    return '\n'.join('  '.join(cell.ljust(w) for cell, w in zip(line, widths)) + '  ' + line[-1]
                     for line in [head] + lines)


def run(args):
    from tqdm import tqdm

    from ..cluster import run_tasks
    from ..evaluate import write_json

    if args.ray:
        from ..cluster import import_ray
        import_ray()                # not installed: say how, before any work
    jobs = jobs_of(args)
    rows = {}
    with tqdm(total=len(jobs), desc='sweep', unit='run', dynamic_ncols=True) as bar:
        for job, row in run_tasks(optimize_one, jobs, failed, args.ray, args.task_cpus):
            rows[job['name']] = row
            bar.write(f"{row['name']}: {row['status']}")
            bar.update(1)
    rows = [rows[job['name']] for job in jobs]
    os.makedirs(args.out, exist_ok=True)
    write_json(os.path.join(args.out, 'sweep.json'), rows)
    print(table(rows))
    print(f"{sum(r['status'] != 'failed' for r in rows)} of {len(rows)} runs finished; "
          f"results in {os.path.join(args.out, 'sweep.json')}")
    return 1 if any(r['status'] == 'failed' for r in rows) else 0
