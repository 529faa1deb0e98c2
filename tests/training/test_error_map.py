"""The error map that draws training rays where the error is (training/error_map.py)."""
import numpy as np
import pytest

from mi_nerfpp.training.error_map import (CAP, RATE, REFERENCE_EVERY, UNVISITED,
                                          ErrorMap)


def _pixels(index, shape, factor):
    """``(image, y, x)`` at the level of a ray bank index, as RayBank._pixel decodes it."""
    n, h, w = shape
    hf, wf = h // factor, w // factor
    image, within = np.divmod(index.astype(np.int64), hf * wf)
    y, x = np.divmod(within, wf)
    return image, y, x


@pytest.mark.parametrize('factor', [1, 2, 4, 8])
@pytest.mark.parametrize('height, width, tile', [(48, 64, 16), (37, 50, 8), (30, 30, 5),
                                                  (20, 24, 3)])
def test_a_drawn_ray_lies_in_the_tile_it_reports(height, width, tile, factor):
    m = ErrorMap(3, height, width, tile, share=0.5)
    m.error[:] = np.random.default_rng(1).random(m.error.size) + 0.01
    index, tiles = m.draw(np.random.default_rng(0), 4000, factor)
    image, y, x = _pixels(index, m.shape, factor)
    assert index.dtype == np.uint32
    assert np.all(y < height // factor) and np.all(x < width // factor)
    t_image, within = np.divmod(tiles, m.rows * m.cols)
    row, col = np.divmod(within, m.cols)
    np.testing.assert_array_equal(image, t_image)
    # The level pixel's block of F x F full-size pixels starts in the tile, or (a tile
    # narrower than a block, or cropped away at this level) is the nearest block to it.
    for level, tile_index, size in ((y, row, height // factor), (x, col, width // factor)):
        start = level * factor
        inside = (start >= tile_index * tile) & (start < (tile_index + 1) * tile)
        holds = (start <= tile_index * tile) & (tile_index * tile < start + factor)
        last = level == size - 1
        assert np.all(inside | holds | last)


def test_rays_go_to_tiles_in_proportion_to_their_error_within_their_image():
    m = ErrorMap(2, 32, 32, 16, share=1.0)          # 2 images of 4 tiles
    m.error[:4] = [0.001, 0.001, 0.001, 0.003]      # image 0: one tile 3x its neighbours
    m.error[4:] = 0.1                               # image 1: off as a whole (an exposure)
    m._take_reference()
    _, tiles = m.draw(np.random.default_rng(0), 200_000)
    share = np.bincount(tiles, minlength=8) / tiles.size
    # Each image keeps its area's half; within image 0, errors relative to its median 0.001.
    expected = np.array([1, 1, 1, 3, 1.5, 1.5, 1.5, 1.5]) / 12
    np.testing.assert_allclose(share, expected, rtol=0.03)
    np.testing.assert_allclose(m.probabilities(), expected, rtol=1e-12)


def test_a_tile_no_scene_explains_takes_at_most_cap_times_its_images_mean():
    m = ErrorMap(1, 64, 64, 16, share=1.0)          # 16 tiles
    m.update(np.arange(16), np.full(16, 0.001))
    for _ in range(REFERENCE_EVERY):                # a transient: huge, for ever
        m.update(np.array([5]), np.array([1e6]))
    assert m.reference[0] == pytest.approx(0.001)
    p = m.probabilities()
    assert p[5] / p[0] == pytest.approx(CAP, rel=1e-9)
    assert p[5] == pytest.approx(CAP / (15 + CAP))


def test_the_medians_are_taken_every_few_updates_and_resume_with_the_map():
    m = ErrorMap(2, 32, 32, 16, share=0.5)
    m.update(np.arange(8), np.full(8, 0.002))
    np.testing.assert_allclose(m.reference, [0.002, 0.002])
    m.update(np.arange(4), np.full(4, 0.102))           # not yet taken again
    np.testing.assert_allclose(m.reference, [0.002, 0.002])
    for _ in range(REFERENCE_EVERY - 2):
        m.update(np.array([0]), np.array([0.0]))
    r = ErrorMap(2, 32, 32, 16, share=0.5)
    r.restore(m.state())
    for k in (m, r):                                     # the 32nd update takes them
        k.update(np.array([7]), np.array([0.002]))
    np.testing.assert_array_equal(r.reference, m.reference)
    assert m.reference[0] > 0.002
    np.testing.assert_array_equal(r.probabilities(), m.probabilities())


def test_without_a_share_for_the_error_every_pixel_is_as_likely():
    # 20 x 20 images in tiles of 8: the edge tiles are 8 x 4 and 4 x 4 pixels.
    m = ErrorMap(2, 20, 20, 8, share=0.0)
    m.error[:] = np.linspace(0.001, 1.0, m.error.size)      # ignored at share 0
    index, _ = m.draw(np.random.default_rng(0), 400_000)
    counts = np.bincount(index, minlength=2 * 20 * 20)
    expected = 400_000 / counts.size
    assert abs(counts.mean() - expected) < 1e-9
    # Binomial spread: 1,000 draws a pixel, sd ~32; the edge tiles' pixels as the others'.
    assert np.abs(counts - expected).max() < 6 * np.sqrt(expected)
    edge = counts.reshape(2, 20, 20)[:, 16:, 16:]
    assert edge.mean() == pytest.approx(expected, rel=0.03)


def test_the_map_keeps_a_moving_average_of_each_tiles_error():
    m = ErrorMap(1, 32, 32, 16, share=0.5)
    assert np.all(m.error == UNVISITED) and not m.visited.any()
    m.update(np.array([0, 0, 3]), np.array([0.02, 0.04, 0.5]))
    assert m.error[0] == pytest.approx(0.03) and m.error[3] == pytest.approx(0.5)
    assert m.error[1] == UNVISITED and list(m.visited) == [True, False, False, True]
    m.update(np.array([0]), np.array([0.13]))
    assert m.error[0] == pytest.approx((1 - RATE) * 0.03 + RATE * 0.13)
    for _ in range(200):                            # fitted exactly: still drawn, rarely
        m.update(np.array([3]), np.array([0.0]))
    assert 0 < m.error[3] < 1e-9
    assert 0 < m.probabilities()[3] < 0.5 / 4 * 1.001          # its share of the uniform half


def test_unvisited_tiles_are_drawn_first_within_their_image():
    m = ErrorMap(2, 64, 64, 16, share=0.9)               # 16 tiles an image
    m.update(np.arange(8), np.full(8, 0.001))            # half of image 0 seen, fitted well
    m.update(np.arange(16, 32), np.full(16, 0.001))      # all of image 1
    _, tiles = m.draw(np.random.default_rng(0), 10_000)
    first = tiles[tiles < 16]
    assert np.mean(first >= 8) > 0.9
    assert np.mean(tiles < 16) == pytest.approx(0.5, abs=0.03)   # each image its area


def test_the_state_round_trips_and_another_tiling_starts_anew():
    m = ErrorMap(2, 40, 40, 10, share=0.5)
    m.update(np.array([1, 7, 7]), np.array([0.1, 0.2, 0.4]))
    r = ErrorMap(2, 40, 40, 10, share=0.5)
    r.restore(m.state())
    np.testing.assert_array_equal(r.error, m.error)
    np.testing.assert_array_equal(r.visited, m.visited)
    other = ErrorMap(2, 40, 40, 8, share=0.5)
    other.restore(m.state())
    assert np.all(other.error == UNVISITED) and not other.visited.any()
    fresh = ErrorMap(2, 40, 40, 10, share=0.5)
    fresh.restore({})                                     # a checkpoint without a map
    assert not fresh.visited.any()


@pytest.mark.parametrize('tile, share', [(0, 0.5), (16, -0.1), (16, 1.5)])
def test_bad_settings_are_refused(tile, share):
    with pytest.raises(ValueError, match='error map'):
        ErrorMap(1, 16, 16, tile, share)
