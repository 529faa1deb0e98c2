"""Masks: transients left out of the loss (``--masks ignore``), object silhouettes fitted
(``--masks object``).

    python benchmarks/masks.py make CLEAN --out WORK [--transient-share 0.25]
    python benchmarks/masks.py train WORK --minutes 2 [--cases LABEL ...]
    python benchmarks/masks.py score WORK [--name NAME] [--note T]

``make`` writes, from the clean synthetic capture ``CLEAN`` (``python -m mi_nerfpp synth``):
``WORK/transients`` (a share of the training photos with a person-shaped transient,
:mod:`mi_nerfpp.data.synth.realistic` with every other degradation off), ``WORK/masked`` (the
same photos shipping masks that leave the transients out), ``WORK/clean`` (the same capture
without transients) and ``WORK/object`` (the clean capture with each view's object silhouette
as its mask, from the ground truth's ``fg.A``). ``train`` trains them one after the other,
alone, into ``WORK/runs/<case>``, with their default ``--masks`` (ignore where there are
masks), the transients capture also with ``--transients 3`` (no masks: what the other photos
of a point say) and the object capture also with ``--masks none``. ``score`` reports, per run, the
held-out PSNR and soft matte share; for the transient cases the PSNR of the transients' pixels
in renders of their training views against the clean photos (the trace a transient leaves);
for the object cases the matte's intersection over union with the held-out masks. It writes a
figure of one transient view: the photo given, then each transient case's render.
Results: ``benchmarks/results/<--name>.json``.
"""
import argparse
import dataclasses
import json
import os
import shutil
import subprocess
import sys

import imageio.v3 as iio
import numpy as np

import mi_nerfpp  # noqa: F401
from mi_nerfpp.data.synth.capture import write_object_masks
from mi_nerfpp.data.synth.realistic import Realism, realistic_copy
from mi_nerfpp.files.exr import read_exr
from mi_nerfpp.jobs import bench
from mi_nerfpp.jobs.run import open_run
from mi_nerfpp.output.views import ViewRenderer, encoded_rgb
from mi_nerfpp.training.evaluate import matte_iou
from mi_nerfpp.training.metrics import masked_psnr

TRANSIENT_CASES = ('transients', 'masked', 'clean')
# Every training case: (label, data folder, options).
RUNS = (('transients', 'transients', []), ('masked', 'masked', []), ('clean', 'clean', []),
        ('transients, --transients 3', 'transients', ['--transients', '3']),
        ('object, --masks none', 'object', ['--masks', 'none']),
        ('object, --masks object', 'object', ['--masks', 'object']))


def make(args):
    only = Realism(transient_share=args.transient_share).without(
        'lens', 'exposure', 'noise', 'jpeg', 'blur', 'poses')
    for case, realism in (('transients', only), ('masked', dataclasses.replace(only, masks=True)),
                          ('clean', only.without('transients'))):
        realistic_copy(args.clean, os.path.join(args.out, case), realism, seed=args.seed)
    target = os.path.join(args.out, 'object')
    shutil.rmtree(target, ignore_errors=True)
    shutil.copytree(args.clean, target)
    print(f'object masks: {write_object_masks(target)} written to {target}')


def _run_dir(work, label):
    return os.path.join(work, 'runs', label.replace(', --masks ', '-').replace(', --', '-')
                        .replace(' ', ''))


def train(args):
    for label, data, options in RUNS:
        if label not in args.cases:
            continue
        out = _run_dir(args.work, label)
        command = [sys.executable, 'optimize.py', os.path.join(args.work, data), '--out', out,
                   '--overwrite', '--minutes', str(args.minutes), '--seed', str(args.seed),
                   *options]
        print(' '.join(command), flush=True)
        subprocess.run(command, check=True)


