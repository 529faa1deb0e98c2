"""Sparse grid levels (:mod:`mi_nerfpp.core.bricks`): lookups equal the dense texture they
replace, gradients match finite differences, bricks come from an occupancy mask, and a field
with sparse levels survives a checkpoint and a training run that allocates them."""
import json

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.core.bricks import BrickGrid, block_mask, block_max, choose, dilate
from mi_nerfpp.core.fields import grid_field
from mi_nerfpp.core.model import NeRFPPModel
from mi_nerfpp.files.checkpoint import load_checkpoint, save_checkpoint
from tests.helpers import tiny_model

SHAPE, BLOCKS = (8, 12, 16), (2, 3, 4)


def _pool_of(grid, dense):
    """The pool holding ``dense``'s texels for the bricks ``grid`` has allocated."""
    bz, by, bx = grid.brick
    _, BY, BX = grid.blocks
    pool = np.zeros(grid.pool_shape(), np.float32)
    for s, b in enumerate(grid.allocated):
        z, r = divmod(int(b), BY * BX)
        y, x = divmod(r, BX)
        pool[s] = dense[z * bz:(z + 1) * bz, y * by:(y + 1) * by, x * bx:(x + 1) * bx]
    return pool


def _dense_of(grid, dense):
    """``dense`` with the texels of bricks ``grid`` has not allocated set to zero."""
    out = np.zeros_like(dense)
    bz, by, bx = grid.brick
    _, BY, BX = grid.blocks
    for b in grid.allocated:
        z, r = divmod(int(b), BY * BX)
        y, x = divmod(r, BX)
        sl = (slice(z * bz, (z + 1) * bz), slice(y * by, (y + 1) * by), slice(x * bx, (x + 1) * bx))
        out[sl] = dense[sl]
    return out


def _points(rng, n, periodic):
    p = [rng.uniform(-0.05, 1.05, n) for _ in range(3)]
    if periodic:            # as the background's lookups: periodic in x, y and z kept inside
        p[0] = rng.uniform(0, 1, n)
        p[1] = np.clip(p[1], 0.5 / SHAPE[1], 1 - 0.5 / SHAPE[1])
        p[2] = np.clip(p[2], 0.5 / SHAPE[0], 1 - 0.5 / SHAPE[0])
    return [mi.Float(v.astype(np.float32)) for v in p]


@pytest.mark.parametrize('channels,periodic,share', [(4, False, 1.0), (3, True, 1.0),
                                                     (2, True, 0.4), (4, False, 0.3)])
def test_a_lookup_equals_the_dense_texture_of_the_allocated_bricks(channels, periodic, share):
    rng = np.random.default_rng(channels)
    dense = rng.normal(size=SHAPE + (channels,)).astype(np.float32)
    grid = BrickGrid(SHAPE, BLOCKS, channels, periodic)
    n = grid.n_blocks
    grid.allocate(rng.permutation(n)[:max(int(share * n), 1)])   # any slot order
    wrap = dr.WrapMode.Repeat if periodic else dr.WrapMode.Clamp
    tex = mi.Texture3f(mi.TensorXf(_dense_of(grid, dense)), use_accel=False, wrap_mode=wrap)
    p = _points(rng, 2000, periodic)
    expected = tex.eval(mi.Point3f(*p))
    got = grid.lookup(mi.Float(_pool_of(grid, dense).ravel()), p)
    for e, g in zip(expected, got):
        assert np.allclose(e.numpy(), g.numpy(), atol=1e-5)


def test_nothing_allocated_reads_zero():
    grid = BrickGrid(SHAPE, BLOCKS, 4)
    assert grid.pool_shape() == (1, 4, 4, 4, 4)
    got = grid.lookup(dr.ones(mi.Float, 256), _points(np.random.default_rng(0), 50, False))
    assert all(np.all(v.numpy() == 0) for v in got)


