"""Quality of one training setting at a fixed number of steps (the README's tuning table).

    python benchmarks/ablation.py [DATA] --iterations 1500 [any optimize training option]

Trains ``--iterations`` steps (default 1500) from scratch with the given options (the same
flags and defaults as ``optimize``), then prints one line: held-out PSNR (mean and per test
view), held-out PSNR over the pixels whose direction at least ``SEEN_BY`` training views saw
(``mi_nerfpp.data.direction_coverage``: the rest is extrapolation), with the synthetic ground
truth held-out PSNR over the pixels that meet no surface (the environment map: true depth 0,
mean over the test views that have such pixels), PSNR of every 8th
training view (the generalization gap; with the synthetic ground truth also split into the
pixels whose true foreground mask is 1 and 0, to see which volume's fit stalls), foreground/background
separation against the synthetic ground truth (``mi_nerfpp.training.metrics.separation``: mean
|alpha - alpha_gt|, foreground opacity where the true mask is 0, fraction of soft alpha) and
the fraction of occupied cells. A fixed step count makes settings comparable however busy the
machine is; time-based quality is ``benchmarks/quality.py``. Without DATA, the embedded
default capture is used. Results: ``benchmarks/results/<--name>.json`` (default
``ablation``; name each setting to keep several).
"""
import argparse
import glob
import os

import numpy as np

import mi_nerfpp  # noqa: F401
from mi_nerfpp.jobs import bench, run
from mi_nerfpp.training.config import TrainConfig
from mi_nerfpp.jobs.console import ConsoleObserver
from mi_nerfpp.data import direction_coverage
from mi_nerfpp.files.exr import read_exr
from mi_nerfpp.training.metrics import masked_psnr, psnr, separation
from mi_nerfpp.core.coverage import SEEN_BY
from mi_nerfpp.training.options import add_options, values
from mi_nerfpp.data.synth import default_capture
from mi_nerfpp.output.views import ViewRenderer, encoded_rgb


