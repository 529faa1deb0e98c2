"""A photo collection in the wild: what per-photo appearance and the transients' handling buy.

    python benchmarks/wild.py make CLEAN --out WORK [--without lens noise ...]
    python benchmarks/wild.py train WORK --minutes 3 [--cases ...] [--options LABEL=ARGS ...]
    python benchmarks/wild.py score WORK [--name NAME] [--note T]

``make`` writes the in-the-wild stand-in of the clean synthetic capture ``CLEAN`` (a NeRF++
capture of ``python -m mi_nerfpp synth``, with ``gt/``) into ``WORK/data``
(:meth:`mi_nerfpp.data.synth.realistic.Realism.in_the_wild`: the phone's degradations, wider
exposure and white balance, the sky and the haze changing from photo to photo, passers-by in a
third of the photos; the held-out views clean); ``--without`` switches named degradations off
(:data:`mi_nerfpp.data.synth.realistic.DEGRADATIONS`; e.g. the phone's own, to measure what
appearance and transients alone cost). ``train`` trains each case on it, alone, one
after the other, into ``WORK/runs/<case>``. ``score`` reports, per run: its steps; the
held-out PSNR against the clean views as ``metrics.json`` has it (with per-photo appearance,
NeRF-W's: each view's colour transform fitted on its left half, the right half scored) and
neutral (whole views, nothing fitted); the soft matte share; and the PSNR of the transients'
pixels in renders of their training views, from the true cameras, against the clean renders
(the trace a passer-by leaves); and a figure of the photo with the largest passer-by, as given
and as each run renders its view. Results: ``benchmarks/results/<--name>.json``.
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
from mi_nerfpp.data.nerfpp import _split_frames
from mi_nerfpp.data.cameras import Camera
from mi_nerfpp.data.synth.realistic import DEGRADATIONS, Realism, realistic_copy
from mi_nerfpp.jobs import bench
from mi_nerfpp.jobs.run import open_run
from mi_nerfpp.output.views import ViewRenderer, encoded_rgb

CASES = {'defaults': [], 'appearance': ['--appearance'],
         'embedding': ['--appearance-embedding', '8'],
         'embedding+appearance': ['--appearance-embedding', '8', '--appearance']}


def make(args):
    realistic_copy(args.clean, os.path.join(args.out, 'data'),
                   Realism.in_the_wild().without(*args.without), seed=args.seed)
    with open(os.path.join(args.out, 'clean.txt'), 'w') as f:
        f.write(os.path.abspath(args.clean))


def train(args):
    cases = [(case, CASES[case]) for case in args.cases]
    cases += [(label, shlex.split(options)) for label, _, options in
              (item.partition('=') for item in args.options)]
    for label, options in cases:
        command = [sys.executable, 'optimize.py', os.path.join(args.work, 'data'), '--out',
                   os.path.join(args.work, 'runs', label), '--overwrite', '--minutes',
                   str(args.minutes), '--seed', str(args.seed), *options]
        print(' '.join(command), flush=True)
        subprocess.run(command, check=True)


def score(args):
    with open(os.path.join(args.work, 'clean.txt')) as f:
        clean = f.read().strip()
    with open(os.path.join(args.work, 'data', 'realistic.json')) as f:
        record = json.load(f)
    views = [i for i, v in enumerate(record['views']['train']) if 'transient_pixels' in v]
    stems = [v['name'] for v in record['views']['train']]
    cameras = {frame.name: frame for frame in _split_frames(os.path.join(clean, 'train'))}
    # The figure's view: the training photo with the largest passer-by.
    shown = max(views, key=lambda i: record['views']['train'][i]['transient_pixels'])
    rows, renders = [], {}
    for label in sorted(os.listdir(os.path.join(args.work, 'runs'))):
        run = os.path.join(args.work, 'runs', label)
        with open(os.path.join(run, 'metrics.json')) as f:
            metrics = json.load(f)
        test = metrics['test']
        model, _, _, _ = open_run(run)
        renderer = ViewRenderer(model)
        errors = []
        for i in views:
            frame = cameras[stems[i]]
            photo = iio.imread(frame.image_path)[..., :3] / 255.0
            h, w = photo.shape[:2]
            world = Camera(K=frame.intrinsics(w, h), c2w=frame.c2w, width=w, height=h)
            render = np.clip(encoded_rgb(renderer.render(
                model.normalization.to_model_camera(world)), model.color_space), 0, 1)
            region = iio.imread(os.path.join(args.work, 'data', 'transients',
                                             stems[i] + '.png')) > 127
            errors.append(np.mean((render[region] - photo[region]) ** 2))
            if i == shown:
                renders[label] = render
        trace = round(float(-10 * np.log10(np.mean(errors))), 2)
        rows.append([label, metrics['iterations'], round(test['psnr'], 2),
                     round(test.get('psnr_neutral', test['psnr']), 2),
                     round(100 * test.get('soft_alpha', float('nan')), 2), trace])
        print(f'{label:>22}  {rows[-1][1]:>6} steps  PSNR {rows[-1][2]:6.2f} (neutral '
              f'{rows[-1][3]:6.2f})  soft matte {rows[-1][4]:5.2f} %  transient pixels '
              f'{trace:6.2f} dB', flush=True)
    table = bench.table('The in-the-wild stand-in',
                        ['run', 'steps', 'held-out PSNR, appearance fitted on the left half '
                         'where learned (dB)', 'held-out PSNR, neutral (dB)',
                         'soft matte (% of held-out pixels)',
                         "transients' pixels in their training views, true cameras, against "
                         'the clean renders (PSNR, dB)'], rows, note=args.note)
    figure = _figure(args.work, stems[shown], renders)
    path = bench.write_results(args.name, 'A photo collection in the wild', [table],
                               figures=[figure])
    print(f'wrote {path}')


def _figure(work, stem, renders):
    """The training photo ``stem`` as given (with its passer-by), then each run's render of
    its view (``renders``: label -> image), 2x, in one row: ``WORK/transient_view.png``."""
    folder = os.path.join(work, 'data', 'images', 'train')
    name = next(n for n in sorted(os.listdir(folder)) if os.path.splitext(n)[0] == stem)
    photo = iio.imread(os.path.join(folder, name))[..., :3] / 255.0
    path = bench.write_image_row(os.path.join(work, 'transient_view.png'),
                                 [photo, *renders.values()])
    print(f'figure (the photo given, then {", ".join(renders)}): {path}')
    return path


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    sub = parser.add_subparsers(dest='command', required=True)
    p = sub.add_parser('make', help='write the stand-in from a clean capture')
    p.add_argument('clean')
    p.add_argument('--out', required=True)
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--without', nargs='+', default=[], choices=sorted(DEGRADATIONS),
                   metavar='NAME', help='degradations switched off: '
                   + ', '.join(DEGRADATIONS))
    p.set_defaults(func=make)
    bench.add_train_command(sub, train, minutes=3.0, cases=CASES)
    bench.add_score_command(sub, score, 'wild')
    args = parser.parse_args(argv)
    args.func(args)


if __name__ == '__main__':
    main()
