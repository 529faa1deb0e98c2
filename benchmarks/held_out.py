"""Held-out quality of finished runs, side by side (iteration-matched comparisons).

    python benchmarks/held_out.py LABEL=RUN [LABEL=RUN ...] [--name held_out] [--note TEXT]

Time-matched quality needs the machine alone for every minute of every run; a comparison at
*iteration-matched* budgets does not: train each version for the number of steps it takes in
the same wall time (from a side-by-side speed measurement, ``benchmarks/versus.py train``),
whatever else the machine does meanwhile, then compare the held-out scores here. For each run
folder (written by ``optimize``) this reads ``metrics.json`` and prints the capture, the steps
and rays per step, the held-out PSNR and SSIM (mean and worst view) and the PSNR of each test
view. Results: ``benchmarks/results/<--name>.json``; ``--note`` says how the budgets were chosen.
"""
import argparse
import json
import os

import mi_nerfpp  # noqa: F401
from mi_nerfpp.jobs import bench


def read_run(run):
    """(metrics of the run folder ``run``, its final held-out scores)."""
    path = os.path.join(run, 'metrics.json')
    if not os.path.isfile(path):
        raise SystemExit(f'error: held_out: {run} has no metrics.json (not a finished run)')
    with open(path) as f:
        metrics = json.load(f)
    if 'test' not in metrics:
        raise SystemExit(f'error: held_out: {path} has no held-out scores (run not finished?)')
    return metrics, metrics['test']


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('runs', nargs='+', metavar='LABEL=RUN')
    parser.add_argument('--name', default='held_out', help='results file name (default held_out)')
    parser.add_argument('--note', default=None, help='how the budgets were chosen')
    args = parser.parse_args(argv)
    rows, views = [], []
    for item in args.runs:
        label, sep, run = item.partition('=')
        if not sep or not run:
            raise SystemExit(f'error: held_out: {item!r} is not LABEL=RUN')
        metrics, test = read_run(run)
        config = metrics['config']             # nested groups, or flat (runs before issue 36)
        schedule = config.get('schedule', config)
        per_view = [v['psnr'] for v in test['views']]
        rows.append([label, os.path.basename(os.path.normpath(metrics['dataset'])),
                     metrics['iterations'], schedule['batch_rays'], round(test['psnr'], 2),
                     round(min(per_view), 2), round(test['ssim'], 3)])
        views.append([label] + [round(p, 2) for p in per_view])
        print(f'{label:>12}  {rows[-1][1]:>10}  {rows[-1][2]:>6} steps x {rows[-1][3]:>5} rays  '
              f'PSNR {rows[-1][4]:6.2f} (worst {rows[-1][5]:5.2f})  SSIM {rows[-1][6]:.3f}')
    n_views = max(len(v) - 1 for v in views)
    tables = [bench.table('Held-out scores', ['run', 'capture', 'steps', 'rays per step',
                                              'PSNR (dB)', 'worst view (dB)', 'SSIM'], rows,
                          note=args.note),
              bench.table('PSNR of each test view (dB)',
                          ['run'] + [f'view {i}' for i in range(n_views)],
                          [v + [''] * (n_views + 1 - len(v)) for v in views])]
    path = bench.write_results(args.name, 'Held-out quality at matched budgets', tables)
    print(f'results: {path}')


if __name__ == '__main__':
    main()
