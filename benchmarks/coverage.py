"""How much of the held-out error is extrapolation: the test pixels no training view saw.

    python benchmarks/coverage.py [LABEL=]RUN [[LABEL=]RUN ...] [--without-occupancy]
                                  [--toggle-fill] [--name N]

For each trained run (a folder written by ``optimize``; several runs of one capture side by
side) this renders each test view and splits its pixels by
``mi_nerfpp.data.cameras.direction_coverage``: a pixel is *seen* when at least ``SEEN_BY``
training views saw its direction, *unseen* otherwise (content in directions that no
training view looked at: no model can know it). It prints per view, in the encoding the
held-out PSNR is scored in:

* ``unseen``: the share of unseen pixels;
* ``model``, ``seen``, ``unseen``: PSNR of the render over the whole view and over each part;
* ``seen exact``: PSNR of the render with its seen pixels replaced by the test image (what the
  view would score if the model were perfect wherever training views looked);
* ``best fill``: PSNR of the render with its unseen pixels replaced by their mean colour in the
  test image (an oracle: no render that paints one colour where it knows nothing does better);
* ``both``: the two together, the ceiling of a model that is exact where it was shown the
  scene and paints the best single colour elsewhere;
* ``unseen best``: the PSNR of the unseen pixels alone at that best colour (what the
  ``unseen`` column of a render that paints one colour where it knows nothing reaches).

The last column answers whether a target on every test view (none below 24 dB, say) is
reachable on a capture at all. ``--without-occupancy`` renders each run a second time with its
occupancy grids off (every interval sampled): what empty-space skipping does to the
directions few training rays constrain; ``--toggle-fill`` a second time with the colour painted
where no training view looked (:mod:`mi_nerfpp.core.coverage`) toggled: without it when the
checkpoint holds one, with one made from the training views when it does not. Results: ``benchmarks/results/<--name>.json``, with a
picture of the two test views with the most unseen pixels (test image, then each render).
"""
import argparse

import numpy as np

import mi_nerfpp  # noqa: F401
from mi_nerfpp.jobs import bench
from mi_nerfpp.data.cameras import direction_coverage
from mi_nerfpp.training.metrics import masked_psnr, psnr
from mi_nerfpp.core.coverage import SEEN_BY, CoverageFill
from mi_nerfpp.core.render import Sampling
from mi_nerfpp.jobs.run import open_run
from mi_nerfpp.output.views import ViewRenderer, encoded_rgb

# Samples per volume of a render without empty-space skipping: whole rays' (one home).
WHOLE_RAY = Sampling()


def ceilings(pred, gt, seen):
    """PSNR of ``pred`` with its seen pixels exact, with its unseen pixels at their best constant,
    and with both (``seen``: H x W boolean)."""
    exact = np.where(seen[..., None], gt, pred)
    fill = pred.copy()
    if (~seen).any():
        fill[~seen] = gt[~seen].mean(axis=0)
    both = np.where(seen[..., None], gt, fill)
    return psnr(exact, gt), psnr(fill, gt), psnr(both, gt)


def score(renderer, model, dataset):
    """Per test view: [unseen share, model, seen, unseen, *ceilings] and the sRGB render."""
    rows, renders = [], []
    for i in range(len(dataset.test)):
        layers = renderer.render(dataset.test.cameras[i])
        pred = np.clip(encoded_rgb(layers, model.color_space), 0, 1)
        gt = np.asarray(dataset.test.images[i], dtype=np.float64)
        seen = direction_coverage(dataset.test.cameras[i], dataset.train.cameras) >= SEEN_BY
        best = gt[~seen].mean(axis=0) if (~seen).any() else 0.0
        rows.append([np.mean(~seen), psnr(pred, gt), masked_psnr(pred, gt, seen),
                     masked_psnr(pred, gt, ~seen), *ceilings(pred, gt, seen),
                     masked_psnr(np.broadcast_to(best, gt.shape), gt, ~seen)])
        renders.append(pred)
    return np.array(rows), renders


