"""``python -m mi_nerfpp evaluate RUN``: re-run the held-out evaluation of a training run."""
from __future__ import annotations

import os


def add_parser(sub):
    p = sub.add_parser('evaluate', help='re-run the held-out evaluation of a training run')
    p.add_argument('run', help='run folder written by optimize (holds model.npz)')
    p.set_defaults(func=run)
    return p


def run(args):
    import sys

    from ..evaluate import finish_run, matte_warning
    from ..train import samples_per_second
    from . import open_run_or_exit

    model, meta, cfg, dataset = open_run_or_exit(args.run)
    held_out = dataset.test if len(dataset.test) else dataset.validation
    metrics = finish_run(args.run, model, held_out, cfg, os.path.join(args.run, 'model.npz'), {
        'dataset': dataset.root, 'iterations': meta['iteration'],
        'train_seconds': round(meta['elapsed'], 2),
        'train_samples_per_second': samples_per_second(cfg, meta['iteration'], meta['elapsed'])})
    if 'test' in metrics:
        print(f'{len(held_out)} held-out views: PSNR {metrics["test"]["psnr"]:.2f} dB, '
              f'SSIM {metrics["test"]["ssim"]:.3f}; written to {args.run}/metrics.json and test/')
        warning = matte_warning(metrics['test'])
        if warning:
            print(warning, file=sys.stderr)
    else:
        print(f'{dataset.root} has no test or validation views to evaluate')
