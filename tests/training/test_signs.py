"""What a run tells a user about their capture (training/signs.py)."""
import numpy as np
import pytest

from mi_nerfpp.training.error_map import CAP, ErrorMap
from mi_nerfpp.training.signs import (DECAY, OUTLIER, SRGB_EXPONENT, CaptureSigns,
                                      sign_lines)


def _batches(signs, rng, steps, error, brightness, photo):
    """Feed ``steps`` batches of 512 rays over the views; per view its error and luminances."""
    n = len(error)
    for _ in range(steps):
        view = rng.integers(0, n, 512)
        noise = rng.uniform(0.5, 1.5, 512)
        signs.update(view, error[view] * noise, brightness[view], photo[view])


def test_a_view_that_fits_far_worse_is_named_and_the_rest_are_not():
    rng = np.random.default_rng(0)
    error = np.full(10, 0.002)
    error[7] = 0.002 * (OUTLIER + 1.5)        # a wrong pose, say
    error[3] = 0.002 * (OUTLIER - 1.0)        # worse, but not far worse
    signs = CaptureSigns(10)
    _batches(signs, rng, 200, error, np.full(10, 0.4), np.full(10, 0.4))
    summary = signs.summary([f'img{i}.jpg' for i in range(10)])
    assert summary['outliers'] == ['img7.jpg']
    assert summary['views'][7]['relative_error'] == pytest.approx(OUTLIER + 1.5, rel=0.1)
    lines = sign_lines(summary)
    assert len(lines) == 1 and 'img7.jpg (4.5x)' in lines[0] and '--refine-poses' in lines[0]


def test_the_exposure_of_each_view_is_measured_in_stops():
    rng = np.random.default_rng(1)
    stops = np.linspace(-0.5, 0.5, 9)
    model = np.full(9, 0.45)                          # the model's consistent brightness
    photo = model * 2.0 ** (stops / SRGB_EXPONENT)    # encoded: linear^(1/2.2)
    signs = CaptureSigns(9)
    _batches(signs, rng, 50, np.full(9, 0.003), model, photo)
    summary = signs.summary()
    np.testing.assert_allclose([v['stops'] for v in summary['views']], stops, atol=1e-3)
    assert summary['exposure_spread_stops'] == pytest.approx(np.std(stops), abs=1e-3)
    assert sign_lines(summary) == []        # a lower bound only: no advice on it


def test_the_signs_forget_old_steps_and_resume_with_the_run():
    signs = CaptureSigns(2)
    signs.update(np.array([0, 1]), np.array([1.0, 1.0]), np.ones(2), np.ones(2))
    for _ in range(3000):                   # view 1 fits better from then on
        signs.update(np.array([0, 1]), np.array([0.01, 0.001]), np.ones(2), np.ones(2))
    views = signs.summary()['views']
    # The first batch's weight has decayed to DECAY^3000 (5 %) of the last one's.
    assert DECAY ** 3000 < 0.05
    assert views[0]['relative_error'] > 1.5
    other = CaptureSigns(2)
    other.restore(signs.state())
    assert other.summary() == signs.summary()
    other.restore({'capture_signs': np.zeros((5, 4))})          # another capture's: kept
    assert other.summary() == signs.summary()
    assert CaptureSigns(3).summary() == {}                      # nothing seen: nothing said


def test_the_unexplained_share_counts_tiles_far_above_their_images_median():
    m = ErrorMap(2, 64, 64, 16, share=0.8)          # 16 tiles of 256 pixels each image
    m.update(np.arange(32), np.full(32, 0.001))
    m.update(np.arange(32), np.full(32, 0.001))
    m.update(np.array([3, 20]), np.full(2, 0.001 * CAP * 10))    # one tile each: a passer-by
    m._take_reference()
    signs = CaptureSigns(2)
    signs.update(np.array([0, 1]), np.full(2, 0.001), np.ones(2), np.ones(2))
    summary = signs.summary(error_map=m)
    assert summary['unexplained_share'] == pytest.approx(2 / 32)
    assert any('6.2 % of the training pixels' in line for line in sign_lines(summary))


def test_outliers_are_split_by_their_pose_check():
    views = [{'name': f'img{i}.jpg', 'relative_error': 1.0, 'stops': 0.0} for i in range(4)]
    views[1]['relative_error'], views[2]['relative_error'] = 5.3, 3.6
    checks = {'img1.jpg': {'error_kept': 0.32, 'turn_degrees': 0.81, 'shift': 0.001,
                           'wrong_pose': True},
              'img2.jpg': {'error_kept': 0.98, 'turn_degrees': 0.03, 'shift': 0.0,
                           'wrong_pose': False}}
    signs = {'views': views, 'outliers': ['img1.jpg', 'img2.jpg'], 'pose_checks': checks}
    wrong, other = sign_lines(signs)
    assert wrong.startswith('training views whose pose looks wrong')
    assert 'img1.jpg (5.3x, 0.81°, 32 %)' in wrong and 'img2.jpg' not in wrong
    assert '--refine-poses' in wrong
    assert 'though not for their pose' in other and 'img2.jpg (3.6x)' in other
    assert 'img1.jpg' not in other and '--refine-poses' not in other
    # A run that refined its poses already says so instead of suggesting it.
    wrong, _ = sign_lines(dict(signs, poses_refined=True))
    assert 'wrong beyond what the run refined' in wrong and '--refine-poses' not in wrong
    # Only hard views: one line, which does not suggest refining poses.
    checks['img1.jpg']['wrong_pose'] = False
    (line,) = sign_lines(signs)
    assert 'img1.jpg (5.3x)' in line and '--refine-poses' not in line
    # An outlier beyond the checked ones is said to be unchecked, not hard.
    views[3]['relative_error'] = 3.1
    signs['outliers'].append('img3.jpg')
    hard, unchecked = sign_lines(signs)
    assert 'img3.jpg' not in hard
    assert 'poses not checked' in unchecked and 'img3.jpg (3.1x)' in unchecked
