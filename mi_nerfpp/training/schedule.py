"""The parts of a training run that act at times of their own, each owning its schedule (as
nerfacc's estimators own ``update_every_n_steps``); the trainer's step asks each whether it is
due and calls it, in order:

* :class:`OccupancyRefresh` — the occupancy grids, every ``--occupancy-every`` steps;
* :class:`SparseAllocation` — the sparse levels' bricks, at each ``--sparse-at`` fraction of
  the run passed: the foreground's where its density is, the background's where the training
  rays' colour comes from (:func:`background_shares`);
* :class:`ImagePyramid` — the level of the training images, coarse to fine at the
  ``--pyramid`` fractions.

The priors say when they apply themselves (:class:`~mi_nerfpp.training.priors.Sparsity`), and
the pose refinement its start and blur (:mod:`mi_nerfpp.core.poses`).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_nerfpp.core import bricks
from mi_nerfpp.core.arrays import owned
from mi_nerfpp.core.fields import GridField
from mi_nerfpp.core.occupancy import cell_index
from mi_nerfpp.core.profiling import stage
from mi_nerfpp.core.render import Background, RenderOptions, render_rays
from mi_nerfpp.core.sampling import flat_index

# The background's bricks after the first allocation: those where one background sample of a
# training ray carries at least BACKGROUND_SHARE of the ray's colour (its weight times the light
# the foreground lets through), over BACKGROUND_RAYS random training rays - Plenoxels' pruning
# by weight. The density alone keeps 73-87 % of the inverted sphere (the far side of every
# wall, haze that no ray sees through to); this keeps 12-23 % on the embedded capture and
# gt_plaza (docs/experiments.md).
BACKGROUND_SHARE = 0.02
BACKGROUND_RAYS = 1 << 15


def passed(fractions, progress) -> int:
    """How many of the run's ``fractions`` ``progress`` (fraction of the run done) has passed."""
    return sum(progress >= f for f in fractions)


class OccupancyRefresh:
    """Refreshes the model's occupancy grids from the fields every ``every`` steps, from the
    first on."""

    def __init__(self, every: int):
        self.every = int(every)

    def due(self, iteration: int) -> bool:
        return iteration % self.every == 0

    def __call__(self, model, seed: int):
        with stage('occupancy refresh'):
            model.update_occupancy(seed)


def background_shares(model, bank, blocks, seed: int, n_rays: int = BACKGROUND_RAYS):
    """Per brick of ``blocks`` bricks (Z, Y, X) over the inverted sphere, the largest share of a
    training ray's colour that one of its background samples there carries (its weight times
    ``1 - the foreground's opacity``), over ``n_rays`` rays of ``bank``
    (:class:`~mi_nerfpp.training.raybank.RayBank`) drawn with ``seed`` and rendered without
    gradients; a float32 array of ``blocks``."""
    with dr.suspend_grad():
        rng = dr.rng(seed=seed)
        rays, _ = bank.batch(rng.integers(mi.UInt32, n_rays, 0, bank.size),
                             footprint=model.antialias)
        rays.seed = rng.integers(mi.UInt32, n_rays, 0, 2 ** 32 - 1)
        res = render_rays(rays, *model.radiance_fields(), model.sampling, RenderOptions())
        ray, _ = flat_index(n_rays, res.bg.n)
        brick = cell_index('inverted_sphere', blocks,
                           Background(rays).inputs(ray, res.bg.position))
        through = 1.0 - dr.gather(mi.Float, res.fg.shading.opacity, ray)
        share = dr.zeros(mi.Float, int(np.prod(blocks)))
        dr.scatter_reduce(dr.ReduceOp.Max, share, res.bg.weights * through, brick)
    return share.numpy().reshape(blocks)


def sparse_levels(model):
    """``(volume, field, level)`` of every sparse grid level of ``model``."""
    return [(volume, field, i) for volume, field in (('fg', model.fg), ('bg', model.bg))
            if isinstance(field, GridField) for i in range(len(field.sparse))]


def moved_moments(opt, key, grid, chosen):
    """The Adam state of the sparse level ``key`` (a :class:`~mi_nerfpp.core.bricks.BrickGrid`
    ``grid``) re-laid for an allocation of ``chosen``, so that a reallocation does not restart
    every brick's Adam (a fresh state's first steps are a full learning rate for every entry):
    the kept bricks keep their moments and the step count. New bricks start with no first
    moment and the kept entries' mean second moment: with a zero second moment and the step
    count of the others (no bias correction left), their first steps would be
    ``(1 − β₁)/√(1 − β₂)`` ≈ 3x the learning rate. None (a fresh state, whose bias correction
    starts over) where no brick is kept, as at a level's first allocation."""
    state = opt.state.get(key)
    kept = grid.kept(chosen)[1]
    if state is None or state[3][1] is None or not kept.size:
        return None
    t, m, v, v_max = state[3]
    v_old = dr.detach(v).numpy()
    start = float(v_old.reshape(grid.pool_shape())[kept].mean())
    if dr.width(m) > 1:      # (none where a grid learns without one, optim.without_momentum)
        m = owned(grid.moved(dr.detach(m).numpy(), chosen).ravel(), mi.Float)
    v = grid.moved(v_old, chosen, np.full(grid.pool_shape(len(chosen)), start, np.float32))
    return t, m, owned(v.ravel(), mi.Float), v_max


