"""How much of the held-out error is extrapolation: the test pixels no training view saw.

    python benchmarks/coverage.py RUN

For a trained run (a folder written by ``optimize``) this renders each test view and splits its
pixels by ``mi_nerfpp.data.cameras.direction_coverage``: a pixel is *seen* when at least
``SEEN_BY`` training views saw its direction, *unseen* otherwise (content in directions that no
training view looked at: no model can know it). It prints per view, in the encoding the
held-out PSNR is scored in:

* ``unseen``: the share of unseen pixels;
* ``model``, ``seen``, ``unseen``: PSNR of the render over the whole view and over each part;
* ``seen exact``: PSNR of the render with its seen pixels replaced by the test image (what the
  view would score if the model were perfect wherever training views looked);
* ``best fill``: PSNR of the render with its unseen pixels replaced by their mean colour in the
  test image (an oracle: no render that paints one colour where it knows nothing does better);
* ``both``: the two together, the ceiling of a model that is exact where it was shown the
  scene and paints the best single colour elsewhere.

The last column answers whether a target on every test view (none below 24 dB, say) is
reachable on a capture at all. Results: ``benchmarks/results/coverage.json``.
"""
import argparse

import numpy as np

import mi_nerfpp  # noqa: F401
from mi_nerfpp import bench
from mi_nerfpp.data.cameras import direction_coverage
from mi_nerfpp.metrics import SEEN_BY, masked_psnr, psnr
from mi_nerfpp.run import open_run
from mi_nerfpp.views import ViewRenderer, encoded_rgb


def ceilings(pred, gt, seen):
    """PSNR of ``pred`` with its seen pixels exact, with its unseen pixels at their best constant,
    and with both (``seen``: H x W boolean)."""
    exact = np.where(seen[..., None], gt, pred)
    fill = pred.copy()
    if (~seen).any():
        fill[~seen] = gt[~seen].mean(axis=0)
    both = np.where(seen[..., None], gt, fill)
    return psnr(exact, gt), psnr(fill, gt), psnr(both, gt)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('run', help='run folder written by optimize')
    a = ap.parse_args()
    model, _, _, dataset = open_run(a.run)
    renderer = ViewRenderer(model)       # with the model's render settings
    test = dataset.test
    if not len(test):
        raise SystemExit(f'{dataset.root}: no test views to score')
    print(f'{"view":>4} {"unseen":>6} {"model":>6} {"seen":>6} {"unseen":>6} '
          f'{"seen exact":>10} {"best fill":>9} {"both":>6}')
    rows = []
    for i in range(len(test)):
        layers = renderer.render(test.cameras[i])
        pred = np.clip(encoded_rgb(layers, model.color_space), 0, 1)
        gt = np.asarray(test.images[i], dtype=np.float64)
        seen = direction_coverage(test.cameras[i], dataset.train.cameras) >= SEEN_BY
        row = [np.mean(~seen), psnr(pred, gt), masked_psnr(pred, gt, seen),
               masked_psnr(pred, gt, ~seen), *ceilings(pred, gt, seen)]
        rows.append(row)
        print(f'{i:4d} {100 * row[0]:5.0f}% ' + ' '.join(f'{v:{w}.2f}' for v, w in
                                                      zip(row[1:], (6, 6, 6, 10, 9, 6))), flush=True)
    r = np.array(rows)
    m = np.nanmean(r[:, :4], axis=0)
    # A view with no unseen pixel scores inf once its seen pixels are exact: report the worst
    # view of each ceiling, which is what a target on every view is about.
    print(f'mean: {100 * m[0]:.0f} % unseen; model {m[1]:.2f} dB (seen {m[2]:.2f}, unseen '
          f'{m[3]:.2f}); worst view: model {r[:, 1].min():.2f} dB, seen pixels exact '
          f'{r[:, 4].min():.2f}, unseen at their best colour {r[:, 5].min():.2f}, both '
          f'{r[:, 6].min():.2f}')
    columns = ['unseen (%)', 'model (dB)', 'seen (dB)', 'unseen (dB)', 'seen exact (dB)',
               'best fill (dB)', 'both (dB)']
    bench.write_results('coverage', 'Held-out error in the pixels no training view saw', [
        bench.table('Worst view of each ceiling', ['model (dB)', 'seen pixels exact (dB)',
                                                   'unseen at their best colour (dB)', 'both (dB)'],
                    [[r[:, 1].min(), r[:, 4].min(), r[:, 5].min(), r[:, 6].min()]]),
        bench.table('Per test view', ['view'] + columns,
                    [[i, 100 * row[0]] + list(row[1:]) for i, row in enumerate(rows)])],
        notes=f'Run {a.run}; a pixel is seen when at least {SEEN_BY} training views saw its '
              f'direction.')

if __name__ == '__main__':
    main()
