"""The realistic stand-in of a phone capture: what each degradation and each option costs.

    python benchmarks/realistic.py make CLEAN --out WORK [--cases all no-lens ...]
    python benchmarks/realistic.py train WORK --minutes 10 [--cases ...] [--options CASE=ARGS]
    python benchmarks/realistic.py truth CLEAN --out TRUTH [--spp 256]
    python benchmarks/realistic.py score LABEL=RUN [...] --truth CLEAN [--truth-images TRUTH]
                                         [--name NAME] [--note T] [--crop VIEW]

``make`` writes the stand-in of the clean synthetic capture ``CLEAN`` (``synth --realistic``
keeps it in ``DATA/clean``) once with every degradation (``WORK/all``) and once with each
degradation switched off in turn (``WORK/no-<name>``: lens, exposure, noise, jpeg, blur, poses,
transients; :mod:`mi_nerfpp.data.synth.realistic`), all from one seed. ``train`` trains the
cases one after the other, alone, into ``WORK/runs/<case>`` (``--options`` adds option cases on
the full stand-in, e.g. ``'uniform=--error-rays 0'``). ``score`` reads finished runs: their
held-out PSNR/SSIM against the clean ground truth (the stand-in's held-out views are clean),
their steps, and the share of the foreground's pixels that are dark speckles
(:func:`~mi_nerfpp.training.metrics.dark_speckle_share`) in the held-out renders beside the
ground truth's own share. A capture rendered with few samples per pixel has Monte Carlo noise
in its held-out views too, which caps PSNR and counts as speckles: ``truth`` renders the test
views again with more samples, and ``score --truth-images`` scores against those (the column
"against the truth images"; ``metrics.json``'s PSNR is against the capture's own).
Results: ``benchmarks/results/<--name>.json``.
"""
import argparse
import json
import os
import shlex
import subprocess
import sys

import imageio.v3 as iio
import numpy as np

import mi_nerfpp  # noqa: F401
from mi_nerfpp.core.color import srgb_eotf
from mi_nerfpp.data.synth.realistic import DEGRADATIONS, Realism, realistic_copy
from mi_nerfpp.files.exr import read_exr
from mi_nerfpp.jobs import bench
from mi_nerfpp.training.metrics import SPECKLE_DEPTH, dark_speckle_share

# Rec. 709 luminance weights (tone column).
LUMA = np.array([0.2126, 0.7152, 0.0722])
# The side of the crops of --crop, in pixels (shown 2x).
CROP = 160
# The degradations a phone capture has (weather is the in-the-wild collection's).
CASES = ['all'] + [f'no-{name}' for name, fields in DEGRADATIONS.items()
                   if any(getattr(Realism(), f) for f in fields)]


def make(args):
    for case in args.cases:
        realism = Realism() if case == 'all' else Realism().without(case[3:])
        out = os.path.join(args.out, case)
        realistic_copy(args.clean, out, realism, seed=args.seed)
        print(f'{case}: {out}')


def train(args):
    cases = [(case, os.path.join(args.work, case), []) for case in args.cases]
    for item in args.options:
        label, _, options = item.partition('=')
        cases.append((label, os.path.join(args.work, 'all'), shlex.split(options)))
    for label, data, options in cases:
        out = os.path.join(args.work, 'runs', label)
        command = [sys.executable, '-m', 'mi_nerfpp', 'optimize', data, '--out', out,
                   '--minutes', str(args.minutes), '--seed', str(args.seed), '--overwrite',
                   *options]
        print(' '.join(command), flush=True)
        subprocess.run(command, check=True)


def truth(args):
    """Render the clean capture's test views again with ``--spp`` samples, into ``--out``."""
    import mitsuba as mi
    from mi_nerfpp.core.color import to_srgb8
    from mi_nerfpp.data.cameras import Camera
    from mi_nerfpp.data.nerfpp import _read_matrix
    from mi_nerfpp.data.synth.capture import _sensor
    with open(os.path.join(args.clean, 'capture.json')) as f:
        capture = json.load(f)
    scene = mi.load_file(capture['scene_path'])
    folder = os.path.join(args.clean, 'test')
    os.makedirs(args.out, exist_ok=True)
    for stem in _stems(args.clean):
        K = _read_matrix(os.path.join(folder, 'intrinsics', stem + '.txt'))[:3, :3]
        c2w = _read_matrix(os.path.join(folder, 'pose', stem + '.txt'))
        w, h = capture['resolution']
        camera = Camera(K, c2w, w, h, stem)
        rgb = np.array(mi.render(scene, sensor=_sensor(camera, args.spp), spp=args.spp,
                                 seed=args.seed + 7919), dtype=np.float32)[..., :3]
        iio.imwrite(os.path.join(args.out, stem + '.png'), to_srgb8(np.nan_to_num(rgb)))
        print(f'{stem}: {args.spp} spp', flush=True)


def _stems(clean):
    return sorted(os.path.splitext(n)[0]
                  for n in os.listdir(os.path.join(clean, 'test', 'rgb')))


def _truth(clean, images_dir=None):
    """The clean capture's test images (encoded, float; from ``images_dir`` when given, else
    the capture's own) and foreground masks, in file order."""
    folder = os.path.join(clean, 'test')
    stems = _stems(clean)
    images = [iio.imread(os.path.join(images_dir or os.path.join(folder, 'rgb'),
                                      s + '.png'))[..., :3] / 255.0 for s in stems]
    masks = [read_exr(os.path.join(folder, 'gt', s + '.exr'))['fg.A'] > 0.5 for s in stems]
    return images, masks


