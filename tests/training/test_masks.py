"""Masks in training (--masks): the ray bank's coverage, the kept rays' loss, the silhouette
loss, the run's choice and announcement, and the held-out scores."""
import dataclasses
import os
import shutil

import drjit as dr
import imageio.v3 as iio
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.commands.cli import main
from mi_nerfpp.data import DatasetError, load_dataset
from mi_nerfpp.data.storage import StoredImages
from mi_nerfpp.data.synth import scene_file, synthesize
from mi_nerfpp.data.synth.capture import write_object_masks
from mi_nerfpp.training import optim
from mi_nerfpp.training.config import TrainConfig
from mi_nerfpp.training.evaluate import matte_iou
from mi_nerfpp.training.raybank import RayBank
from mi_nerfpp.training.train import Trainer
from tests.helpers import TINY_RUN, one_thread

FAST = dict(batch_rays=512, fg_samples=8, bg_samples=8, fine_samples=8, checkpoint_every=0,
            preview_every=0, seed=0)


def with_masks(split, seed):
    """``split`` with a random mask per image (30 % of the pixels black)."""
    rng = np.random.default_rng(seed)
    h, w = split.images[0].shape[:2]
    masks = [np.where(rng.random((h, w)) < 0.3, 0, 255).astype(np.uint8) for _ in split.cameras]
    return dataclasses.replace(split, masks=masks)


@pytest.mark.parametrize('factor', [1, 2])
def test_the_bank_gives_each_ray_its_blocks_mask_coverage(capture, factor):
    split = with_masks(load_dataset(capture).train, seed=0)
    split.masks[1] = None                      # a photo without a mask is kept whole
    bank = RayBank(split, masks=True).level(factor)
    n, h, w = len(split), split.images[0].shape[0] // factor, split.images[0].shape[1] // factor
    index = mi.UInt32(np.arange(n * h * w, dtype=np.uint32))
    mean = bank.mask(index).numpy().reshape(n, h, w)
    least = bank.mask(index, least=True).numpy().reshape(n, h, w)
    for i, mask in enumerate(split.masks):
        full = np.full(split.images[0].shape[:2], 255, np.uint8) if mask is None else mask
        blocks = full[:h * factor, :w * factor].reshape(h, factor, w, factor) / 255.0
        np.testing.assert_allclose(mean[i], blocks.mean(axis=(1, 3)), atol=1e-6)
        np.testing.assert_allclose(least[i], blocks.min(axis=(1, 3)), atol=1e-6)


def test_losses_over_the_kept_rays():
    rng = np.random.default_rng(1)
    a, b = (mi.Color3f(*[mi.Float(rng.random(64)) for _ in range(3)]) for _ in range(2))
    kept = rng.random(64).astype(np.float32)
    err = optim.squared_error(a, b).numpy()
    np.testing.assert_allclose(optim.mse(a, b, mi.Float(kept)).numpy(),
                               np.sum(kept * err) / np.sum(kept), rtol=1e-5)
    np.testing.assert_allclose(optim.mse(a, b).numpy(), np.mean(err), rtol=1e-5)
    # Rays with zero weight get no gradient, whatever their colour.
    x = mi.Color3f(a)
    dr.enable_grad(x)
    zero = np.where(np.arange(64) % 2 == 0, 0.0, 1.0).astype(np.float32)
    dr.backward(optim.charbonnier(x, b, mi.Float(zero)))
    assert np.all(dr.grad(x).numpy()[:, ::2] == 0) and np.any(dr.grad(x).numpy()[:, 1::2] != 0)


def test_silhouette_loss_gradient_matches_finite_differences():
    rng = np.random.default_rng(2)
    alpha, mask = rng.random(32), (rng.random(32) > 0.5).astype(np.float64)
    x = mi.Float(alpha)
    dr.enable_grad(x)
    dr.backward(optim.silhouette_loss(x, mi.Float(mask)))
    eps = 1e-3
    for i in (0, 7, 31):
        up, down = alpha.copy(), alpha.copy()
        up[i] += eps
        down[i] -= eps
        fd = (np.mean((up - mask) ** 2) - np.mean((down - mask) ** 2)) / (2 * eps)
        assert abs(dr.grad(x).numpy()[i] - fd) < 1e-4