def test_gradients_match_central_differences():
    rng = np.random.default_rng(3)
    grid = BrickGrid(SHAPE, BLOCKS, 4, periodic=True)
    grid.allocate(np.arange(0, grid.n_blocks, 2))
    pool0 = rng.normal(size=grid.pool_shape()).astype(np.float32).ravel()
    p = _points(rng, 300, True)
    weights = [mi.Float(rng.normal(size=300).astype(np.float32)) for _ in range(4)]

    def loss(pool):
        return dr.sum(sum((w * dr.square(v) for w, v in zip(weights, grid.lookup(pool, p))),
                          mi.Float(0.0)))

    pool = mi.Float(pool0)
    dr.enable_grad(pool)
    dr.backward(loss(pool))
    grad = dr.grad(pool).numpy()
    touched = np.flatnonzero(grad)
    assert touched.size > 50
    eps = 1e-2
    for k in rng.choice(touched, 12, replace=False):
        hi, lo = pool0.copy(), pool0.copy()
        hi[k] += eps
        lo[k] -= eps
        fd = (loss(mi.Float(hi)).numpy()[0] - loss(mi.Float(lo)).numpy()[0]) / (2 * eps)
        assert fd == pytest.approx(grad[k], rel=2e-2, abs=2e-3)


def test_bricks_come_from_an_occupancy_mask():
    occupied = np.zeros((4, 6, 8), bool)
    occupied[1, 2, 3] = occupied[3, 5, 7] = True
    # Bricks over 2 x 3 x 4 cells: a brick is occupied when any of its cells is.
    mask = block_mask(occupied, (2, 2, 2))
    assert mask.shape == (2, 2, 2) and np.argwhere(mask).tolist() == [[0, 0, 0], [1, 1, 1]]
    # A cell over several bricks marks all of them.
    assert block_mask(occupied, (8, 6, 8)).sum() == 4
    density = np.arange(4 * 6 * 8, dtype=np.float32).reshape(4, 6, 8)
    assert block_max(density, (2, 2, 2))[1, 1, 1] == density.max()
    with pytest.raises(ValueError, match='does not map onto'):
        block_mask(occupied, (3, 2, 2))
    # Grown by one brick: along x periodic (the background's longitude), clamped otherwise.
    one = np.zeros((3, 3, 4), bool)
    one[1, 1, 0] = True
    grown = dilate(one, (1, 1, 1), periodic_x=True)
    assert grown.sum() == 27 and grown[1, 1, 3]
    assert dilate(one, (1, 1, 1)).sum() == 18 and not dilate(one, (1, 1, 1))[1, 1, 3]
    assert dilate(one, (1, 0, 0)).sum() == 3
    # At most ``limit`` bricks, the highest scores first, in index order.
    score = np.array([5.0, 1.0, 9.0, 7.0])
    assert choose(np.array([True, True, False, True]), score, 2).tolist() == [0, 3]
    assert choose(np.array([True, True, False, True]), score, None).tolist() == [0, 1, 3]


def test_reallocating_keeps_the_texels_of_bricks_kept():
    grid = BrickGrid(SHAPE, BLOCKS, 2)
    grid.allocate([3, 7, 9])
    pool = np.random.default_rng(1).normal(size=grid.pool_shape()).astype(np.float32)
    moved = grid.moved(pool, [1, 7, 9, 20])
    assert moved.shape == (4,) + grid.brick + (2,)
    assert np.all(moved[0] == 0) and np.all(moved[3] == 0)
    assert np.array_equal(moved[1], pool[1]) and np.array_equal(moved[2], pool[2])
    # New bricks take their texels from a fill (a fresh level's noise), kept ones do not.
    fill = np.full(grid.pool_shape(4), 0.5, np.float32)
    filled = grid.moved(pool, [1, 7, 9, 20], fill)
    assert np.all(filled[0] == 0.5) and np.all(filled[3] == 0.5)
    assert np.array_equal(filled[1], pool[1]) and np.array_equal(filled[2], pool[2])
    assert [a.tolist() for a in grid.kept([1, 7, 9, 20])] == [[1, 2], [1, 2]]
    with pytest.raises(ValueError, match='distinct'):
        grid.allocate([1, 1])


