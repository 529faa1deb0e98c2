"""Does rendering with more samples per ray than a model was trained with improve it?

    python benchmarks/render_samples.py RUN [--samples FG BG FINE ...]

Renders the held-out views of a training run (a folder written by ``optimize``) once with the
sample counts it was trained with and once with each ``--samples`` triple (coarse foreground,
coarse background, fine per volume: the ``nerfpp`` integrator's ``fg_samples``,
``bg_samples`` and ``fine_samples``), and prints the held-out PSNR of each, with the PSNR per
view and the render time of all views. The renders go to a temporary folder; the run is not
changed. Results: ``benchmarks/results/render_samples.json``.
"""
import argparse
import dataclasses
import tempfile

import mi_nerfpp  # noqa: F401
from mi_nerfpp.jobs import bench
from mi_nerfpp.training.evaluate import evaluate_split
from mi_nerfpp.jobs.run import open_run


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('run')
    ap.add_argument('--samples', type=int, nargs=3, action='append',
                    metavar=('FG', 'BG', 'FINE'),
                    help='sample counts to compare (repeatable; default: 32 32 32, 16 16 48 and '
                         '32 32 16)')
    a = ap.parse_args()
    model, _, _, dataset = open_run(a.run)
    if not len(dataset.test):
        raise SystemExit(f'error: {a.run}: its dataset has no test views to score')
    base = model.sampling           # what it was trained with (its render settings)
    trained = (base.fg_samples, base.bg_samples, base.fine_samples)
    others = [tuple(s) for s in (a.samples or [(32, 32, 32), (16, 16, 48), (32, 32, 16)])]
    rows = []
    with tempfile.TemporaryDirectory() as out:
        for samples in [trained] + [o for o in others if o != trained]:
            fg, bg, fine = samples
            sampling = dataclasses.replace(base, fg_samples=fg, bg_samples=bg, fine_samples=fine)
            m = evaluate_split(model, dataset.test, out, sampling)
            label = ' '.join(map(str, samples)) + (' (trained)' if samples == trained else '')
            views = ', '.join(f"{v['psnr']:.2f}" for v in m['views'])
            print(f'samples {label}: held-out PSNR {m["psnr"]:.2f} dB (views {views}); '
                  f'{m["render_seconds"]:.1f} s for {len(dataset.test)} views', flush=True)
            rows.append([label, m['psnr'], m['render_seconds']])
    bench.write_results('render_samples', 'Rendering with more samples than trained with', [
        bench.table('Held-out PSNR by sample counts (coarse fg, coarse bg, fine)',
                    ['samples', 'held-out PSNR (dB)', f'render time of {len(dataset.test)} views (s)'],
                    rows)],
        notes=f'Run {a.run}.')


if __name__ == '__main__':
    main()
