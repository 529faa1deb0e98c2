"""The realistic stand-in of a phone capture (data/synth/realistic.py): each degradation does what
it says, alone, and the readers take the result back (the lens through COLMAP's undistortion)."""
import json
import os

import imageio.v3 as iio
import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from mi_nerfpp.commands.cli import main
from mi_nerfpp.core.color import srgb_eotf
from mi_nerfpp.data import load_dataset
from mi_nerfpp.data.cameras import opengl_to_opencv
from mi_nerfpp.data.synth import scene_file, synthesize
from mi_nerfpp.data.synth.realistic import (DEGRADATIONS, REALISTIC_FILE, Realism,
                                            realistic_copy)
from mi_nerfpp.files.exr import read_exr

NOTHING = Realism().without(*DEGRADATIONS)


@pytest.fixture(scope='module')
def clean(tmp_path_factory):
    out = str(tmp_path_factory.mktemp('clean') / 'c')
    synthesize(scene_file('gt_garden.xml'), out, views=12, res=(96, 72), spp=4, progress=False)
    return out


def _linear(path):
    return srgb_eotf(iio.imread(path)[..., :3].astype(np.float64) / 255.0)


def _clean_linear(clean, stem):
    layers = read_exr(os.path.join(clean, 'train', 'gt', stem + '.exr'))
    return np.clip(np.stack([layers[c] for c in 'RGB'], axis=-1), 0, 1).astype(np.float64)