@pytest.mark.parametrize('first_moment', [True, False])
def test_reallocating_carries_adam_moments_of_bricks_kept(first_moment):
    """A reallocation keeps the kept bricks' Adam moments and step count; new bricks start
    with no first moment and the kept entries' mean second moment, so that their first step
    is about a learning rate, not the ~3x of zero moments without bias correction. A background
    grid, which learns without a first moment (optim.without_momentum), keeps its one-entry
    placeholder."""
    from mi_nerfpp.training import optim
    from mi_nerfpp.training.schedule import moved_moments
    grid = BrickGrid(SHAPE, BLOCKS, 2)
    grid.allocate([3, 7, 9])
    key = 'fg.sparse0' if first_moment else 'bg.sparse0'
    opt = optim.adam({key: mi.TensorXf(np.zeros(grid.pool_shape(), np.float32))})
    entries = 2 * grid.texels_per_brick * 2
    t, m0, v0, _ = moved_moments(opt, key, grid, [7, 20])      # no step yet
    assert t.numpy().tolist() == [0] and not m0.numpy().any() and not v0.numpy().any()
    assert dr.width(m0) == (entries if first_moment else 1) and dr.width(v0) == entries
    # No brick kept (a level's first allocation, after steps of its empty placeholder): a
    # fresh state, whose bias correction starts over, not zero moments at a late step count.
    assert moved_moments(opt, key, grid, [1, 20]) is None
    rng = np.random.default_rng(2)
    m = rng.normal(size=grid.pool_shape()).astype(np.float32)
    v = rng.uniform(1, 2, size=grid.pool_shape()).astype(np.float32)
    value, promoted, lr, (_, placeholder, _, _) = opt.state[key]
    opt.state[key] = (value, promoted, lr,
                               (mi.UInt32(17), mi.Float(m.ravel()) if first_moment
                                else placeholder, mi.Float(v.ravel()), None))
    t, m2, v2, _ = moved_moments(opt, key, grid, [7, 20])
    v2 = v2.numpy().reshape(grid.pool_shape(2))
    assert t.numpy().tolist() == [17]
    assert np.array_equal(v2[0], v[1])
    np.testing.assert_allclose(v2[1], v[1].mean(), rtol=1e-6)
    if first_moment:
        m2 = m2.numpy().reshape(grid.pool_shape(2))
        assert np.array_equal(m2[0], m[1]) and np.all(m2[1] == 0)
    else:
        assert m2 is placeholder


def test_new_bricks_start_as_a_dense_level_does():
    """A sparse level allocated at the first step (in place of a dense level) starts as
    normal noise of the dense levels' ``init``; bricks kept keep their texels, and bricks
    added later start at zero (they add nothing to what was learned until trained)."""
    from mi_nerfpp.core.encodings import SparseLevels
    levels = SparseLevels('ball', (16,), blocks=(4, 4, 4), init=0.1, seed=3)
    levels.allocate({'sparse0': np.arange(40)}, start=True)
    first = levels.params['sparse0'].numpy()
    assert first.shape == (40, 4, 4, 4, 4)
    assert abs(first.std() - 0.1) < 0.005 and abs(first.mean()) < 0.005
    levels.allocate({'sparse0': np.arange(20, 60)})
    again = levels.params['sparse0'].numpy()
    assert np.array_equal(again[:20], first[20:])                 # kept
    assert not again[20:].any()                                   # added later: zero
    zero = SparseLevels('ball', (16,), blocks=(4, 4, 4), init=0.1)
    zero.allocate({'sparse0': np.arange(5)})                      # not at the start: zeros
    assert not zero.params['sparse0'].numpy().any()


def _sparse_model():
    fg = grid_field('ball', resolutions=(4,), channels=4, sparse=(16,), sparse_blocks=(4, 4, 4),
                    antialias=True, seed=1)
    bg = grid_field('inverted_sphere', resolutions=(4,), channels=4, sparse=(16,),
                    sparse_blocks=(4, 8, 16), seed=2)
    return NeRFPPModel(fg, bg)