def score(args):
    rows, renders = [], {}
    with open(os.path.join(args.work, 'transients', 'realistic.json')) as f:
        record = json.load(f)
    transient_views = [i for i, v in enumerate(record['views']['train']) if 'transient_pixels' in v]
    stems = [v['name'] for v in record['views']['train']]
    for label, data, _ in RUNS:
        run = _run_dir(args.work, label)
        with open(os.path.join(run, 'metrics.json')) as f:
            metrics = json.load(f)
        test = metrics['test']
        trace = iou = ''
        if data in TRANSIENT_CASES:
            trace, renders[label] = transient_trace(args.work, run, transient_views, stems)
        else:
            iou = round(_matte_iou(run, os.path.join(args.work, data)), 4)
        rows.append([label, metrics['iterations'], round(test['psnr'], 2),
                     round(100 * test.get('soft_alpha', float('nan')), 2), trace, iou])
        print(f'{label:>24}  {rows[-1][1]:>6} steps  PSNR {rows[-1][2]:6.2f}  soft matte '
              f'{rows[-1][3]:5.2f} %  transient pixels {trace} dB  matte IoU {iou}')
    figure = _figure(args, renders, transient_views[0], stems)
    table = bench.table('Masks: transients and object silhouettes',
                        ['run', 'steps', 'held-out PSNR (dB)', 'soft matte (% of held-out pixels)',
                         "transients' pixels in their training views against the clean photos "
                         '(PSNR, dB)', 'held-out matte IoU with the object masks'],
                        rows, note=args.note)
    path = bench.write_results(args.name, 'Masks: transients left out, object silhouettes',
                               [table], figures=[figure])
    print(f'wrote {path}')


def transient_trace(work, run, views, stems, clean_dir=None, stand_in=None):
    """The PSNR of the transients' pixels in the run's renders of their training views against
    the clean photos, and those renders. ``clean_dir``: the clean capture's training photos
    (default ``WORK/clean/images/train``, ``.png``; a NeRF++ capture's ``train/rgb``);
    ``stand_in``: the stand-in whose ``transients/`` masks say where (default
    ``WORK/transients``)."""
    model, _, _, splits = open_run(run)
    renderer = ViewRenderer(model)
    clean_dir = clean_dir or os.path.join(work, 'clean', 'images', 'train')
    stand_in = stand_in or os.path.join(work, 'transients')
    errors, renders = [], []
    for i in views:
        render = np.clip(encoded_rgb(renderer.render(splits.train.cameras[i]),
                                     model.color_space), 0, 1)
        clean = iio.imread(os.path.join(clean_dir, stems[i] + '.png'))[..., :3] / 255.0
        region = iio.imread(os.path.join(stand_in, 'transients', stems[i] + '.png')) > 127
        errors.append(np.mean((render[region] - clean[region]) ** 2))
        renders.append(render)
    return round(float(-10 * np.log10(np.mean(errors))), 2), renders


def _matte_iou(run, data):
    scores = []
    for i, name in enumerate(sorted(os.listdir(os.path.join(data, 'test', 'mask')))):
        alpha = read_exr(os.path.join(run, 'test', f'test_{i:03d}.exr'))['fg.A']
        scores.append(matte_iou(alpha, iio.imread(os.path.join(data, 'test', 'mask', name)) > 127))
    return float(np.mean(scores))


def _figure(args, renders, view, stems):
    """One transient view (the first of ``renders``' views), 2x: the photo given, then each
    transient case's render."""
    photo = iio.imread(os.path.join(args.work, 'transients', 'images', 'train',
                                    stems[view] + '.png'))[..., :3] / 255.0
    path = bench.write_image_row(os.path.join(args.work, 'transient_view.png'),
                                 [photo] + [renders[label][0] for label in renders])
    print(f'figure (the photo given, then {", ".join(renders)}): {path}')
    return path


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    sub = parser.add_subparsers(dest='command', required=True)
    p = sub.add_parser('make', help='write the cases from a clean capture')
    p.add_argument('clean')
    p.add_argument('--out', required=True)
    p.add_argument('--transient-share', type=float, default=0.25)
    p.add_argument('--seed', type=int, default=0)
    p.set_defaults(func=make)
    p = bench.add_train_command(sub, train, minutes=2.0)
    p.add_argument('--cases', nargs='*', choices=[label for label, _, _ in RUNS],
                   default=[label for label, _, _ in RUNS], help='the runs to train (all)')
    bench.add_score_command(sub, score, 'masks')
    args = parser.parse_args(argv)
    args.func(args)


if __name__ == '__main__':
    main()
