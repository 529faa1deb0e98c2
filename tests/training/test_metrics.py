"""Tests for the image quality metrics in mi_nerfpp.training.metrics."""
from __future__ import annotations

import math

import numpy as np
import pytest

from mi_nerfpp.training import metrics


def noisy(image, sigma, seed=0):
    rng = np.random.default_rng(seed)
    return np.clip(image + rng.normal(0.0, sigma, image.shape), 0.0, 1.0)


@pytest.fixture
def gt():
    rng = np.random.default_rng(42)
    smooth = np.cumsum(rng.uniform(size=(32, 40, 3)), axis=1)
    return smooth / smooth.max()


def test_mse_and_psnr_of_constant_offset():
    gt = np.full((8, 8, 3), 0.5)
    pred = gt + 0.1
    assert metrics.mse(pred, gt) == pytest.approx(0.01, rel=1e-12)
    assert metrics.psnr(pred, gt) == pytest.approx(20.0, abs=1e-9)


def test_psnr_data_range():
    gt = np.full((4, 4, 3), 128.0)
    pred = gt + 25.5
    assert metrics.psnr(pred, gt, data_range=255.0) == pytest.approx(20.0, abs=1e-9)


def test_psnr_mean_over_pixels_and_channels():
    gt = np.zeros((2, 2, 3))
    pred = gt.copy()
    pred[0, 0, 0] = 1.0  # one of 12 values off by 1: mse = 1/12
    assert metrics.psnr(pred, gt) == pytest.approx(10.0 * math.log10(12.0))


def test_identical_images():
    image = np.random.default_rng(0).uniform(size=(9, 11, 3))
    assert metrics.mse(image, image) == 0.0
    assert metrics.psnr(image, image) == math.inf
    assert metrics.ssim(image, image) == pytest.approx(1.0)


def test_ssim_decreases_with_noise(gt):
    scores = [metrics.ssim(noisy(gt, sigma), gt) for sigma in (0.01, 0.05, 0.2)]
    assert 1.0 > scores[0] > scores[1] > scores[2]


def test_psnr_decreases_with_noise(gt):
    scores = [metrics.psnr(noisy(gt, sigma), gt) for sigma in (0.01, 0.05, 0.2)]
    assert scores[0] > scores[1] > scores[2]


def test_float32_inputs(gt):
    pred = noisy(gt, 0.05).astype(np.float32)
    assert metrics.ssim(pred, gt.astype(np.float32)) == pytest.approx(
        metrics.ssim(pred, gt), abs=1e-5)


@pytest.mark.parametrize('shape', [(3, 3, 3), (4, 6, 3), (5, 100, 3), (6, 6, 3)])
def test_ssim_tiny_images(shape):
    gt = np.random.default_rng(1).uniform(size=shape)
    assert metrics.ssim(gt, gt) == pytest.approx(1.0)
    assert metrics.ssim(noisy(gt, 0.3), gt) < 1.0


@pytest.mark.parametrize('size, win', [((3, 3), 3), ((4, 9), 3), ((6, 20), 5),
                                       ((7, 7), 7), ((100, 50), 7)])
def test_ssim_win_size(size, win):
    assert metrics._ssim_win_size(*size) == win


def test_ssim_too_small():
    image = np.zeros((2, 5, 3))
    with pytest.raises(ValueError, match='at least 3'):
        metrics.ssim(image, image)


@pytest.mark.parametrize('fn', [metrics.mse, metrics.psnr, metrics.ssim])
def test_shape_mismatch(fn):
    with pytest.raises(ValueError, match='shapes differ'):
        fn(np.zeros((8, 8, 3)), np.zeros((8, 9, 3)))
    with pytest.raises(ValueError, match='H x W x C'):
        fn(np.zeros((8, 8)), np.zeros((8, 8)))


def test_separation_against_a_hand_computed_example():
    from mi_nerfpp.training.metrics import separation
    gt = np.array([[1.0, 1.0, 0.0, 0.0]])
    alpha = np.array([[1.0, 0.5, 0.1, 0.0]])
    depth_gt = np.array([[2.0, 4.0, 0.0, 0.0]])
    depth = np.array([[2.2, 4.0, 9.0, 9.0]])
    s = separation(alpha, gt, depth, depth_gt)
    assert s['alpha_error'] == pytest.approx((0.5 + 0.1) / 4)
    assert s['leak'] == pytest.approx(0.05)
    assert s['soft_fraction'] == pytest.approx(0.5)          # 0.5 and 0.1
    assert s['depth_error'] == pytest.approx(0.05)           # median of 0.1 and 0
    assert np.isnan(separation(alpha[:, :2], gt[:, :2])['leak'])
    with pytest.raises(ValueError, match='alpha shapes'):
        separation(alpha, gt[:, :2])


def test_soft_alpha_fraction_counts_the_open_band_only():
    from mi_nerfpp.training.metrics import soft_alpha_fraction
    alpha = np.array([[0.0, 0.05, 0.06, 0.5], [0.94, 0.95, 1.0, 0.2]])
    assert soft_alpha_fraction(alpha) == pytest.approx(4 / 8)      # 0.06, 0.5, 0.94, 0.2
    assert soft_alpha_fraction(alpha, (0.1, 0.9)) == pytest.approx(2 / 8)


def test_matte_warning_only_above_the_threshold():
    from mi_nerfpp.training.evaluate import matte_warning
    from mi_nerfpp.training.metrics import SOFT_ALPHA_WARNING
    assert matte_warning({'psnr': 25.0}) is None                     # no background volume
    assert matte_warning({'soft_alpha': SOFT_ALPHA_WARNING}) is None
    text = matte_warning({'soft_alpha': 0.255})
    assert '25.5 %' in text and '--seed' in text and 'soft_alpha' in text


