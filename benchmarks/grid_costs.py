"""What one dense grid level costs a training step, by its size: the gradient sum and the Adam
update, and the sparse update that would touch only the entries a step reached.

    python benchmarks/grid_costs.py [--resolutions 32 64 96 128] [--rays 1024] [--samples 40]
                                    [--rounds 20]

For each resolution ``R``, a ball :class:`~mi_nerfpp.core.fields.GridField` of that one level
(``R³`` cells of 4 channels, as the foreground's levels) is looked up at ``--rays`` rays of
``--samples`` samples each, drawn as a training batch sees them (cameras on a sphere of radius
1.5 looking at points within 0.3 of the centre, the samples spread around the depth of the
centre), and these are timed, each as the median of ``--rounds`` warm repetitions, taking turns:

- the gradient sum: ``drjit.backward`` of the features' sum and the evaluation of the level's
  gradient (zeroing it included), with a training step's scatter settings
  (:data:`mi_nerfpp.training.train.GRADIENT_LOCAL_REDUCTION`; atomic adds above Dr.Jit's expand
  threshold, a copy per thread at or below it);
- the dense Adam update of every entry (:class:`mi_nerfpp.training.optim.Adam`, as training);
- the sparse alternative: the same arithmetic on the entries with a nonzero gradient only,
  read and written in place by masked gathers and scatters (what a step would save if it
  paid only for the cells it touched), with the copies Dr.Jit makes of the arrays a kernel
  writes when the same kernel reads them.

The samples are the same at every resolution, so what grows with ``R`` is what the level's size
costs. Prints a table; writes ``benchmarks/results/grid_costs.json``.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import mi_nerfpp  # noqa: F401  (libLLVM, variant)
import drjit as dr
import mitsuba as mi

import mi_nerfpp.training.train as T
from mi_nerfpp.jobs import bench
from mi_nerfpp.training import optim
from mi_nerfpp.core.fields import grid_field

CAMERA_RADIUS = 1.5     # the cameras' distance from the centre, in units of the ball
TARGET_RADIUS = 0.3     # the points they look at lie within this of the centre
DEPTH_SPREAD = 0.15     # standard deviation of the samples' distance around the centre's


def sample_points(rays, samples, seed=0):
    """``rays * samples`` points (ray by ray, sorted along each) in the ball, as a list of
    three Floats."""
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(rays, 3))
    o *= CAMERA_RADIUS / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-TARGET_RADIUS, TARGET_RADIUS, size=(rays, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t = np.sort(CAMERA_RADIUS + rng.normal(scale=DEPTH_SPREAD, size=(rays, samples)), axis=1)
    p = np.clip(o[:, None, :] + t[..., None] * d[:, None, :], -1, 1).reshape(-1, 3)
    return [mi.Float(p[:, k].astype(np.float32)) for k in range(3)]


def timed(fn):
    dr.sync_thread()
    t0 = time.perf_counter()
    fn()
    dr.sync_thread()
    return time.perf_counter() - t0


def timed_backward(fn):
    """:func:`timed` ``fn`` (a reverse pass) under a training step's Dr.Jit settings (its
    scatter reductions, :data:`mi_nerfpp.training.train.GRADIENT_LOCAL_REDUCTION`)."""
    with T._step_settings(llvm=True, big=False):
        return timed(fn)


class Level:
    """One grid level, its optimizer, and the three measurements."""

    def __init__(self, resolution, points):
        self.field = grid_field('ball', resolutions=(resolution,), seed=0)
        self.points = points
        self.opt = optim.adam({'grid0': self.field.params['grid0']}, lr=optim.LR_GRID)
        self.entries = dr.width(self.field.params['grid0'].array)
        self.gradient = None

    def gradient_sum(self):
        self.field.set_parameters({'grid0': self.opt['grid0']})
        density, features = self.field.features(self.points)
        dr.eval(density, features)        # the lookup is not part of the measurement

        def backward():
            dr.backward(dr.sum(density) + sum(dr.sum(f) for f in features))
            self.gradient = dr.grad(self.opt['grid0']).array
            dr.eval(self.gradient)
        return timed_backward(backward)

    def dense_adam(self):
        def step():
            self.opt.step(eval=False)
            dr.eval()
        return timed(step)

    def sparse_update(self):
        """Adam's arithmetic on the touched entries only, in place (moments of their own)."""
        if not hasattr(self, 'moments'):
            self.value = mi.Float(dr.detach(self.opt['grid0']).array)
            self.moments = [dr.zeros(mi.Float, self.entries) for _ in range(2)]
            dr.eval(self.value, self.moments)
        g, (m, v), value = mi.Float(self.gradient), self.moments, self.value
        dr.eval(g)
        beta_1, beta_2, lr = self.opt.beta_1, self.opt.beta_2, dr.opaque(mi.Float, optim.LR_GRID)

        def step():
            i = dr.arange(mi.UInt32, self.entries)
            touched = g != 0
            m_t = dr.lerp(g, dr.gather(mi.Float, m, i, touched), beta_1)
            v_t = dr.lerp(dr.square(g), dr.gather(mi.Float, v, i, touched), beta_2)
            step = m_t * dr.rsqrt(v_t + self.opt.epsilon ** 2)          # as optim.Adam
            new = dr.fma(step, -lr, dr.gather(mi.Float, value, i, touched))
            dr.scatter(m, m_t, i, touched)
            dr.scatter(v, v_t, i, touched)
            dr.scatter(value, new, i, touched)
            dr.eval(m, v, value)
        return timed(step)

    def touched(self):
        return float(dr.count(self.gradient != 0)[0]) / self.entries


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--resolutions', type=int, nargs='+', default=[32, 64, 96, 128])
    ap.add_argument('--rays', type=int, default=1024)
    ap.add_argument('--samples', type=int, default=40)
    ap.add_argument('--rounds', type=int, default=20)
    a = ap.parse_args()

    points = sample_points(a.rays, a.samples)
    levels = {r: Level(r, points) for r in a.resolutions}
    times = {r: {'sum': [], 'dense': [], 'sparse': []} for r in a.resolutions}
    for i in range(a.rounds + 2):                 # two warm-up rounds, not counted
        for r in (a.resolutions if i % 2 == 0 else a.resolutions[::-1]):
            level, t = levels[r], times[r]
            measured = (level.gradient_sum(), level.sparse_update(), level.dense_adam())
            if i >= 2:
                for key, s in zip(('sum', 'sparse', 'dense'), measured):
                    t[key].append(1e3 * s)
    columns = ['resolution', 'entries (M)', 'touched', 'gradient sum (ms)', 'dense Adam (ms)',
               'sparse update of the touched entries (ms)']
    rows = []
    for r in a.resolutions:
        t = times[r]
        rows.append([r, round(levels[r].entries / 1e6, 2), f'{levels[r].touched():.1%}',
                     round(statistics.median(t['sum']), 2), round(statistics.median(t['dense']), 2),
                     round(statistics.median(t['sparse']), 2)])
    print(f'{a.rays} rays x {a.samples} samples; medians of {a.rounds} rounds')
    print(' | '.join(columns))
    for row in rows:
        print(' | '.join(str(x) for x in row))
    bench.write_results('grid_costs', 'What a dense grid level costs a training step', [
        bench.table('One ball level of 4 channels, by resolution', columns, rows,
                    note=f'{a.rays} rays x {a.samples} samples looked up (the same points at '
                         f'every resolution); medians of {a.rounds} warm rounds, the '
                         f'resolutions taking turns. Dr.Jit sums gradients into arrays above '
                         f'its expand threshold ({dr.expand_threshold():,} entries) by atomic '
                         f'adds, into smaller ones through a copy per thread.')],
        notes='The sparse update reads and writes only the entries whose gradient is nonzero '
              '(masked gathers and scatters, in place); the dense one streams every entry.')


if __name__ == '__main__':
    main()
