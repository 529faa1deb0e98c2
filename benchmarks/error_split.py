"""Where a run's held-out error is: by region of the image and by frequency (issue 47, item 1).

    python benchmarks/error_split.py RUN [--noise-psnr DB] [--sigma PX] [--name N]

RUN is a folder written by ``optimize`` on a synthetic capture (``python -m mi_nerfpp synth``:
its ``capture.json``, the ground-truth layers ``test/gt/*.exr`` and the scene file). Each test
view is rendered with the model's own settings and its error against the test image (in the
encoding the held-out PSNR is scored in) is split (:func:`mi_nerfpp.training.metrics.error_split`)
over these regions:

* ``foreground`` / ``background``: the ground truth's ``fg.A`` (the first surface lies inside
  the foreground sphere, or not);
* ``specular``: the first surface is a mirror or glossy object (its BSDF has a delta or glossy
  lobe: the mirror ball of ``gt_plaza``), found by tracing the pixel centres through the scene;
* ``unseen``: no training view saw the pixel's direction
  (:func:`mi_nerfpp.data.cameras.direction_coverage`, fewer than ``SEEN_BY`` views);
* ``all``.

and by frequency: ``low`` is the error that survives a Gaussian blur of ``--sigma`` pixels
(wrong colours, haze), ``high`` the rest (missing detail). ``--noise-psnr``: the PSNR between
two renders of the ground truth (``benchmarks/noise_ceiling.py``); half their MSE is the noise
each test image holds against the converged render: ``excess`` is each region's MSE less it
(before 2026-11-27 the whole MSE was subtracted, which overstated the excess PSNR). Per region it prints the share of pixels,
the PSNR, the share of the image's squared error, the low and high MSE and the excess PSNR,
summed over the test views. Results: ``benchmarks/results/<--name>.json``.
"""
import argparse
import json
import os

import drjit as dr
import mitsuba as mi
import numpy as np

import mi_nerfpp  # noqa: F401
from mi_nerfpp.data.cameras import direction_coverage, mitsuba_sensor_dict
from mi_nerfpp.files.exr import read_exr
from mi_nerfpp.jobs import bench
from mi_nerfpp.jobs.run import open_run
from mi_nerfpp.output.views import ViewRenderer, encoded_rgb
from mi_nerfpp.training.metrics import SPLIT_SIGMA, error_split
from mi_nerfpp.core.coverage import SEEN_BY

REGIONS = ('foreground', 'background', 'specular', 'unseen', 'all')


def specular_mask(scene, camera):
    """H x W: the pixel centre's first surface has a delta or glossy BSDF lobe."""
    sensor = mi.load_dict(mitsuba_sensor_dict(camera))
    w, h = camera.width, camera.height
    y, x = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing='ij')
    pos = mi.Point2f(mi.Float((x / w).ravel().astype(np.float32)),
                     mi.Float((y / h).ravel().astype(np.float32)))
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    bsdf = si.bsdf(ray)
    flags = dr.select(si.is_valid(), bsdf.flags(), 0)
    lobes = mi.UInt32(mi.BSDFFlags.Delta | mi.BSDFFlags.Glossy)
    return (np.array(flags & lobes) != 0).reshape(h, w)


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('run', help='a run folder written by optimize on a synthetic capture')
    ap.add_argument('--noise-psnr', type=float, default=None, metavar='DB',
                    help="PSNR between two renders of the ground truth (the capture's noise)")
    ap.add_argument('--sigma', type=float, default=SPLIT_SIGMA, metavar='PX',
                    help=f'blur separating low from high frequencies (default {SPLIT_SIGMA})')
    ap.add_argument('--name', default='error_split', help='results file name')
    a = ap.parse_args()
    model, _, _, dataset = open_run(a.run)
    capture = os.path.join(dataset.root, 'capture.json')
    if not os.path.isfile(capture):
        raise SystemExit(f'{dataset.root}: not a synthetic capture (no capture.json)')
    with open(capture) as f:
        info = json.load(f)
    scene = mi.load_file(info['scene_path'])
    # Two independent renders differ by twice the noise each holds against the converged one.
    noise = 0.0 if a.noise_psnr is None else 0.5 * 10 ** (-a.noise_psnr / 10)
    renderer = ViewRenderer(model)
    sums = {r: {'n': 0, 'se': 0.0, 'low': 0.0, 'high': 0.0} for r in REGIONS}
    total_pixels, total_se = 0, 0.0
    print(f'{"view":>4} ' + ' '.join(f'{r:>10}' for r in REGIONS) + '   (PSNR dB)')
    for i in range(len(dataset.test)):
        camera = dataset.test.cameras[i]
        pred = np.clip(encoded_rgb(renderer.render(camera), model.color_space), 0, 1)
        gt = np.asarray(dataset.test.images[i], dtype=np.float64)[..., :3]
        layers = read_exr(os.path.join(dataset.root, 'test', 'gt', f'{i:06d}.exr'))
        fg = np.asarray(layers['fg.A']).reshape(gt.shape[:2]) > 0.5
        world = dataset.normalization.to_world_camera(camera)     # the scene's own units
        regions = {'foreground': fg, 'background': ~fg,
                   'specular': specular_mask(scene, world),
                   'unseen': direction_coverage(camera, dataset.train.cameras) < SEEN_BY}
        split = error_split(pred, gt, regions, noise, a.sigma)
        print(f'{i:4d} ' + ' '.join(f'{split[r]["psnr"]:10.2f}' for r in REGIONS), flush=True)
        pixels = gt.shape[0] * gt.shape[1]
        total_pixels += pixels
        for r in REGIONS:
            n = round(split[r]['pixels'] * pixels)
            sums[r]['n'] += n
            if n:
                sums[r]['se'] += split[r]['mse'] * n
                sums[r]['low'] += split[r]['low'] * n
                sums[r]['high'] += split[r]['high'] * n
        total_se += split['all']['mse'] * pixels
    rows = []
    for r in REGIONS:
        s = sums[r]
        if not s['n']:
            rows.append([r, 0.0, float('nan'), 0.0, float('nan'), float('nan'), float('nan')])
            continue
        mse = s['se'] / s['n']
        excess = max(mse - noise, 0.0)
        rows.append([r, 100 * s['n'] / total_pixels, 10 * np.log10(1 / mse),
                     100 * s['se'] / total_se, s['low'] / s['n'], s['high'] / s['n'],
                     10 * np.log10(1 / excess) if excess > 0 else float('inf')])
    columns = ['region', 'pixels (%)', 'PSNR (dB)', 'share of the error (%)', 'low MSE',
               'high MSE', 'excess PSNR (dB)']
    for row in rows:
        print(f'{row[0]:>10}: {row[1]:5.1f} % of pixels, {row[2]:6.2f} dB, {row[3]:5.1f} % of '
              f'the error, low {row[4]:.2e} / high {row[5]:.2e}, excess {row[6]:.2f} dB')
    bench.write_results(
        a.name, "Where the held-out error is: by region and frequency",
        [bench.table(f'Test views of {os.path.basename(os.path.normpath(a.run))}', columns,
                     rows)],
        notes=f'Low: the error after a Gaussian blur of {a.sigma:g} px; high: the rest. '
              f'Excess: MSE less the test image\'s noise (half the MSE of two renders '
              f'{"not given" if a.noise_psnr is None else f"at {a.noise_psnr:g} dB"}).')


if __name__ == '__main__':
    main()