def test_ignored_pixels_do_not_reach_the_model(capture, tmp_path):
    """Two captures that differ only under the masks train to the same parameters, bit for
    bit, with --masks ignore (through the image pyramid's coarse levels too); with --masks
    none they do not."""
    dataset = load_dataset(capture)
    masked = with_masks(dataset.train, seed=3)
    garbage = []        # magenta under the masks, in the store's own 8 bits
    for stored, mask in zip(masked.images.stored, masked.masks):
        assert stored.dtype == np.uint8
        changed = np.array(stored)
        changed[mask == 0] = [255, 0, 255]
        garbage.append(changed)
    plain = dataclasses.replace(dataset, train=masked)
    painted = dataclasses.replace(dataset, train=dataclasses.replace(
        masked, images=StoredImages(garbage, masked.images.scale)))
    params = {}
    for meaning in ('ignore', 'none'):
        for name, data in (('plain', plain), ('painted', painted)):
            with one_thread():
                tr = Trainer(data, str(tmp_path / f'{meaning}_{name}'),
                             TrainConfig.from_options(iterations=3, masks=meaning, **FAST))
                tr.run()
            assert tr.cfg.losses.masks == meaning
            params[meaning, name] = {k: np.array(tr.opt[k]) for k in tr.opt.keys()}
    for key, value in params['ignore', 'plain'].items():
        np.testing.assert_array_equal(value, params['ignore', 'painted'][key])
    assert any(np.any(v != params['none', 'painted'][k])
               for k, v in params['none', 'plain'].items())


def test_masks_need_masks(capture, tmp_path, capsys):
    with pytest.raises(DatasetError, match='--masks object, but no training photo has a mask'):
        Trainer(load_dataset(capture), str(tmp_path / 't'),
                TrainConfig.from_options(iterations=1, masks='object', **FAST))
    assert main(['optimize', capture, '--out', str(tmp_path / 'r'), '--masks', 'ignore',
                 *TINY_RUN]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and '--masks ignore, but no training photo has a mask' in err[0]


@pytest.fixture(scope='module')
def object_capture(tmp_path_factory):
    """A small garden capture with each view's object silhouette as its mask."""
    out = str(tmp_path_factory.mktemp('object') / 'c')
    synthesize(scene_file('gt_garden.xml'), out, views=24, res=(48, 36), spp=4, progress=False)
    write_object_masks(out)
    return out


def test_object_masks_make_the_foreground_the_object(object_capture, tmp_path, capsys):
    """--masks object fits the foreground matte to the silhouettes: its held-out IoU with the
    masks beats a run that leaves them unused, and the run says what it did."""
    scores = {}
    for meaning in ('none', 'object'):
        out = str(tmp_path / meaning)
        assert main(['optimize', object_capture, '--out', out, '--iterations', '150',
                     '--batch-rays', '512', '--samples', '8', '8', '8', '--checkpoint-every',
                     '0', '--preview-every', '0', '--masks', meaning]) == 0
        printed = capsys.readouterr().out
        assert f'masks: 20 of 20 training photos have one; --masks {meaning}' in printed
        import json
        with open(os.path.join(out, 'metrics.json')) as f:
            test = json.load(f)['test']
        ious = []
        for i, name in enumerate(sorted(os.listdir(os.path.join(object_capture, 'test',
                                                                 'mask')))):
            from mi_nerfpp.files.exr import read_exr
            alpha = read_exr(os.path.join(out, 'test', f'test_{i:03d}.exr'))['fg.A']
            mask = iio.imread(os.path.join(object_capture, 'test', 'mask', name)) > 127
            ious.append(matte_iou(alpha, mask))
        scores[meaning] = float(np.mean(ious))
        if meaning == 'object':
            assert test['matte_iou'] == pytest.approx(scores[meaning], abs=1e-9)
            assert 'psnr_masked' in test
        else:
            assert 'matte_iou' not in test
    assert scores['object'] > scores['none'] + 0.01, scores


def test_matte_iou():
    alpha = np.array([[0.9, 0.6, 0.2], [0.0, 0.7, 0.4]])
    inside = np.array([[True, False, False], [False, True, True]])
    assert matte_iou(alpha, inside) == pytest.approx(2 / 4)
    assert matte_iou(np.zeros((2, 2)), np.zeros((2, 2), bool)) == 1.0


def test_masked_pixels_do_not_colour_the_coverage_fill(capture):
    from mi_nerfpp.core.coverage import mean_colors
    split = with_masks(load_dataset(capture).train, seed=4)
    painted = []
    for image, mask in zip(split.images, split.masks):
        changed = np.array(image)
        changed[mask == 0] = [1.0, 0.0, 1.0]
        painted.append(changed)
    weights = [m / 255.0 for m in split.masks]
    ours = mean_colors(split.cameras, painted, 'srgb', 16, weights)
    np.testing.assert_allclose(ours, mean_colors(split.cameras, list(split.images), 'srgb', 16,
                                                  weights), atol=1e-12)
    assert not np.allclose(ours, mean_colors(split.cameras, painted, 'srgb', 16))