def picture(dataset, renders, views, scale=3):
    """The test images of ``views`` over one another, each followed by the renders of every
    run (``renders``: one list of images per run), magnified ``scale`` times; a PNG path."""
    import os
    import tempfile

    import imageio.v3 as iio
    strips = []
    for i in views:
        row = [np.asarray(dataset.test.images[i], dtype=np.float64)[..., :3]]
        row += [r[i][..., :3] for r in renders]
        strips.append(np.concatenate(row, axis=1))
    image = np.repeat(np.repeat(np.concatenate(strips, axis=0), scale, 0), scale, 1)
    path = os.path.join(tempfile.mkdtemp(), 'views.png')
    iio.imwrite(path, (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8))
    return path


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('runs', nargs='+', metavar='[LABEL=]RUN', help='run folders written by '
                    'optimize (on one capture, to compare them)')
    ap.add_argument('--without-occupancy', action='store_true', help='also render each run '
                    'without its occupancy grids (every interval sampled, %d + %d + %d samples): '
                    'what empty-space skipping changes' % (WHOLE_RAY.fg_samples, WHOLE_RAY.bg_samples,
                                                          WHOLE_RAY.fine_samples))
    ap.add_argument('--toggle-fill', action='store_true', help='also render each run with its '
                    'coverage fill toggled: without it where the checkpoint holds one, with one '
                    'made from its training views where it does not')
    ap.add_argument('--name', default='coverage', help='results file name (default coverage)')
    a = ap.parse_args()
    print(f'{"run":>12} {"view":>4} {"unseen":>6} {"model":>6} {"seen":>6} {"unseen":>6} '
          f'{"seen exact":>10} {"best fill":>9} {"both":>6} {"unseen best":>11}')
    tables, renders, labels, dataset = [], [], [], None
    for item in a.runs:
        label, _, run = item.rpartition('=')
        model, _, _, data = open_run(run)
        if not len(data.test):
            raise SystemExit(f'{data.root}: no test views to score')
        if dataset is not None and data.root != dataset.root:
            raise SystemExit(f'{run}: trained on {data.root}, not on {dataset.root} as '
                             f'{a.runs[0]}: compare runs of one capture')
        dataset = data
        stored = model.coverage
        name = label or run
        variants = [(name, False, stored)]                  # with the model's render settings
        if a.toggle_fill and model.bg is not None:
            if stored is None:
                made = CoverageFill.of_views(data.train.cameras, data.train.images,
                                             data.color_space)
                variants.append((f'{name}, with a fill', False, made))
            else:
                variants.append((f'{name}, no fill', False, None))
        if a.without_occupancy:
            variants.append((f'{name}, no skipping', True, stored))
        for name, whole_rays, fill in variants:
            model.coverage = fill
            if whole_rays:
                model.occupancy = {}
            renderer = ViewRenderer(model, sampling=WHOLE_RAY) if whole_rays \
                else ViewRenderer(model)
            r, images = score(renderer, model, data)
            for i, row in enumerate(r):
                print(f'{name[-12:]:>12} {i:4d} {100 * row[0]:5.0f}% ' + ' '.join(
                    f'{v:{w}.2f}' for v, w in zip(row[1:], (6, 6, 6, 10, 9, 6, 11))), flush=True)
            m = np.nanmean(r[:, :4], axis=0)
            # A view with no unseen pixel scores inf once its seen pixels are exact: report
            # the worst view of each ceiling, which is what a target on every view is about.
            print(f'{name}: {100 * m[0]:.0f} % unseen; model {m[1]:.2f} dB (seen {m[2]:.2f}, '
                  f'unseen {m[3]:.2f}); worst view: model {r[:, 1].min():.2f} dB, seen pixels '
                  f'exact {r[:, 4].min():.2f}, unseen at their best colour {r[:, 5].min():.2f}, '
                  f'both {r[:, 6].min():.2f}')
            tables.append((name, r))
            renders.append(images)
            labels.append(name)
    columns = ['unseen (%)', 'model (dB)', 'seen (dB)', 'unseen (dB)', 'seen exact (dB)',
               'best fill (dB)', 'both (dB)', 'unseen at their best colour (dB)']
    r0 = tables[0][1]
    most_unseen = sorted(np.argsort(-r0[:, 0])[:2].tolist())
    out = [bench.table('Worst view of each ceiling', ['run', 'model (dB)',
                                                      'seen pixels exact (dB)',
                                                      'unseen at their best colour (dB)',
                                                      'both (dB)'],
                       [[name, r[:, 1].min(), r[:, 4].min(), r[:, 5].min(), r[:, 6].min()]
                        for name, r in tables])]
    out += [bench.table(f'Per test view: {name}', ['view'] + columns,
                        [[i, 100 * row[0]] + list(row[1:]) for i, row in enumerate(r)])
            for name, r in tables]
    bench.write_results(a.name, 'Held-out error in the pixels no training view saw', out,
                        figures=[picture(dataset, renders, most_unseen)],
                        notes=f'A pixel is seen when at least {SEEN_BY} training views saw its '
                              f'direction. The picture: test views {most_unseen} (the most '
                              f'unseen pixels), left to right: the test image; '
                              + '; '.join(labels) + '.')


if __name__ == '__main__':
    main()
