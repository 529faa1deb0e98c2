"""What a sparse grid level costs a training step against the dense level it would replace.

    python benchmarks/sparse_level.py [--resolutions 64 128 256] [--rays 1024] [--samples 40]
                                      [--rounds 10] [--all-bricks] [--name NAME]

Issue 61 asks for the fine levels to be stored only where the surfaces are: a step's Adam
update, gradient buffers and memsets then scale with the allocated bricks instead of the
bounding grid, as long as the sparse lookup is not much slower than the dense texture's. For each
resolution ``R`` this benchmark builds one ball level of ``R³`` texels of 4 channels twice, as
a dense level (:class:`~mi_nerfpp.core.encodings.DenseLevels`, a ``Texture3f``) and as a sparse
level (:class:`~mi_nerfpp.core.encodings.SparseLevels`, bricks over the training's 64³
occupancy cells). The sparse level's allocated bricks are those that the batch's samples reach,
grown by one brick as training grows them (:data:`~mi_nerfpp.core.bricks.DILATION`); with
``--all-bricks`` every brick, so that both levels store the same entries and only the layout
and the lookup differ (what a level whose occupancy does not thin out, as the background's
before its sparsity prior starts, would cost in bricks). Both levels
are looked up at the same ``--rays`` x ``--samples`` points (:func:`grid_costs.sample_points`:
a training batch's shape). Three stages are timed, each the median of ``--rounds`` warm rounds,
with the two kinds taking turns:

- the lookup: the level's channels at the points, evaluated;
- the gradient sum: ``drjit.backward`` of the channels' sum and the evaluation of the level's
  gradient (its zeroing included), with a training step's scatter settings;
- Adam: :class:`mi_nerfpp.training.optim.Adam`'s update of every stored entry (the grid or
  the brick pool), as training runs it.

Prints a table; writes ``benchmarks/results/sparse_level.json`` (``--name``: another name).
"""
from __future__ import annotations

import argparse
import statistics

import numpy as np

import mi_nerfpp  # noqa: F401  (libLLVM, variant)
import drjit as dr
import mitsuba as mi

from mi_nerfpp.core import bricks
from mi_nerfpp.core.encodings import DenseLevels, SparseLevels
from mi_nerfpp.jobs import bench
from mi_nerfpp.training import optim

from grid_costs import sample_points, timed, timed_backward

BLOCKS = (64, 64, 64)     # bricks per axis: one per cell of training's occupancy grid


def reached_bricks(points, resolution):
    """The flat indices of the bricks (of :data:`BLOCKS`) that trilinear lookups at ``points``
    (three Floats in [-1, 1]) read, grown by training's dilation."""
    p = np.stack([np.asarray(c, dtype=np.float64) for c in points], axis=1)
    u = (p + 1.0) / 2.0 * resolution - 0.5           # texel coordinates (x, y, z)
    brick = resolution // BLOCKS[0]
    mask = np.zeros(BLOCKS, dtype=bool)
    for offset in (0.0, 1.0):                        # the lower and upper texel of each axis
        t = np.clip(np.floor(u) + offset, 0, resolution - 1).astype(np.int64) // brick
        mask[t[:, 2], t[:, 1], t[:, 0]] = True
    mask = bricks.dilate(mask, bricks.DILATION['ball'])
    return np.flatnonzero(mask.ravel())


class Level:
    """One level of ``kind`` (``'dense'`` or ``'sparse'``) at ``resolution``, its optimizer
    and the three measurements."""

    def __init__(self, kind, resolution, points, all_bricks=False):
        self.kind, self.points = kind, points
        self.coords = [(c + 1.0) * 0.5 for c in points]
        if kind == 'dense':
            self.levels = DenseLevels('ball', (resolution,), rng=dr.rng(seed=0))
            self.key = 'grid0'
        else:
            self.levels = SparseLevels('ball', (resolution,), blocks=BLOCKS)
            chosen = (np.arange(int(np.prod(BLOCKS))) if all_bricks
                      else reached_bricks(points, resolution))
            self.levels.allocate({'sparse0': chosen})
            self.key = 'sparse0'
        self.opt = optim.adam({self.key: self.levels.params[self.key]}, lr=optim.LR_GRID)
        optim.set_learning_rates(self.opt, 0.5)
        self.entries = dr.width(self.levels.params[self.key].array)
        self.channels = None

    def lookup(self):
        self.levels.params[self.key] = self.opt[self.key]
        self.levels.bind()

        def run():
            self.channels = self.levels.lookup(self.coords)[0]
            dr.eval(self.channels)
        return timed(run)

    def gradient_sum(self):
        def backward():
            dr.backward(sum(dr.sum(c) for c in self.channels))
            dr.eval(dr.grad(self.opt[self.key]).array)
        return timed_backward(backward)

    def adam(self):
        def step():
            self.opt.step(eval=False)
            dr.eval()
        return timed(step)


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--resolutions', type=int, nargs='+', default=[64, 128, 256])
    ap.add_argument('--rays', type=int, default=1024)
    ap.add_argument('--samples', type=int, default=40)
    ap.add_argument('--rounds', type=int, default=10)
    ap.add_argument('--all-bricks', action='store_true',
                    help='allocate every brick of the sparse level (equal entries stored)')
    ap.add_argument('--name', default='sparse_level')
    a = ap.parse_args()
    if any(r % BLOCKS[0] for r in a.resolutions):
        ap.error(f'--resolutions must be multiples of {BLOCKS[0]} (the bricks per axis)')

    points = sample_points(a.rays, a.samples)
    levels = {(k, r): Level(k, r, points, a.all_bricks) for r in a.resolutions
              for k in ('dense', 'sparse')}
    stages = ('lookup', 'gradient sum', 'Adam')
    times = {key: {s: [] for s in stages} for key in levels}
    for i in range(a.rounds + 2):                 # two warm-up rounds, not counted
        order = list(levels) if i % 2 == 0 else list(levels)[::-1]
        for key in order:
            level = levels[key]
            measured = (level.lookup(), level.gradient_sum(), level.adam())
            if i >= 2:
                for s, t in zip(stages, measured):
                    times[key][s].append(1e3 * t)
    columns = ['resolution', 'kind', 'entries stored (M)', 'share of the dense entries',
               'lookup (ms)', 'gradient sum (ms)', 'Adam (ms)', 'total (ms)']
    rows = []
    for (kind, r), level in levels.items():
        med = [statistics.median(times[(kind, r)][s]) for s in stages]
        dense = levels[('dense', r)].entries
        rows.append([r, kind, round(level.entries / 1e6, 3), f'{level.entries / dense:.1%}']
                    + [round(m, 2) for m in med] + [round(sum(med), 2)])
    print(f'{a.rays} rays x {a.samples} samples; medians of {a.rounds} rounds')
    print(' | '.join(columns))
    for row in rows:
        print(' | '.join(str(x) for x in row))
    bench.write_results(a.name, 'A sparse grid level against the dense level it would replace', [
        bench.table('One ball level of 4 channels: dense texture against bricks where the '
                    'samples are', columns, rows,
                    note=f'{a.rays} rays x {a.samples} samples looked up (the same points for '
                         f'both kinds and every resolution); the sparse level holds '
                         + (f'every brick of a {BLOCKS[0]}³ brick grid' if a.all_bricks else
                            f'the bricks (of a {BLOCKS[0]}³ brick grid) those samples reach, '
                            f'grown by one brick')
                         + f'; medians of {a.rounds} warm rounds, the kinds taking turns.')],
        notes='Adam streams every stored entry: the dense grid, or the sparse level\'s brick '
              'pool.')


if __name__ == '__main__':
    main()