def _picture(folder, i, layers, gt, space):
    """One PNG row per test view: what a person looks at to see where the error is."""
    import imageio.v3 as iio
    from mi_nerfpp.core.color import to_srgb8
    pred = np.clip(encoded_rgb(layers, space), 0, 1)
    enc = 'srgb' if space == 'srgb' else 'linear'
    fg = np.stack([layers[f'fg.{c}'] for c in 'RGB'], axis=-1)
    bg = np.stack([layers[f'bg.{c}'] for c in 'RGB'], axis=-1)
    err = np.clip(4 * np.abs(pred - gt), 0, 1)
    row = np.concatenate([to_srgb8(gt, enc), to_srgb8(pred, enc), to_srgb8(fg), to_srgb8(bg),
                          to_srgb8(err, 'srgb')], axis=1)
    os.makedirs(folder, exist_ok=True)
    iio.imwrite(os.path.join(folder, f'test_{i:02d}.png'), row)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('data', nargs='?')
    ap.add_argument('--out', default='/tmp/mi_nerfpp_ablation')
    ap.add_argument('--name', default='ablation',
                    help='name of the results file (benchmarks/results/NAME.json)')
    ap.add_argument('--pictures', metavar='DIR',
                    help='also write, per test view, ground truth | render | foreground over black | '
                         'background | 4x absolute error as one PNG row')
    add_options(ap, TrainConfig)
    a = ap.parse_args()
    data = a.data or default_capture()
    options = dict(values(a, TrainConfig), checkpoint_every=0, preview_every=0, minutes=None,
                   eval_at=())
    options['iterations'] = options['iterations'] or 1500
    options['downscale'] = options['downscale'] or 1
    cfg = TrainConfig.from_options(**options)
    observer = ConsoleObserver('train')
    inputs = run.prepare(data, cfg, a.out, overwrite=True, observer=observer)
    trainer = run.start(inputs, observer=observer)
    run.train(trainer, observer)

    renderer = ViewRenderer(trainer.model)
    space = trainer.model.color_space

    def score(split, i):
        """A view's layers, its image as scored (clipped) and its PSNR."""
        layers = renderer.render(split.cameras[i])
        pred = np.clip(encoded_rgb(layers, space), 0, 1)
        return layers, pred, psnr(pred, split.images[i])

    gts = sorted(glob.glob(os.path.join(data, 'test', 'gt', '*.exr')))
    test, seen, sep, sky = [], [], [], []
    for i in range(len(trainer.test)):
        layers, pred, p = score(trainer.test, i)
        test.append(p)
        mask = direction_coverage(trainer.test.cameras[i], trainer.train.cameras) >= SEEN_BY
        seen.append(masked_psnr(pred, trainer.test.images[i], mask))
        if a.pictures:
            _picture(a.pictures, i, layers, trainer.test.images[i], space)
        if i < len(gts):
            truth = read_exr(gts[i])
            sep.append(separation(layers['fg.A'], truth['fg.A']))
            # The ground truth's depth is 0 where a ray meets no surface (the environment map).
            sky.append(masked_psnr(pred, trainer.test.images[i], truth['depth.Z'] <= 0))
    train, train_fg, train_bg = [], [], []
    train_gts = sorted(glob.glob(os.path.join(data, 'train', 'gt', '*.exr')))
    for i in range(0, len(trainer.train), 8):
        _, pred, p = score(trainer.train, i)
        train.append(p)
        if len(train_gts) == len(trainer.train):
            inside = read_exr(train_gts[i])['fg.A'] > 0.5
            train_fg.append(masked_psnr(pred, trainer.train.images[i], inside))
            train_bg.append(masked_psnr(pred, trainer.train.images[i], ~inside))
    split = (f' (true foreground {np.nanmean(train_fg):.2f}, background {np.nanmean(train_bg):.2f})'
             if train_fg else '')
    mean = {k: np.nanmean([s[k] for s in sep]) for k in sep[0]} if sep else {}
    occupied = {k: round(g.fraction(), 3) for k, g in trainer.model.occupancy.items()}
    print(f'{cfg.schedule.iterations} steps: held-out PSNR {np.mean(test):.2f} dB '
          f'(views {", ".join(f"{p:.1f}" for p in test)}); seen by >= {SEEN_BY} training views '
          f'{np.nanmean(seen):.2f} dB (worst {np.nanmin(seen):.1f}); '
          + (f'sky {np.nanmean(sky):.2f} dB; ' if sky else '')
          + f'training views '
          f'{np.mean(train):.2f} dB{split}; |alpha - alpha_gt| {mean.get("alpha_error", np.nan):.3f}, '
          f'leak {mean.get("leak", np.nan):.3f}, soft alpha {100 * mean.get("soft_fraction", np.nan):.0f}%; '
          f'occupied cells {occupied or "-"}')
    setting = bench.changed_options(cfg, ignore=('checkpoint_every', 'preview_every', 'iterations',
                                                 'minutes', 'eval_at', 'downscale'))
    bench.write_results(a.name, f'Quality after {cfg.schedule.iterations} steps: {setting}', [
        bench.table('Held-out quality at a fixed number of steps',
                    ['setting', 'steps', 'held-out PSNR (dB)', f'seen by >= {SEEN_BY} views (dB)',
                     'sky PSNR (dB)', 'training views PSNR (dB)', '|alpha - alpha_gt|', 'leak',
                     'soft alpha (%)', 'occupied fg', 'occupied bg'],
                    [[setting, cfg.schedule.iterations, np.mean(test), np.nanmean(seen),
                      np.nanmean(sky) if sky else '-', np.mean(train),
                      mean.get('alpha_error', '-'), mean.get('leak', '-'),
                      100 * mean['soft_fraction'] if 'soft_fraction' in mean else '-',
                      occupied.get('fg', '-'), occupied.get('bg', '-')]])],
        raw={'test_views_psnr': test, 'seen_psnr': seen, 'config': cfg.to_dict()})


if __name__ == '__main__':
    main()