def test_masked_psnr_scores_only_the_masked_pixels():
    from mi_nerfpp.training.metrics import masked_psnr
    gt = np.zeros((4, 4, 3))
    pred = gt.copy()
    pred[:, :2] = 0.1                     # error 0.1 on the left half only
    left = np.zeros((4, 4), bool)
    left[:, :2] = True
    assert masked_psnr(pred, gt, left) == pytest.approx(20.0)
    assert masked_psnr(pred, gt, ~left) == float('inf')
    assert np.isnan(masked_psnr(pred, gt, np.zeros((4, 4), bool)))
    with pytest.raises(ValueError, match='mask shape'):
        masked_psnr(pred, gt, np.ones((2, 2), bool))


def test_equivalent_blur_recovers_the_blur_of_a_blurred_image():
    from scipy.ndimage import gaussian_filter
    rng = np.random.default_rng(3)
    reference = gaussian_filter(rng.uniform(size=(48, 64, 3)), (0.7, 0.7, 0))
    for sigma in (0.6, 1.3, 2.5):
        blurred = gaussian_filter(reference, (sigma, sigma, 0))
        assert metrics.equivalent_blur(blurred, reference) == pytest.approx(sigma, abs=0.01)


def test_equivalent_blur_of_a_perfect_and_of_a_hopeless_prediction(gt):
    assert metrics.equivalent_blur(gt, gt) == 0.0
    # An error no blur of the reference comes near: a constant offset of half the range.
    assert metrics.equivalent_blur(np.clip(gt + 0.5, 0, 1), gt) == math.inf


# ----------------------------------------------------------------------------- error split

def test_the_error_split_finds_known_errors_by_region_and_frequency():
    """A constant colour error in one half (low frequency) and a checkerboard error in the other
    (high frequency): each region's error lands in its band, the shares follow the regions'
    summed errors, and the capture's noise is subtracted."""
    from mi_nerfpp.training.metrics import error_split
    h, w = 64, 64
    gt = np.full((h, w, 3), 0.5)
    pred = gt.copy()
    left = np.zeros((h, w), bool)
    left[:, :w // 2] = True
    pred[:, :w // 2] += 0.1                                   # low: a wrong colour
    checker = (np.indices((h, w)).sum(0) % 2) * 2.0 - 1.0
    pred[:, w // 2:] += 0.05 * checker[:, w // 2:, None]     # high: missing detail / noise
    split = error_split(pred, gt, {'colour': left, 'detail': ~left}, noise_mse=0.0001)
    colour, detail, whole = split['colour'], split['detail'], split['all']
    assert colour['pixels'] == detail['pixels'] == 0.5 and whole['pixels'] == 1.0
    assert colour['mse'] == pytest.approx(0.01) and detail['mse'] == pytest.approx(0.0025)
    # Away from the seam the split is exact: a constant survives blurring, a checkerboard does not.
    assert colour['low'] > 0.9 * colour['mse'] and colour['high'] < 0.05 * colour['mse']
    assert detail['high'] > 0.9 * detail['mse'] and detail['low'] < 0.1 * detail['mse']
    assert colour['share'] == pytest.approx(0.01 / 0.0125) and \
        colour['share'] + detail['share'] == pytest.approx(1.0)
    assert colour['psnr'] == pytest.approx(20.0)
    assert colour['excess'] == pytest.approx(0.0099)
    assert colour['excess_psnr'] == pytest.approx(10 * np.log10(1 / 0.0099))
    assert whole['mse'] == pytest.approx(0.00625)


def test_the_error_split_refuses_a_mask_of_another_size_and_reports_empty_regions():
    from mi_nerfpp.training.metrics import error_split
    image = np.zeros((8, 8, 3))
    with pytest.raises(ValueError, match="region 'x': mask shape"):
        error_split(image, image, {'x': np.ones((4, 4), bool)})
    empty = error_split(image, image, {'none': np.zeros((8, 8), bool)})
    assert empty['none']['pixels'] == 0.0 and np.isnan(empty['none']['mse'])
    assert empty['all']['mse'] == 0.0 and empty['all']['psnr'] == float('inf')


def test_dark_speckles_are_counted_where_a_pixel_falls_below_its_neighbours():
    from mi_nerfpp.training.metrics import SPECKLE_DEPTH, dark_speckle_share
    rng = np.random.default_rng(0)
    image = np.full((40, 50, 3), 0.6) + rng.uniform(-0.02, 0.02, (40, 50, 3))
    assert dark_speckle_share(image) == 0.0
    speckled = image.copy()
    spots = [(5, 7), (20, 30), (33, 44)]
    for y, x in spots:
        speckled[y, x] = 0.6 - 2 * SPECKLE_DEPTH
    assert dark_speckle_share(speckled) == pytest.approx(len(spots) / (40 * 50))
    # A dark region is no speckle but at its four corners (a 3x3 median there is its
    # surroundings'): the ground truth's own share is the baseline a render is held to.
    region = image.copy()
    region[10:20, 10:20] = 0.1
    assert dark_speckle_share(region) == pytest.approx(4 / (40 * 50))
    # Only the mask's pixels count; an empty mask has nothing to measure.
    mask = np.zeros((40, 50), bool)
    mask[:10, :10] = True
    assert dark_speckle_share(speckled, mask) == pytest.approx(1 / 100)
    assert np.isnan(dark_speckle_share(speckled, np.zeros((40, 50), bool)))
