"""Masks (mi_nerfpp.data.masks): found in every layout, read, downscaled, checked."""
import json
import os
import warnings

import imageio.v3 as iio
import numpy as np
import pytest

from mi_nerfpp.data import DatasetError, load_dataset
from mi_nerfpp.data.cameras import opencv_to_opengl
from mi_nerfpp.data.images import downscale_image, write_encoded_png
from mi_nerfpp.data.masks import find_mask, stored_mask
from tests.data.test_colmap import ground_truth_cameras, write_colmap
from tests.data.test_datasets import W, H, random_images, ring_cameras, write_nerfpp_dataset


def random_masks(n, seed, width=W, height=H):
    rng = np.random.default_rng(seed)
    return [np.where(rng.random((height, width)) < 0.3, 0, 255).astype(np.uint8)
            for _ in range(n)]


def write_masks(folder, names, masks, ext='.png'):
    os.makedirs(folder, exist_ok=True)
    for name, mask in zip(names, masks):
        iio.imwrite(os.path.join(folder, name + ext), mask)


def test_nerfpp_layout_reads_each_splits_mask_folder(tmp_path):
    write_nerfpp_dataset(tmp_path, n_train=4, n_test=2)
    train, test = random_masks(4, 0), random_masks(2, 1)
    write_masks(tmp_path / 'train' / 'mask', [f'{i:06d}' for i in range(4)], train)
    write_masks(tmp_path / 'test' / 'mask', [f'{i:06d}' for i in range(2)], test, ext='.jpg')
    ds = load_dataset(tmp_path)
    assert ds.has_masks and ds.validation.masks is None
    for got, want in zip(ds.train.masks, train):
        np.testing.assert_array_equal(got, want)
    # JPEG masks: read through their compression, still binary where it matters.
    assert all(np.mean((got > 127) == (want > 127)) > 0.9 for got, want in zip(ds.test.masks, test))


def test_masks_are_downscaled_with_their_photos_as_coverage(tmp_path):
    write_nerfpp_dataset(tmp_path, n_train=3, n_test=1)
    masks = random_masks(3, 2)
    write_masks(tmp_path / 'train' / 'mask', [f'{i:06d}' for i in range(3)], masks)
    ds = load_dataset(tmp_path, downscale=2)
    for got, want in zip(ds.train.masks, masks):
        expected = downscale_image(want[..., None].astype(np.float32) / 255, 2)[..., 0]
        assert got.shape == ds.train.images[0].shape[:2]
        np.testing.assert_allclose(got / 255.0, expected, atol=0.5 / 255)
    assert stored_mask(np.ones((4, 4), np.float32), 1).dtype == np.uint8


def test_transforms_mask_path_and_missing_mask_file(tmp_path):
    cams, images = ring_cameras(3, 0.5), random_images(3, seed=3)
    masks = random_masks(3, 4)
    frames = []
    for i, (cam, image) in enumerate(zip(cams, images)):
        write_encoded_png(tmp_path / f'r_{i}.png', image)
        frames.append({'file_path': f'r_{i}.png', 'mask_path': f'm/r_{i}.png',
                       'transform_matrix': opencv_to_opengl(cam.c2w).tolist()})
    write_masks(tmp_path / 'm', [f'r_{i}' for i in range(3)], masks)
    meta = {'fl_x': float(cams[0].K[0, 0]), 'cx': float(cams[0].K[0, 2]),
            'cy': float(cams[0].K[1, 2]), 'frames': frames}
    (tmp_path / 'transforms.json').write_text(json.dumps(meta))
    ds = load_dataset(tmp_path, llff_hold=0)
    for got, want in zip(ds.train.masks, masks):
        np.testing.assert_array_equal(got, want)
    os.remove(tmp_path / 'm' / 'r_1.png')
    with pytest.raises(DatasetError, match=r'r_1\.png: the mask that .* names .* is missing'):
        load_dataset(tmp_path, llff_hold=0)


def test_llff_and_colmap_read_masks_beside_images(tmp_path):
    cams = ground_truth_cameras(6)
    write_colmap(tmp_path, cams)
    masks = random_masks(6, 5, width=cams[0].width, height=cams[0].height)
    write_masks(tmp_path / 'masks', [c.name for c in cams], masks)
    ds = load_dataset(tmp_path, llff_hold=0)
    for cam, got in zip(ds.train.cameras, ds.train.masks):
        np.testing.assert_array_equal(got, masks[[c.name for c in cams].index(cam.name)])
    # COLMAP's own naming (the image's name plus .png) is found too.
    assert find_mask(str(tmp_path / 'masks'), 'img_00.png') is not None
    os.rename(tmp_path / 'masks' / 'img_00.png', tmp_path / 'masks' / 'img_00.png.png')
    assert find_mask(str(tmp_path / 'masks'), 'img_00.png').endswith('img_00.png.png')


def test_masks_of_a_distorted_colmap_model_are_undistorted_like_their_images(tmp_path):
    cams = ground_truth_cameras(4)
    write_colmap(tmp_path, cams, 'OPENCV', extra=[-0.08, 0.02, 0.001, -0.001])
    # Each mask is its image's red channel thresholded: after undistortion it must still be.
    names = [c.name for c in cams]
    masks = [np.where(iio.imread(tmp_path / 'images' / (n + '.png'))[..., 0] > 127, 255, 0)
             .astype(np.uint8) for n in names]
    write_masks(tmp_path / 'masks', names, masks)
    ds = load_dataset(tmp_path, llff_hold=0)
    assert os.path.isdir(tmp_path / 'undistorted_masks')
    for image, mask in zip(ds.train.images, ds.train.masks):
        assert mask.shape == image.shape[:2]
        sure = (mask > 230) | (mask < 25)          # away from resampled edges
        agree = (mask[sure] > 127) == (image[..., 0][sure] > 0.5)
        assert agree.mean() > 0.9, agree.mean()


def test_bad_masks_end_with_one_line_or_warn_what_was_assumed(tmp_path):
    write_nerfpp_dataset(tmp_path, n_train=3, n_test=1)
    folder = tmp_path / 'train' / 'mask'
    write_masks(folder, ['000000'], [np.zeros((H + 1, W), np.uint8)])
    with pytest.raises(DatasetError, match=rf'000000\.png: the mask is {W}x{H + 1} but its photo '):
        load_dataset(tmp_path)
    (folder / '000000.png').write_bytes(b'not a png')
    with pytest.raises(DatasetError, match=r'000000\.png: cannot read the mask'):
        load_dataset(tmp_path)
    write_masks(folder, ['000000'], [np.zeros((H, W), np.uint8)])
    with pytest.warns(UserWarning) as caught:
        ds = load_dataset(tmp_path)
    text = ' '.join(str(w.message) for w in caught)
    assert 'black everywhere' in text and '2 of 3 photos have no mask' in text
    assert ds.train.masks[1] is None
    soft = np.tile(np.linspace(0, 255, W).astype(np.uint8), (H, 1))
    write_masks(folder, ['000000', '000001', '000002'], [soft] * 3)
    with pytest.warns(UserWarning, match='not black and white'):
        load_dataset(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        write_masks(folder, ['000000', '000001', '000002'], random_masks(3, 6))
        load_dataset(tmp_path)
