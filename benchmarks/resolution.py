"""Held-out quality at the capture's own resolution, and anti-aliasing across resolutions.

    python benchmarks/resolution.py LABEL=RUN [LABEL=RUN ...] [--views N] [--name resolution]

For each finished run (a folder written by ``optimize``; runs of older revisions too) this
renders, with the code of this checkout:

* every test view at the capture's full resolution, scored against the test images (PSNR, SSIM,
  and the equivalent blur in pixels, :func:`mi_nerfpp.training.metrics.equivalent_blur`);
* every test view at the resolution the run *trained* at (a run that shrank the photos),
  upsampled bilinearly to full resolution and scored the same way: what a thumbnail model
  gives at plate size;
* the first ``--views`` training views at half resolution, against the training images
  box-filtered by 2 (the pyramid's level 2), with grid lookups filtered by the pixels'
  footprints (``--antialias``) and with point lookups, whichever the model was trained with
  (on captures whose footprints stay within the finest cells, as the default capture's, the
  two train alike) - the anti-aliasing check of issue 34.

A crop of the first test view from each run, beside the test image, goes to
``results/<name>_crops.png``. Results: ``benchmarks/results/<--name>.json``.
"""
import argparse
import dataclasses
import os
import tempfile

import numpy as np

import mi_nerfpp  # noqa: F401
from mi_nerfpp.jobs import bench
from mi_nerfpp.data import load_dataset
from mi_nerfpp.data.images import downscale_image
from mi_nerfpp.training.metrics import equivalent_blur, psnr, ssim
from mi_nerfpp.jobs.run import open_run
from mi_nerfpp.training.train import in_model_frame
from mi_nerfpp.output.views import ViewRenderer, encoded_rgb


def trained_factor(meta, cfg, dataset):
    """How much smaller than the capture's images the run trained at (1: full size)."""
    rays = meta.get('data', {}).get('training_rays')
    train = dataset.train
    full = len(train) * train.images.stored[0].shape[0] * train.images.stored[0].shape[1]
    if rays:
        return max(1, int(round(np.sqrt(full / rays))))
    return max(1, int(cfg.data.downscale))


def render(renderer, camera, model):
    return np.clip(encoded_rgb(renderer.render(camera), model.color_space), 0.0, 1.0)


def upsample(img, shape):
    from skimage.transform import resize
    return resize(img, shape, order=1, mode='edge', anti_aliasing=False)


def set_antialias(model, on):
    for field in (model.fg, model.bg):
        if field is not None and hasattr(field, 'antialias'):
            field.antialias = on


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('runs', nargs='+', metavar='LABEL=RUN')
    ap.add_argument('--views', type=int, default=8, help='training views scored at half '
                    'resolution (default 8)')
    ap.add_argument('--name', default='resolution', help='results file name')
    a = ap.parse_args()
    rows, half_rows, crops = [], [], []
    for item in a.runs:
        label, _, run = item.partition('=')
        model, meta, cfg, data = open_run(run)
        if cfg.data.downscale != 1:        # score at the capture's own resolution
            full = load_dataset(data.root, downscale=1, background=cfg.data.background)
            data = dataclasses.replace(full, **in_model_frame(full, model.normalization))
        renderer = ViewRenderer(model)
        test = data.test
        factor = trained_factor(meta, cfg, data)
        full, thumb = [], []
        for i in range(len(test)):
            gt = np.asarray(test.images[i], np.float64)
            pred = render(renderer, test.cameras[i], model)
            full.append((psnr(pred, gt), ssim(pred, gt), equivalent_blur(pred, gt)))
            if factor > 1:
                small = render(renderer, test.cameras[i].downscaled(factor), model)
                up = upsample(small, gt.shape)
                thumb.append((psnr(up, gt), ssim(up, gt), equivalent_blur(up, gt)))
            if i == 0:
                if not crops:
                    crops.append(gt)
                crops.append(pred)
        h, w = test.images[0].shape[:2]
        full, thumb = np.array(full), np.array(thumb) if thumb else None
        rows.append([label, f'{w // factor}x{h // factor}', meta.get('iteration'),
                     *full.mean(axis=0).round(3),
                     *(thumb.mean(axis=0).round(3) if thumb is not None else ['-'] * 3)])
        print(f'{label}: trained at {w // factor}x{h // factor}, {meta.get("iteration")} steps; '
              f'{w}x{h} render {full[:, 0].mean():.2f} dB SSIM {full[:, 1].mean():.3f} blur '
              f'{full[:, 2].mean():.2f} px' + (f'; {w // factor}x{h // factor} upsampled '
                                             f'{thumb[:, 0].mean():.2f} dB SSIM '
                                             f'{thumb[:, 1].mean():.3f} blur '
                                             f'{thumb[:, 2].mean():.2f} px'
                                             if thumb is not None else ''), flush=True)
        # Half resolution against the training images box-filtered by 2.
        train = data.train
        trained_aa = model.antialias
        for mode, on in (('footprint-filtered', True), ('point lookups', False)):
            set_antialias(model, on)
            scores = []
            for i in range(min(a.views, len(train))):
                gt = downscale_image(np.asarray(train.images[i], np.float64), 2)
                pred = render(renderer, train.cameras[i].downscaled(2), model)
                scores.append((psnr(pred, gt), ssim(pred, gt)))
            scores = np.array(scores)
            half_rows.append([label, mode, *scores.mean(axis=0).round(3),
                              round(float(scores[:, 0].min()), 2)])
            print(f'  half resolution vs training images / 2, {mode}: '
                  f'{scores[:, 0].mean():.2f} dB (worst view {scores[:, 0].min():.2f}), '
                  f'SSIM {scores[:, 1].mean():.3f}', flush=True)
        set_antialias(model, trained_aa)
    figure = None
    if crops:
        h, w = crops[0].shape[:2]
        y0, x0 = h // 4, w // 4
        strip = np.concatenate([c[y0:y0 + h // 2, x0:x0 + w // 2] for c in crops], axis=1)
        import imageio.v3 as iio
        figure = os.path.join(tempfile.mkdtemp(), 'crops.png')
        # Renders and images in the images' own encoding (sRGB for PNG captures).
        iio.imwrite(figure, (np.clip(strip, 0, 1) * 255 + 0.5).astype(np.uint8))
    bench.write_results(a.name, 'Quality at the capture\'s resolution and across resolutions', [
        bench.table('Test views at full resolution, and rendered at the training size then '
                    'upsampled', ['run', 'trained at', 'steps', 'PSNR (dB)', 'SSIM',
                                  'blur (px)', 'upsampled PSNR (dB)', 'upsampled SSIM',
                                  'upsampled blur (px)'], rows),
        bench.table('Training views at half resolution against the images box-filtered by 2',
                    ['run', 'lookups', 'PSNR (dB)', 'SSIM', 'worst view (dB)'], half_rows)],
        figures=[figure] if figure else (),
        notes='Crops: the centre of the first test view; the test image first, then each run '
              'in the order of the command.')


if __name__ == '__main__':
    main()