def _turn_degrees(a, b):
    cos = (np.trace(a @ b.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def _frames(out, split='train'):
    name = {'train': 'transforms_train.json', 'test': 'transforms_test.json'}[split]
    with open(os.path.join(out, name)) as f:
        return json.load(f)['frames']


def test_with_every_degradation_off_the_copy_is_the_clean_capture(clean, tmp_path):
    out = str(tmp_path / 's')
    record = realistic_copy(clean, out, NOTHING, progress=False)
    for frame, view in zip(_frames(out), record['views']['train']):
        image = iio.imread(os.path.join(out, frame['file_path']))
        stored = iio.imread(os.path.join(clean, 'train', 'rgb', view['name'] + '.png'))[..., :3]
        assert frame['file_path'].endswith('.png') and 'k1' not in frame
        assert np.abs(image.astype(int) - stored.astype(int)).max() <= 1     # rounding
        np.testing.assert_allclose(opengl_to_opencv(np.array(frame['transform_matrix'])),
                                   view['true_c2w'])


def test_the_lens_is_undone_by_the_reader(clean, tmp_path):
    out = str(tmp_path / 's')
    realistic_copy(clean, out, Realism(k1=0.08, k2=0.02, p1=1e-3, p2=-1e-3).without(
        'exposure', 'noise', 'jpeg', 'blur', 'poses', 'transients'), progress=False)
    frame = _frames(out)[0]
    assert frame['camera_model'] == 'OPENCV' and frame['k1'] == 0.08
    distorted = iio.imread(os.path.join(out, frame['file_path']))
    stored = iio.imread(os.path.join(clean, 'train', 'rgb', '000000.png'))[..., :3]
    assert np.abs(distorted.astype(float) - stored).mean() > 3        # the lens moved pixels
    dataset = load_dataset(out)
    cam = dataset.train.cameras[0]
    # The undistorted (pinhole) image against the clean render resampled through the two Ks.
    K = np.loadtxt(os.path.join(clean, 'train', 'intrinsics', '000000.txt'))[:3, :3]
    y, x = np.mgrid[0:cam.height, 0:cam.width] + 0.5
    u = (x - cam.K[0, 2]) / cam.K[0, 0] * K[0, 0] + K[0, 2]
    v = (y - cam.K[1, 2]) / cam.K[1, 1] * K[1, 1] + K[1, 2]
    want = np.stack([map_coordinates(stored[..., c] / 255.0, [v - 0.5, u - 0.5], order=1)
                     for c in range(3)], axis=-1)
    got = np.asarray(dataset.train.images[0])[..., :3]
    inner = (slice(3, -3), slice(3, -3))
    psnr = -10 * np.log10(np.mean((got[inner] - want[inner]) ** 2))
    as_given = -10 * np.log10(np.mean((distorted / 255.0 - stored / 255.0) ** 2))
    assert psnr > 31 and psnr > as_given + 4, (psnr, as_given)     # 33.6 against 27.1 here


def test_exposure_and_noise_are_applied_in_linear_light(clean, tmp_path):
    out = str(tmp_path / 's')
    record = realistic_copy(clean, out, NOTHING.__class__(
        **{**NOTHING.__dict__, 'exposure_stops': 0.5, 'white_balance': 0.1}), progress=False)
    views = record['views']['train']
    assert views[0]['gain'] != [1.0, 1.0, 1.0]      # the first photo has its own exposure too
    for frame, view in zip(_frames(out), views):
        gain = np.array(view['gain'])
        assert np.all(np.abs(np.log2(gain)) <= 0.6 + 1e-9)
        clean_lin = _clean_linear(clean, view['name'])
        ok = (clean_lin > 0.05) & (clean_lin * gain < 0.9)
        ratio = _linear(os.path.join(out, frame['file_path'])) / np.maximum(clean_lin, 1e-6)
        for c in range(3):
            assert np.median(ratio[..., c][ok[..., c]]) == pytest.approx(gain[c], rel=0.03)
    noisy = str(tmp_path / 'n')
    realistic_copy(clean, noisy, NOTHING.__class__(**{**NOTHING.__dict__, 'shot_noise': 4e-3,
                                                      'read_noise': 1e-4}), progress=False)
    frame = _frames(noisy)[3]
    stem = os.path.splitext(os.path.basename(frame['file_path']))[0]
    clean_lin = _clean_linear(clean, stem)
    residual = _linear(os.path.join(noisy, frame['file_path'])) - clean_lin
    mid = (clean_lin > 0.1) & (clean_lin < 0.5)
    sigma = np.sqrt(4e-3 * clean_lin[mid] + 1e-4)
    # Standardized residuals: unit spread (8-bit rounding adds a little).
    assert np.std(residual[mid] / sigma) == pytest.approx(1.0, abs=0.12)


def test_poses_blur_transients_and_jpeg(clean, tmp_path):
    out = str(tmp_path / 's')
    r = Realism(pose_degrees=0.5, pose_fraction=0.01, blur_share=0.3, blur_length=0.06,
                transient_share=0.2, jpeg_quality=80).without('lens', 'exposure', 'noise')
    record = realistic_copy(clean, out, r, seed=3, progress=False)
    views, frames = record['views']['train'], _frames(out)
    for i, (frame, view) in enumerate(zip(frames, views)):
        given = opengl_to_opencv(np.array(frame['transform_matrix']))
        true = np.array(view['true_c2w'])
        np.testing.assert_allclose(given, view['given_c2w'])
        turn = _turn_degrees(given[:3, :3], true[:3, :3])
        shift = np.linalg.norm(given[:3, 3] - true[:3, 3])
        if i == 0:
            assert turn == pytest.approx(0, abs=1e-6) and shift == pytest.approx(0, abs=1e-12)
        else:
            assert turn == pytest.approx(0.5, abs=1e-6)
            assert shift == pytest.approx(0.01 * record['radius'], rel=1e-6)
        assert frame['file_path'].endswith('.jpg')
    blurred = [i for i, v in enumerate(views) if 'blur' in v]
    masked = [i for i, v in enumerate(views) if 'transient_pixels' in v]
    assert len(blurred) == round(0.3 * len(views)) and len(masked) == round(0.2 * len(views))

    def detail(i):
        image = _linear(os.path.join(out, frames[i]['file_path'])).mean(axis=2)
        return np.mean(np.abs(np.diff(image, axis=1)))

    def clean_detail(i):
        return np.mean(np.abs(np.diff(_clean_linear(clean, views[i]['name']).mean(axis=2),
                                      axis=1)))
    for i in blurred:
        assert detail(i) < 0.8 * clean_detail(i)
    for i in masked:
        mask = iio.imread(os.path.join(out, 'transients', views[i]['name'] + '.png')) > 0
        assert mask.sum() == views[i]['transient_pixels'] > 0.02 * mask.size
        image = _linear(os.path.join(out, frames[i]['file_path']))
        assert np.abs(image - _clean_linear(clean, views[i]['name']))[mask].mean() > 0.02
    # Held-out views stay clean, at their true poses.
    for frame in _frames(out, 'test'):
        assert frame['file_path'].endswith('.png') and 'k1' not in frame


def test_the_command_writes_a_stand_in_the_reader_takes(tmp_path):
    out = str(tmp_path / 'phone')
    assert main(['synth', scene_file('gt_garden.xml'), '--out', out, '--res', '64x48',
                 '--views', '10', '--spp', '2', '--realistic']) == 0
    with open(os.path.join(out, REALISTIC_FILE)) as f:
        record = json.load(f)
    assert record['realism'] == Realism().__dict__
    dataset = load_dataset(out)
    assert len(dataset.train) == 8 and len(dataset.test) == 1
    # Again: the clean capture is reused and the stand-in written anew.
    assert main(['synth', scene_file('gt_garden.xml'), '--out', out, '--res', '64x48',
                 '--views', '10', '--spp', '2', '--realistic']) == 0


def test_bad_folders_are_refused(clean, tmp_path):
    with pytest.raises(FileNotFoundError, match='not a synthetic capture'):
        realistic_copy(str(tmp_path), str(tmp_path / 'x'))
    busy = tmp_path / 'busy'
    busy.mkdir()
    (busy / 'notes.txt').write_text('mine')
    with pytest.raises(FileExistsError, match='holds no realistic.json'):
        realistic_copy(clean, str(busy))
    assert (busy / 'notes.txt').read_text() == 'mine'
    with pytest.raises(ValueError, match='unknown degradation'):
        Realism().without('fog')


def test_masks_leave_the_transients_out_through_the_lens(clean, tmp_path):
    """With ``masks=True`` every training photo ships a mask, black exactly on its transient;
    the reader undistorts the masks with their photos (under the cache's masks/)."""
    realism = Realism(transient_share=0.5, masks=True).without('noise', 'exposure', 'blur',
                                                                'poses', 'jpeg')
    record = realistic_copy(clean, tmp_path / 's', realism, seed=2, progress=False)
    ds = load_dataset(tmp_path / 's')
    assert os.path.isdir(tmp_path / 's' / 'transforms_train_undistorted' / 'masks')
    for i, view in enumerate(record['views']['train']):
        mask, image = ds.train.masks[i], ds.train.images[i]
        assert mask.shape == image.shape[:2]
        assert (mask < 128).any() == ('transient_pixels' in view)
        if 'transient_pixels' in view:      # as large as the transient, through the lens
            masked = np.count_nonzero(mask < 128)
            assert abs(masked / view['transient_pixels'] - 1) < 0.3, (masked, view)
    assert ds.test.masks is None