class SparseAllocation:
    """At each of ``fractions`` of the run passed, allocates the sparse levels' bricks, grown
    by :data:`~mi_nerfpp.core.bricks.DILATION`, at most ``max_entries`` entries a level, the
    highest scores first; bricks kept keep their texels. A foreground level takes the bricks
    where the field's density now, at :data:`~mi_nerfpp.core.occupancy.ALLOCATION_POINTS`
    points of each occupancy cell (:meth:`~mi_nerfpp.core.occupancy.OccupancyGrid.sampled`),
    is above the occupancy threshold; a background level, the bricks where the rays of ``bank``
    (the training rays) take at least :data:`BACKGROUND_SHARE` of their colour
    (:func:`background_shares`; by density as the foreground without a ``bank``). At the
    first step (a fraction of 0), where neither knows anything yet, a level is allocated
    whole, started as a dense level would be, if ``max_entries`` holds it; a level that it
    does not hold waits for the next fraction. A resumed run that has bricks has the
    fractions before its ``progress`` behind it."""

    def __init__(self, fractions, max_entries: int, model=None, progress: float = 0.0,
                 bank=None):
        self.fractions, self.max_entries, self.bank = tuple(fractions), int(max_entries), bank
        allocated = model is not None and any(len(g) for g in model.allocated_bricks().values())
        self.done = passed(self.fractions, progress) if allocated else 0
        self.records = []       # one dict per level and allocation (metrics.json)

    def due(self, progress: float) -> bool:
        return passed(self.fractions, progress) > self.done

    def __call__(self, model, params, iteration: int, progress: float):
        """Allocate in every sparse level of ``model``; ``params`` (the optimizer, which owns
        the parameters) gets each level's new texel pool, with fresh Adam moments."""
        self.done = passed(self.fractions, progress)
        for volume, field, i in sparse_levels(model):
            brick = field.sparse.bricks[i]
            limit = self.max_entries // (brick.texels_per_brick * brick.channels)
            if iteration == 0 and brick.n_blocks > limit:
                continue        # not whole within the budget: waits for the occupancy
            occupied, score = self._scores(model, volume, field, brick, iteration)
            mask = bricks.dilate(occupied, bricks.DILATION[field.domain],
                                 periodic_x=field.domain == 'inverted_sphere')
            chosen = bricks.choose(mask, score, max(limit, 1))
            key = f'{volume}.sparse{i}'
            moments = moved_moments(params, key, brick, chosen)
            field.set_parameters({f'sparse{i}': dr.detach(params[key])})
            field.set_bricks({f'sparse{i}': chosen}, start=iteration == 0)
            params[key] = field.params[f'sparse{i}']     # new shape: new Adam state
            if moments is not None:
                value, promoted, lr, _ = params.state[key]
                params.state[key] = (value, promoted, lr, moments)
            self.records.append({'iteration': iteration, 'level': key,
                                 'bricks': int(chosen.size), 'of': brick.n_blocks,
                                 'occupied': int(mask.sum()),
                                 'entries': int(np.prod(brick.pool_shape()))})

    def _scores(self, model, volume, field, brick, iteration):
        """``(wanted, score)`` per brick of the level ``brick`` of ``field``: the bricks its
        rule asks for (bool) and the score that ranks them within the budget."""
        if field.domain == 'inverted_sphere' and self.bank is not None and iteration > 0:
            with stage('background shares'):
                share = background_shares(model, self.bank, brick.blocks, iteration)
            return share >= BACKGROUND_SHARE, share
        grid = model.occupancy[volume]
        # The field's density now, not the grid's running maximum, which remembers for
        # hundreds of steps what training has carved away; at the first step, every cell.
        density = grid.numpy() if grid.fresh or iteration == 0 \
            else grid.sampled(field, iteration)
        return (bricks.block_mask(density > grid.threshold, brick.blocks),
                bricks.block_max(density, brick.blocks))


class ImagePyramid:
    """The training images coarse to fine: at ``progress`` (fraction of the run done) a step
    draws its rays from the ray bank at factor ``2^(fractions not passed yet)``, at most as
    coarse as leaves the images a pixel (:meth:`~mi_nerfpp.training.raybank.RayBank.level`);
    the last fraction reaches full size."""

    def __init__(self, bank, fractions):
        self.bank, self.fractions = bank, tuple(fractions)

    def factor(self, progress: float) -> int:
        f = 1 << sum(progress < f for f in self.fractions)
        return 1 if f == 1 else min(f, self.bank.max_factor())

    def level(self, progress: float):
        factor = self.factor(progress)
        return self.bank if factor == 1 else self.bank.level(factor)
