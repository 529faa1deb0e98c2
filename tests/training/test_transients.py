"""Transients without masks (training/transients.py): a tile that errs where the other photos
of the same point do not weighs nothing; one that errs in every photo, or a photo that errs as
a whole, keeps its weight."""
import json
import os
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest

from mi_nerfpp.training.transients import START, TransientWeights
from tests.helpers import TINY_RUN, orbit_camera

W, H, TILE = 32, 24, 8


def ring(n=8):
    """``n`` cameras on a ring around the origin, all looking at it."""
    return [orbit_camera(2 * np.pi * i / n, 0.2, 2.5, W, H) for i in range(n)]


def seen(t: TransientWeights, image: int) -> int:
    """The tile of ``image`` that shows the origin (the cameras' target)."""
    cam_K, R, c = t.K[image], t.R[image], t.center[image]
    uv = cam_K @ (R.T @ -c)
    return (image * t.rows + int(uv[1] / uv[2]) // TILE) * t.cols + int(uv[0] / uv[2]) // TILE


def statistics(cameras, target_error):
    """Every tile visited with error 1 and the distance to the origin; the origin's tile of
    each image with ``target_error[i]``."""
    t = TransientWeights(cameras, H, W, TILE, ratio=3.0)
    tiles = np.arange(len(t.error))
    image = tiles // (t.rows * t.cols)
    t.update(tiles, np.ones(len(tiles)), np.linalg.norm(t.center[image], axis=1))
    for i, e in enumerate(target_error):
        t.error[seen(t, i)] = e
    t._take_reference()
    return t


def test_a_tile_that_errs_only_in_its_photo_weighs_nothing():
    cameras = ring()
    t = statistics(cameras, [40.0] + [1.0] * 7)
    weights = t.tile_weights(np.array([seen(t, i) for i in range(8)]))
    assert weights[0] == 0.0
    np.testing.assert_array_equal(weights[1:], 1.0)
    # Between RATIO and twice it, the weight falls linearly: 2 - r / RATIO.
    t = statistics(cameras, [4.5] + [1.0] * 7)
    assert t.tile_weights(np.array([seen(t, 0)]))[0] == pytest.approx(2 - 4.5 / 3.0)


def test_hard_content_that_errs_in_every_photo_keeps_its_weight():
    t = statistics(ring(), [1.0] * 8)
    centre = np.array([seen(t, i) for i in range(8)])
    row = (centre // t.cols) * t.cols
    for i in range(t.cols):             # hard content across the middle of every photo
        t.error[row + i] = 40.0
    t._take_reference()
    np.testing.assert_array_equal(t.tile_weights(np.array([seen(t, i) for i in range(8)])), 1.0)


def test_a_photo_that_errs_as_a_whole_keeps_its_weight():
    t = statistics(ring(), [1.0] * 8)
    per_image = t.rows * t.cols
    t.error[:per_image] *= 25.0               # photo 0 off as a whole (an exposure)
    t._take_reference()
    np.testing.assert_array_equal(t.tile_weights(np.arange(per_image)), 1.0)


def test_unjudged_tiles_and_the_start_of_the_run_keep_their_weight():
    cameras = ring(2)                          # one other photo: fewer than MIN_VIEWS
    t = statistics(cameras, [40.0, 1.0])
    assert t.tile_weights(np.array([seen(t, 0)]))[0] == 1.0
    t = statistics(ring(), [40.0] + [1.0] * 7)
    index = np.array([(H // 2) * W + W // 2])   # photo 0's centre pixel, at full size
    assert t.weights(t.tiles(index), START - 0.01)[0] == 1.0
    assert t.weights(t.tiles(index), START)[0] == t.tile_weights(t.tiles(index))[0]


@pytest.mark.parametrize('factor', [1, 2, 4])
def test_a_rays_tile_holds_the_centre_of_its_pixel_block(factor):
    t = TransientWeights(ring(3), H, W, TILE, ratio=2.0)
    hf, wf = H // factor, W // factor
    index = np.arange(3 * hf * wf)
    image, within = np.divmod(index, hf * wf)
    y, x = np.divmod(within, wf)
    row, col = np.divmod(t.tiles(index, factor) - image * t.rows * t.cols, t.cols)
    cy, cx = y * factor + factor / 2, x * factor + factor / 2
    assert np.all((row * TILE <= cy) & (cy < (row + 1) * TILE + 1))
    assert np.all((col * TILE <= cx) & (cx < (col + 1) * TILE + 1))


def test_state_round_trips_and_damage_is_refused():
    t = statistics(ring(), [40.0] + [1.0] * 7)
    fresh = TransientWeights(ring(), H, W, TILE, ratio=3.0)
    fresh.restore(t.state())
    np.testing.assert_array_equal(fresh.masks(), t.masks())
    for key, bad in (('transients.error', -np.ones_like(t.error)),
                     ('transients.visited', np.full(t.error.size, 2.0)),
                     ('transients.distance', np.array(['a'] * t.error.size))):
        with pytest.raises(ValueError, match='transient statistics are damaged'):
            TransientWeights(ring(), H, W, TILE, 3.0).restore(dict(t.state(), **{key: bad}))
    other = TransientWeights(ring(), H, W, 4, 3.0)       # other tiles: starts anew
    other.restore(t.state())
    assert not other.visited.any()


def test_a_run_with_transients_reports_them_and_writes_their_masks(capture, tmp_path):
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    out = tmp_path / 'run'
    r = subprocess.run([sys.executable, os.path.join(root, 'optimize.py'), capture, '--out',
                        str(out), *TINY_RUN, '--iterations', '20', '--transients', '3'],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    assert 'transients: ' in r.stdout and 'weighed below one half' in r.stdout
    metrics = json.loads((out / 'metrics.json').read_text())
    assert 0.0 <= metrics['transients']['share'] <= 1.0
    masks = sorted(os.listdir(out / 'transients'))
    train = sorted(os.listdir(os.path.join(capture, 'train', 'rgb')))
    assert [os.path.splitext(m)[0] for m in masks] == [os.path.splitext(p)[0] for p in train]
    mask = iio.imread(out / 'transients' / masks[0])
    assert mask.shape[:2] == iio.imread(os.path.join(capture, 'train', 'rgb', train[0])).shape[:2]


def test_bad_transients_options_are_refused():
    from mi_nerfpp.training.config import TrainConfig
    for bad in (1.0, 0.5, -2.0, float('nan')):
        with pytest.raises(ValueError, match='--transients must be 0 \\(off\\) or a ratio above 1'):
            TrainConfig.from_options(transients=bad)
