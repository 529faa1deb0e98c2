"""NeRF versus NeRF++ on the same capture with the same wall-time budget (paper §5).

    python benchmarks/compare.py [DATA] [--minutes 10] [--out runs/compare]
                                 [any other optimize training option]

Trains ``--model nerf`` (one bounded volume, cameras scaled into radius 1/8, both volumes'
samples in the one volume) and ``--model nerfpp`` for the same number of minutes of training
steps, evaluating the held-out views every ``--every`` minutes. Prints a table (PSNR, SSIM,
iterations, wall time, samples/s) and writes ``OUT/psnr_vs_time.png`` and ``OUT/side_by_side.png``
(ground truth / NeRF / NeRF++ / NeRF++ foreground over black / NeRF++ background, as in the
paper's Figures 5-6). Without DATA the embedded default capture is used. Results (the table
and both pictures): ``benchmarks/results/compare.json``.
"""
import argparse
import os
import sys

import numpy as np


def train(data, out, model, minutes, every, extra):
    """Train ``model`` for ``minutes`` into ``out`` (held-out views every ``every`` minutes);
    its metrics."""
    from mi_nerfpp.jobs import bench, run
    from mi_nerfpp.training.config import TrainConfig
    from mi_nerfpp.jobs.console import ConsoleObserver
    options = dict(bench.training_options(extra), model=model, minutes=minutes, iterations=None,
                   preview_every=0,
                   eval_at=tuple(float(m) for m in np.arange(every, minutes, every)))
    result = run.optimize(data, TrainConfig.from_options(**options), out,
                          observer=ConsoleObserver(model))
    if not result.finished:
        sys.exit(f'training {model} was interrupted')
    return result.metrics


def picture(data, runs, path, view=0):
    import imageio.v3 as iio

    from mi_nerfpp.data import load_dataset
    from mi_nerfpp.files.exr import read_exr
    from mi_nerfpp.core.color import to_srgb8
    test = load_dataset(data).test
    gt = (np.clip(test.images[view], 0, 1) * 255).astype(np.uint8)
    nerf = read_exr(os.path.join(runs['nerf'], 'test', f'test_{view:03d}.exr'))
    pp = read_exr(os.path.join(runs['nerfpp'], 'test', f'test_{view:03d}.exr'))

    def img(layers, prefix=''):
        return to_srgb8(np.stack([layers[prefix + c] for c in 'RGB'], -1), 'linear')   # EXRs are scene-linear
    panels = [gt, img(nerf), img(pp), img(pp, 'fg.'), img(pp, 'bg.')]
    iio.imwrite(path, np.concatenate(panels, axis=1))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('data', nargs='?')
    ap.add_argument('--minutes', type=float, default=10.0)
    ap.add_argument('--every', type=float, default=1.0, help='evaluate every this many minutes')
    ap.add_argument('--out', default='runs/compare')
    ap.add_argument('--view', type=int, default=0, help='test view of the side-by-side picture')
    a, extra = ap.parse_known_args()

    import mi_nerfpp  # noqa: F401
    from mi_nerfpp.data.synth import default_capture
    data = a.data or default_capture()
    runs = {m: os.path.join(a.out, m) for m in ('nerf', 'nerfpp')}
    metrics = {m: train(data, runs[m], m, a.minutes, a.every, extra) for m in runs}

    print(f'\nNeRF vs NeRF++ on {data}, {a.minutes:g} min of training each '
          f'({len(metrics["nerfpp"]["test"]["views"])} held-out views)')
    print('| model | PSNR (dB) | SSIM | iterations | training time (s) | samples/s |')
    print('|---|---|---|---|---|---|')
    for m, r in metrics.items():
        print(f'| {"NeRF" if m == "nerf" else "NeRF++"} | {r["test"]["psnr"]:.2f} | '
              f'{r["test"]["ssim"]:.3f} | {r["iterations"]} | {r["train_seconds"]:.0f} | '
              f'{r["train_samples_per_second"] / 1e6:.2f} M |')

    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for m, r in metrics.items():
        pts = [(p['minutes'], p['psnr']) for p in r.get('progress', [])]
        pts.append((r['train_seconds'] / 60, r['test']['psnr']))
        ax.plot(*zip(*pts), marker='o', label='NeRF' if m == 'nerf' else 'NeRF++')
    ax.set(xlabel='minutes of training', ylabel='held-out PSNR (dB)')
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(a.out, 'psnr_vs_time.png'), dpi=100)
    picture(data, runs, os.path.join(a.out, 'side_by_side.png'), a.view)
    print(f'plot: {a.out}/psnr_vs_time.png, picture: {a.out}/side_by_side.png '
          f'(GT / NeRF / NeRF++ / NeRF++ fg / NeRF++ bg)')
    from mi_nerfpp.jobs import bench
    bench.write_results('compare', 'NeRF versus NeRF++ at the same wall-time budget', [
        bench.table(f'{a.minutes:g} min of training each',
                    ['model', 'PSNR (dB)', 'SSIM', 'iterations', 'training time (s)',
                     'M samples/s'],
                    [['NeRF' if m == 'nerf' else 'NeRF++', r['test']['psnr'], r['test']['ssim'],
                      r['iterations'], r['train_seconds'], r['train_samples_per_second'] / 1e6]
                     for m, r in metrics.items()],
                    note=f'{len(metrics["nerfpp"]["test"]["views"])} held-out views.'),
        bench.table('Held-out PSNR (dB) during training', ['minutes', 'NeRF', 'NeRF++'],
                    [[p['minutes'], p['psnr'], q['psnr']] for p, q in
                     zip(metrics['nerf']['progress'], metrics['nerfpp']['progress'])])],
        figures=[os.path.join(a.out, 'psnr_vs_time.png'), os.path.join(a.out, 'side_by_side.png')],
        notes='Side by side: ground truth / NeRF / NeRF++ / NeRF++ foreground over black / '
              'NeRF++ background (paper Figures 5-6).')


if __name__ == '__main__':
    main()
