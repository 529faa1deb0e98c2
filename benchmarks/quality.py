"""Reconstruction quality against time on a synthetic capture, with its ground truth.

    python benchmarks/quality.py [DATA] [--minutes 10] [--eval-at 2 5] [--out runs/quality]
                                 [-- OPTIMIZE OPTIONS...]

Runs ``optimize`` (a child process, so its peak memory is measured alone) for ``--minutes``
of training steps, with held-out evaluations at ``--eval-at`` minutes and at the end. For
each evaluation it reads the written test EXRs and prints, against the capture's
ground truth (``DATA/test/gt/*.exr`` from ``synth``):

* held-out PSNR (mean and the worst view) and SSIM; the same PSNR over the pixels whose
  direction at least ``SEEN_BY`` training views saw ('seen': the rest is extrapolation that
  no method recovers from the capture, ``mi_nerfpp.data.direction_coverage``);
* foreground/background separation (``mi_nerfpp.training.metrics.separation``): mean
  |alpha - alpha_gt|, the foreground opacity where the true mask is 0 (leak), the
  fraction of pixels with 0.05 < alpha < 0.95, median relative depth error where the
  mask is 1;

then the training throughput (rays/s, samples/s) and the child's peak RSS. Without DATA,
the embedded default capture is used. Options after ``--`` go to ``optimize``. Results:
``benchmarks/results/<--name>.json`` (default ``quality``).
"""
import argparse
import glob
import json
import os
import shlex
import subprocess
import sys

import numpy as np


def score(data, test_dir):
    from mi_nerfpp.data import direction_coverage, load_dataset
    from mi_nerfpp.files.exr import read_exr
    from mi_nerfpp.training.metrics import masked_psnr, psnr, separation, ssim
    from mi_nerfpp.core.coverage import SEEN_BY
    from mi_nerfpp.output.views import encoded_rgb
    dataset = load_dataset(data)
    test, test_color_space = dataset.test, dataset.color_space
    gts = sorted(glob.glob(os.path.join(data, 'test', 'gt', '*.exr')))
    rows = []
    for i, gt_path in enumerate(gts):
        layers = read_exr(os.path.join(test_dir, f'test_{i:03d}.exr'))
        gt = read_exr(gt_path)
        # Renders are scene-linear; compare in the encoding of the dataset images.
        pred = np.clip(encoded_rgb(layers, test_color_space), 0, 1)
        seen = direction_coverage(test.cameras[i], dataset.train.cameras) >= SEEN_BY
        row = {'psnr': psnr(pred, test.images[i]), 'ssim': ssim(pred, test.images[i]),
               'psnr_seen': masked_psnr(pred, test.images[i], seen)}
        # Both hold camera-space z.
        row.update(separation(layers['fg.A'], gt['fg.A'], layers['depth.Z'], gt['depth.Z']))
        rows.append(row)
    mean = {k: float(np.nanmean([r[k] for r in rows])) for k in rows[0]}
    mean['worst_psnr'] = min(r['psnr'] for r in rows)
    mean['worst_seen'] = float(np.nanmin([r['psnr_seen'] for r in rows]))
    mean['views'] = [round(r['psnr'], 2) for r in rows]
    return mean


def main():
    argv = sys.argv[1:]
    extra = []
    if '--' in argv:
        extra = argv[argv.index('--') + 1:]
        argv = argv[:argv.index('--')]
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('data', nargs='?')
    ap.add_argument('--minutes', type=float, default=10.0)
    ap.add_argument('--eval-at', type=float, nargs='*', default=[2.0, 5.0])
    ap.add_argument('--out', default='runs/quality')
    ap.add_argument('--name', default='quality',
                    help='name of the results file (benchmarks/results/NAME.json)')
    a = ap.parse_args(argv)

    import mi_nerfpp  # noqa: F401
    from mi_nerfpp.jobs import bench
    from mi_nerfpp.data.synth import default_capture
    data = a.data or default_capture()
    eval_at = [m for m in a.eval_at if m < a.minutes]
    cmd = [sys.executable, '-m', 'mi_nerfpp', 'optimize', data, '--out', a.out, '--minutes',
           str(a.minutes), '--preview-every', '0', '--eval-at', *map(str, eval_at)] + extra
    print('$', ' '.join(cmd), flush=True)
    subprocess.run(cmd, check=True)
    rss = bench.peak_rss_mib(children=True)
    with open(os.path.join(a.out, 'metrics.json')) as f:
        metrics = json.load(f)

    print(f'\n{"minutes":>7} {"iter":>6} {"PSNR":>6} {"worst":>6} {"seen":>6} {"worst":>6} '
          f'{"SSIM":>6} {"|a-a_gt|":>8} '
          f'{"leak":>6} {"soft%":>6} {"depth":>6}  per-view PSNR')
    points = [(p['minutes'], p['iteration'], os.path.join(a.out, f'test_at_{p["minutes"]:g}min'))
              for p in metrics.get('progress', [])]
    points.append((a.minutes, metrics['iterations'], os.path.join(a.out, 'test')))
    rows, views = [], {}
    for minutes, iterations, test_dir in points:
        s = score(data, test_dir)
        rows.append([minutes, iterations, s['psnr'], s['worst_psnr'], s['psnr_seen'],
                     s['worst_seen'], s['ssim'], s['alpha_error'], s['leak'],
                     100 * s['soft_fraction'], s['depth_error']])
        views[f'{minutes:g}'] = s['views']
        print(f'{minutes:7g} {iterations:6d} {s["psnr"]:6.2f} {s["worst_psnr"]:6.2f} '
              f'{s["psnr_seen"]:6.2f} {s["worst_seen"]:6.2f} '
              f'{s["ssim"]:6.3f} {s["alpha_error"]:8.3f} {s["leak"]:6.3f} '
              f'{100 * s["soft_fraction"]:5.1f}% {s["depth_error"]:6.3f}  {s["views"]}')
    cfg = metrics['config']
    rays = metrics['iterations'] * cfg['schedule']['batch_rays'] / metrics['train_seconds']
    print(f'\ntraining: {rays:,.0f} rays/s, {metrics["train_samples_per_second"] / 1e6:.2f} M samples/s '
          f'(field evaluations), {metrics["iterations"]} iterations in {metrics["train_seconds"]:.0f} s')
    print(f'peak RSS of optimize: {rss:.0f} MiB')
    setting = shlex.join(extra) or 'default options'
    bench.write_results(a.name, f'Reconstruction quality against time ({setting})', [
        bench.table('Held-out quality at each evaluation',
                    ['minutes', 'iterations', 'PSNR (dB)', 'worst view (dB)', 'seen PSNR (dB)',
                     'worst seen (dB)', 'SSIM', '|alpha - alpha_gt|', 'leak', 'soft alpha (%)',
                     'depth error'], rows),
        bench.table('Training', ['rays/s', 'M samples/s', 'iterations', 'training time (s)',
                                 'peak RSS of optimize (MiB)'],
                    [[rays, metrics['train_samples_per_second'] / 1e6, metrics['iterations'],
                      metrics['train_seconds'], rss]])],
        raw={'per_view_psnr': views, 'config': cfg})


if __name__ == '__main__':
    main()