def score(args):
    images, masks = _truth(args.truth, args.truth_images)
    truth_share = np.nanmean([dark_speckle_share(i, m) for i, m in zip(images, masks)])
    rows = []
    for item in args.runs:
        label, sep, run = item.partition('=')
        if not sep:
            raise SystemExit(f'error: realistic: {item!r} is not LABEL=RUN')
        with open(os.path.join(run, 'metrics.json')) as f:
            metrics = json.load(f)
        test = metrics['test']
        shares, errors, tones = [], [], []
        for i, (truth, mask) in enumerate(zip(images, masks)):
            render = iio.imread(_render(run, i))[..., :3] / 255.0
            if render.shape != truth.shape:
                raise SystemExit(f'error: realistic: {run} renders {render.shape}, the truth is '
                                 f'{truth.shape}: not a run of this stand-in')
            shares.append(dark_speckle_share(render, mask))
            errors.append(np.mean((render - truth) ** 2))
            tones.append(np.log2(np.mean(srgb_eotf(render) @ LUMA)
                                 / np.mean(srgb_eotf(truth) @ LUMA)))
        rows.append([label, metrics['iterations'], round(test['psnr'], 2),
                     round(float(np.mean([-10 * np.log10(e) for e in errors])), 2),
                     round(min(v['psnr'] for v in test['views']), 2), round(test['ssim'], 3),
                     round(100 * float(np.nanmean(shares)), 3), round(float(np.mean(tones)), 3)])
        print(f'{label:>24}  {rows[-1][1]:>6} steps  PSNR {rows[-1][2]:6.2f} (against the '
              f'truth images {rows[-1][3]:6.2f}, worst view {rows[-1][4]:5.2f})  SSIM '
              f'{rows[-1][5]:.3f}  dark speckles {rows[-1][6]:.3f} %  tone {rows[-1][7]:+.3f} '
              f'stops')
    print(f'{"ground truth":>24}  dark speckles {100 * truth_share:.3f} %')
    rows.append(['ground truth', '', '', '', '', '', round(100 * float(truth_share), 3), 0])
    figures = [_crops(args, images, masks)] if args.crop is not None else []
    table = bench.table('Held-out scores on the realistic stand-in',
                        ['run', 'steps', 'PSNR (dB)', 'PSNR against the truth images (dB)',
                         'worst view (dB)', 'SSIM',
                         f'dark speckles (% of the foreground, > {SPECKLE_DEPTH} below the 3x3 '
                         f'median)', 'tone (stops of linear luminance against the truth)'],
                        rows, note=args.note)
    path = bench.write_results(args.name, 'The realistic stand-in of a phone capture', [table],
                               figures=figures, variant=args.variant)
    print(f'wrote {path}')


def _crops(args, images, masks):
    """A PNG of one test view's foreground, 2x enlarged: the truth, then each run."""
    view = args.crop
    ys, xs = np.nonzero(masks[view])
    cy, cx = (int(np.median(ys)), int(np.median(xs))) if len(ys) else (0, 0)
    h, w = images[view].shape[:2]
    size = min(CROP, h, w)
    y0 = int(np.clip(cy - size // 2, 0, h - size))
    x0 = int(np.clip(cx - size // 2, 0, w - size))
    tiles = [images[view]] + [iio.imread(_render(item.partition('=')[2], view))[..., :3] / 255.0
                              for item in args.runs]
    path = bench.write_image_row(os.path.join(args.work_dir, f'crops_view{view}.png'),
                                 [t[y0:y0 + size, x0:x0 + size] for t in tiles])
    print(f'crops (truth, then {", ".join(i.partition("=")[0] for i in args.runs)}): {path}')
    return path


def _render(run, i):
    for folder in ('test', 'views', '.'):
        path = os.path.join(run, folder, f'test_{i:03d}.png')
        if os.path.isfile(path):
            return path
    raise SystemExit(f'error: realistic: {run} has no test_{i:03d}.png (not a finished run?)')


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    sub = parser.add_subparsers(dest='command', required=True)
    p = sub.add_parser('make', help='write the stand-in cases of a clean capture')
    p.add_argument('clean')
    p.add_argument('--out', required=True)
    p.add_argument('--cases', nargs='+', choices=CASES, default=CASES)
    p.add_argument('--seed', type=int, default=0)
    p.set_defaults(func=make)
    bench.add_train_command(sub, train, minutes=10.0, cases=CASES)
    p = sub.add_parser('truth', help='render the test views again with more samples')
    p.add_argument('clean')
    p.add_argument('--out', required=True)
    p.add_argument('--spp', type=int, default=256)
    p.add_argument('--seed', type=int, default=0)
    p.set_defaults(func=truth)
    p = sub.add_parser('score', help='score finished runs against the clean ground truth')
    p.add_argument('runs', nargs='+', metavar='LABEL=RUN')
    p.add_argument('--truth', required=True, help='the clean capture (DATA/clean)')
    p.add_argument('--name', default='realistic')
    p.add_argument('--note', default=None)
    p.add_argument('--variant', default=None,
                   help='what this result measures (the benchmarks page keeps one of each)')
    p.add_argument('--truth-images', default=None, metavar='DIR',
                   help='the test views rendered anew with more samples (the truth command); '
                        'default: the capture\'s own')
    p.add_argument('--crop', type=int, default=None, metavar='VIEW',
                   help='write crops of this test view\'s foreground: the truth, then each run')
    p.add_argument('--work-dir', default='.', help='where the crops are written first')
    p.set_defaults(func=score)
    args = parser.parse_args(argv)
    args.func(args)


if __name__ == '__main__':
    main()
