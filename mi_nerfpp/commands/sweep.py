"""``python -m mi_nerfpp sweep DATA...``: one ``optimize`` run per capture and option set.

Every dataset folder is trained with the optimize options given here (the same options as
``optimize``), once per ``--set`` when option sets are given, each in its own run folder
(``OUT/<dataset>`` or ``OUT/<dataset>_<set>``) with its progress in ``optimize.log`` there.
With ``--ray`` the runs are Ray tasks on a cluster (:mod:`mi_nerfpp.jobs.cluster`), else they run
one after the other here. A failed run is reported in the table and the others go on; a run
interrupted before (``model.npz`` without ``metrics.json``) is resumed, a finished one is
reported as it is (``--overwrite`` trains it again). One table of held-out PSNR/SSIM and
times at the end, also written to ``OUT/sweep.json``. The runs are :mod:`mi_nerfpp.jobs.sweep`'s.
"""
from __future__ import annotations

import argparse
import os
import shlex

from tqdm import tqdm

from mi_nerfpp.commands.arguments import positive_int
from mi_nerfpp.commands.video import add_ray_options
from mi_nerfpp.files.atomic import (check_not_a_file, check_writable_folder,
                                    write_json)
from mi_nerfpp.jobs.cluster import check_address, run_tasks, timeout_line
from mi_nerfpp.jobs.sweep import failed, make_jobs, run_job
from mi_nerfpp.training.config import TrainConfig
from mi_nerfpp.training.options import add_options, values


def add_parser(sub):
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
    p = argparse.ArgumentParser(prog='sweep --set', add_help=False)
    add_options(p, TrainConfig)
    p.set_defaults(**{a.dest: defaults[a.dest] for a in p._actions if a.dest in defaults})
    return p


def option_sets(args):
    """``[(text, options)]``: each ``--set`` as given and the training options it makes on top
    of the command line's (one set of those alone without ``--set``)."""
    parser = option_parser(vars(args))
    return [(text, values(parser.parse_args(shlex.split(text)), TrainConfig))
            for text in args.option_sets or ['']]


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


def subject(args):
    return 'datasets ' + ' '.join(args.data)


def run(args):


    check_not_a_file(args.out)
    jobs = make_jobs(args.data, option_sets(args), args.out, args.overwrite)
    if args.ray:
        check_address(args.ray)     # ray not installed, or no cluster there: before any work
    check_writable_folder(args.out, what='sweep folder (--out)')
    rows = {}
    with tqdm(total=len(jobs), desc='sweep', unit='run', dynamic_ncols=True) as bar:
        for job, row in run_tasks(run_job, jobs, failed, args.ray, args.task_cpus,
                                  exit_line=timeout_line('sweep', args.ray)):
            rows[job.name] = row
            bar.write(f"{row['name']}: {row['status']}")
            bar.update(1)
    rows = [rows[job.name] for job in jobs]
    os.makedirs(args.out, exist_ok=True)
    write_json(os.path.join(args.out, 'sweep.json'), rows, text=True)
    print(table(rows))
    print(f"{sum(r['status'] != 'failed' for r in rows)} of {len(rows)} runs finished; "
          f"results in {os.path.join(args.out, 'sweep.json')}")
    return 1 if any(r['status'] == 'failed' for r in rows) else 0