def test_a_field_with_sparse_levels_survives_a_checkpoint(tmp_path):
    model = _sparse_model()
    rng = np.random.default_rng(0)
    model.set_bricks({'fg.sparse0': np.array([0, 5, 21, 63]), 'bg.sparse0': np.arange(0, 512, 3)})
    values = {k: mi.TensorXf(rng.normal(size=v.shape).astype(np.float32))
              for k, v in model.parameters().items() if '.sparse' in k}
    model.set_parameters(values)
    x = [mi.Float(rng.uniform(-0.9, 0.9, 500).astype(np.float32)) for _ in range(3)]
    before = model.fg.density(x).numpy()
    save_checkpoint(tmp_path / 'model.npz', model)
    loaded, _, _ = load_checkpoint(tmp_path / 'model.npz')
    assert {k: v.tolist() for k, v in loaded.allocated_bricks().items()} == \
        {k: v.tolist() for k, v in model.allocated_bricks().items()}
    assert np.array_equal(loaded.fg.density(x).numpy(), before)
    # The sparse level is read: without its bricks the density differs.
    loaded.set_bricks({'fg.sparse0': np.zeros(0, np.int64)})
    assert not np.allclose(loaded.fg.density(x).numpy(), before)


def test_a_checkpoint_without_sparse_levels_loads_as_before(tmp_path):
    model = tiny_model()
    save_checkpoint(tmp_path / 'model.npz', model)
    loaded, _, _ = load_checkpoint(tmp_path / 'model.npz')
    assert loaded.allocated_bricks() == {} and 'sparse' not in loaded.fg.config


def test_training_allocates_the_occupied_bricks(capture, tmp_path, capsys):
    from mi_nerfpp.commands.cli import main
    out = tmp_path / 'run'
    assert main(['optimize', capture, '--out', str(out), '--iterations', '40', '--batch-rays',
                 '128', '--samples', '8', '8', '8', '--grid-levels', '8', '16', '--occupancy-res',
                 '16', '--grid-sparse', '32', '--bg-grid-sparse', '16', '--sparse-at', '0.5',
                 '--sparse-entries', '40000', '--preview-every', '0', '--checkpoint-every',
                 '0']) == 0
    model, meta, _ = load_checkpoint(out / 'model.npz')
    fg = model.allocated_bricks()['fg.sparse0']
    # Bricks of 2³ texels x 4 channels: at most 40,000 entries -> 1,250 bricks of 4,096.
    assert 0 < fg.size <= 40000 // 32 and fg.size < 16 ** 3
    assert model.parameters()['fg.sparse0'].shape == (fg.size, 2, 2, 2, 4)
    # Learned after allocation (bricks allocated after the first step start at zero).
    assert np.abs(model.parameters()['fg.sparse0'].numpy()).max() > 0
    # The run says, and records, what each level holds of what the occupancy asked for.
    with open(out / 'metrics.json') as f:
        last = {a['level']: a for a in json.load(f)['sparse_allocations']}
    assert last['fg.sparse0']['bricks'] == fg.size
    assert last['bg.sparse0']['bricks'] == model.allocated_bricks()['bg.sparse0'].size
    said = capsys.readouterr().out
    for level, a in last.items():
        assert f'sparse level {level}: {a["bricks"]:,} bricks' in said


def test_sparse_levels_need_occupancy_cells_that_cut_them(capsys, capture, tmp_path):
    from mi_nerfpp.commands.cli import main
    base = ['optimize', capture, '--out', str(tmp_path / 'r'), '--iterations', '1']
    assert main(base + ['--grid-sparse', '48', '--occupancy-res', '32']) == 1
    assert ('--grid-sparse must be multiples of 32 (the occupancy cells, --occupancy-res 32), '
            'got 48') in capsys.readouterr().err
    assert main(base + ['--bg-grid-sparse', '24', '--occupancy-res', '32']) == 1
    assert ('--bg-grid-sparse must be multiples of 16 (the occupancy cells, --occupancy-res '
            '32), got 24') in capsys.readouterr().err
    assert main(base + ['--grid-sparse', '64', '--no-occupancy']) == 1
    assert '--grid-sparse 64 needs empty-space skipping' in capsys.readouterr().err


