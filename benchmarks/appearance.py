"""Held-out PSNR without and with ``--appearance`` on a capture with per-image exposure.

    python benchmarks/appearance.py DATA OUT [--iterations N] [any optimize training option]

Copies the NeRF++-layout capture ``DATA`` to ``OUT/exposed`` with a different exposure and
white balance per image (:func:`mi_nerfpp.data.synth.vary_exposure`, ±0.5 / ±0.1 stops; training
image 0 untouched), trains ``--iterations`` steps (default 150) from scratch without and with
``--appearance`` (otherwise the same options), and prints for each: held-out PSNR scored NeRF-W
style (each test image's transform fitted on its left half, right half scored), the neutral
full-image PSNR, and for the appearance run the error of the learned gains against the applied
ones (|log ratio|, mean and max). Results: ``benchmarks/results/appearance.json``.
"""
import argparse
import os

import numpy as np

import mi_nerfpp  # noqa: F401
from mi_nerfpp.core import appearance as app
from mi_nerfpp.jobs import bench
from mi_nerfpp.training.config import TrainConfig
from mi_nerfpp.jobs.console import ConsoleObserver
from mi_nerfpp.data import load_dataset
from mi_nerfpp.training.options import add_options, values
from mi_nerfpp.data.synth import vary_exposure


def main():
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('data')
    p.add_argument('out')
    add_options(p, TrainConfig)
    args = p.parse_args()
    options = dict(values(args, TrainConfig), checkpoint_every=0, preview_every=0, minutes=None)
    options['iterations'] = options['iterations'] or 150
    cfg = TrainConfig.from_options(**options)
    exposed = os.path.join(args.out, 'exposed')
    true = vary_exposure(args.data, exposed, seed=1)['train']
    dataset = load_dataset(exposed)
    rows = []
    for on, run, tr, r in bench.without_and_with(dataset, cfg, args.out, 'appearance',
                                                 fit_appearance=True,
                                                 observer=ConsoleObserver('train')):
        line = (f'appearance={on!s:5} {run.schedule.iterations} steps: held-out PSNR (NeRF-W, '
                f'right half) {r["psnr"]:.2f} dB, neutral {r["psnr_neutral"]:.2f} dB')
        row = [f'--{"" if on else "no-"}appearance', run.schedule.iterations, r['psnr'],
               r['psnr_neutral'], '-', '-']
        if on:
            err = np.abs(np.log(app.gains_biases(tr.model.appearance.numpy())[0] / true))
            line += f'; learned gains |log ratio| mean {err.mean():.3f} max {err.max():.3f}'
            row[4:] = [float(err.mean()), float(err.max())]
        rows.append(row)
        print(line, flush=True)
    bench.write_results('appearance', 'Per-image appearance on a capture with varied exposure', [
        bench.table('Held-out PSNR without and with --appearance',
                    ['setting', 'iterations', 'held-out PSNR, NeRF-W right half (dB)',
                     'neutral PSNR (dB)', 'gain |log ratio| mean', 'gain |log ratio| max'],
                    rows)],
        notes='Exposure ±0.5 stops and white balance ±0.1 stops per training image (image 0 '
              'untouched); both runs from scratch with the same options.')


if __name__ == '__main__':
    main()
