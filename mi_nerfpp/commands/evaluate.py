"""``python -m mi_nerfpp evaluate RUN``: re-run the held-out evaluation of a training run."""
from __future__ import annotations

import sys

from mi_nerfpp.jobs.console import ConsoleObserver
from mi_nerfpp.jobs.run import evaluate_run
from mi_nerfpp.training.evaluate import matte_warning


def add_parser(sub):
    p = sub.add_parser('evaluate', help='re-run the held-out evaluation of a training run')
    p.add_argument('run', help='run folder written by optimize (holds model.npz)')
    p.set_defaults(func=run)
    return p


def subject(args):
    return f'run folder {args.run}'


def run(args):


    metrics = evaluate_run(args.run, ConsoleObserver())     # errors: reported by mi_nerfpp.commands.cli
    if 'test' in metrics:
        print(f'{len(metrics["test"]["views"])} held-out views: PSNR '
              f'{metrics["test"]["psnr"]:.2f} dB, SSIM {metrics["test"]["ssim"]:.3f}; '
              f'written to {args.run}/metrics.json and test/')
        warning = matte_warning(metrics['test'])
        if warning:
            print(warning, file=sys.stderr)
    else:
        print(f'{metrics["dataset"]} has no test or validation views to evaluate')