def test_sparse_levels_allocated_at_the_first_step(capture, tmp_path):
    """--sparse-at 0 allocates at the first step, where the occupancy grid still holds every
    cell: every brick, started as a dense level (noise of --grid-init); the background's sparse
    level has as many texels along s as a dense level of its resolution (--bg-s-ratio)."""
    from mi_nerfpp.commands.cli import main
    out = tmp_path / 'run'
    assert main(['optimize', capture, '--out', str(out), '--iterations', '20', '--batch-rays',
                 '128', '--samples', '8', '8', '8', '--grid-levels', '8', '--occupancy-res',
                 '16', '--grid-sparse', '32', '--bg-grid-sparse', '32', '--sparse-at', '0',
                 '--preview-every', '0', '--checkpoint-every', '0']) == 0
    with open(out / 'metrics.json') as f:
        records = json.load(f)['sparse_allocations']
    assert [(a['iteration'], a['level'], a['bricks'] == a['of']) for a in records] == \
        [(0, 'fg.sparse0', True), (0, 'bg.sparse0', True)]
    model, _, _ = load_checkpoint(out / 'model.npz')
    # Behind: 32 x 0.5 = 16 texels along s over the occupancy grid's 4 cells of s.
    assert model.parameters()['bg.sparse0'].shape == (4 * 8 * 16, 4, 4, 4, 4)
    assert model.bg.sparse.bricks[0].shape == (16, 32, 64)
    fg = model.parameters()['fg.sparse0'].numpy()
    # Started as noise: no texel is exactly 0. Bricks started at zero would keep zeros
    # wherever no sample reached, as in the cube's corners outside the ball (48 % of it).
    assert fg.shape == (16 ** 3, 2, 2, 2, 4) and (fg == 0).mean() < 0.001
    assert 0.05 < np.median(np.abs(fg)) < 0.12


def test_a_level_larger_than_the_budget_waits_for_the_occupancy(capsys, capture, tmp_path):
    """At the first step the occupancy knows nothing yet, so a level that --sparse-entries holds
    whole is allocated whole there (started as noise) and a larger one waits for the next
    fraction, where the densest occupied bricks are chosen within the budget. With no later
    fraction it would never be allocated: refused before any work, naming what would do."""
    from mi_nerfpp.commands.cli import main
    base = ['optimize', capture, '--out', str(tmp_path / 'r'), '--iterations', '1',
            '--grid-levels', '8', '--occupancy-res', '16', '--sparse-at', '0']
    # 32³ texels x 4 channels = 131,072 entries in the ball.
    assert main(base + ['--grid-sparse', '32', '--sparse-entries', '131071']) == 1
    err = capsys.readouterr().err
    assert ('--sparse-at 0 allocates every brick of --grid-sparse 32 at the first step, 131,072 '
            'entries, but --sparse-entries is 131,071, so the level would never be allocated: '
            'give --sparse-entries 131072 or more, or a later fraction too') in err
    assert not (tmp_path / 'r' / 'model.npz').exists()
    # Behind, 64 x 32 x 16 texels along s (32 x --bg-s-ratio 0.5) x 4 channels = 131,072.
    assert main(base + ['--grid-sparse', '--bg-grid-sparse', '32',
                        '--sparse-entries', '100000']) == 1
    assert '--sparse-at 0 allocates every brick of --bg-grid-sparse 32 at the first step, ' \
        '131,072 entries' in capsys.readouterr().err
    # With a later fraction: the 16 level (16,384 entries) whole at the first step, the 32
    # level at the tenth step, at most 100,000 entries (3,125 bricks of 2³ x 4) of its 4,096.
    out = tmp_path / 'run'
    assert main(['optimize', capture, '--out', str(out), '--iterations', '20',
                 '--grid-levels', '8', '--occupancy-res', '16', '--sparse-at', '0', '0.5',
                 '--grid-sparse', '16', '32', '--sparse-entries', '100000', '--batch-rays',
                 '64', '--samples', '4', '4', '4', '--preview-every', '0',
                 '--checkpoint-every', '0']) == 0
    with open(out / 'metrics.json') as f:
        records = json.load(f)['sparse_allocations']
    assert [(a['iteration'], a['level'], a['bricks'], a['of']) for a in records][:2] == \
        [(0, 'fg.sparse0', 4096, 4096), (10, 'fg.sparse0', records[1]['bricks'], 4096)]
    late = [a for a in records if a['level'] == 'fg.sparse1']
    assert [a['iteration'] for a in late] == [10] and 0 < late[0]['bricks'] <= 3125
    model, _, _ = load_checkpoint(out / 'model.npz')
    assert model.allocated_bricks()['fg.sparse1'].size == late[0]['bricks']
    # The level allocated later starts at zero and has learned since.
    assert np.abs(model.parameters()['fg.sparse1'].numpy()).max() > 0
