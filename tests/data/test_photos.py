"""Photos as cameras store them: EXIF orientation, grayscale, 16 bits, and the automatic
downscale of image sets too large for the memory."""
import os

import numpy as np
import pytest
from PIL import Image

from mi_nerfpp.data import AutoDownscale, image_size, load_dataset, read_image, write_nerfpp
from mi_nerfpp.data.dataset import DatasetError, stored_bytes
from mi_nerfpp.data.sfm import _prepare_photo
from tests.helpers import orbit_camera

# EXIF orientation -> how the stored pixels turn into the upright image.
UPRIGHT = {1: lambda a: a, 3: lambda a: np.rot90(a, 2), 6: lambda a: np.rot90(a, -1),
           8: lambda a: np.rot90(a, 1)}


def stored_pixels():
    """A 4x6 image whose every pixel differs, so any rotation or flip is visible."""
    a = np.zeros((4, 6, 3), dtype=np.uint8)
    a[..., 0] = np.arange(24).reshape(4, 6) * 10
    a[..., 1] = 255 - a[..., 0]
    return a


def save_with_orientation(path, pixels, orientation):
    img = Image.fromarray(pixels)
    exif = Image.Exif()
    exif[0x0112] = orientation
    img.save(path, exif=exif)


@pytest.mark.parametrize('orientation', [1, 3, 6, 8])
def test_exif_orientation_is_applied(tmp_path, orientation):
    pixels = stored_pixels()
    path = tmp_path / 'photo.png'
    save_with_orientation(path, pixels, orientation)
    upright = UPRIGHT[orientation](pixels)
    back = read_image(path)
    np.testing.assert_allclose(back, upright / 255.0, atol=1e-6)
    assert image_size(path) == (upright.shape[1], upright.shape[0])
    # The copy handed to COLMAP is upright too (COLMAP ignores the EXIF tag).
    out = tmp_path / 'colmap'
    os.makedirs(out)
    name = _prepare_photo(str(path), str(out), 'photo.png')
    with Image.open(out / name) as img:
        np.testing.assert_array_equal(np.asarray(img), upright)


def test_grayscale_jpeg_and_16bit_grayscale_photo(tmp_path):
    gray = (np.arange(64 * 48).reshape(48, 64) % 256).astype(np.uint8)
    Image.fromarray(gray).save(tmp_path / 'g.jpg', quality=100)
    back = read_image(tmp_path / 'g.jpg')
    assert back.shape == (48, 64, 3)
    np.testing.assert_allclose(back[..., 0], back[..., 2])
    deep = (np.arange(64 * 48).reshape(48, 64) * 21).astype(np.uint16)
    Image.fromarray(deep).save(tmp_path / 'd.png')   # 16-bit grayscale ('I;16')
    np.testing.assert_allclose(read_image(tmp_path / 'd.png')[..., 1], deep / 65535.0,
                               atol=1e-6)
    name = _prepare_photo(str(tmp_path / 'd.png'), str(tmp_path), 'd.png')
    with Image.open(tmp_path / name) as img:
        assert img.mode == 'L'
        np.testing.assert_allclose(np.asarray(img), deep / 257.0, atol=0.51)


def test_auto_downscale_factor():
    # Nothing to fit, or everything fits: the images' own resolution.
    assert AutoDownscale(0).pick([], []) == 1
    # The case: 135 photos of 1200x800, every 8th held out. Kept as 8-bit, the 118
    # training photos (held twice) and the 17 held-out ones take 0.73 GB at full size.
    train, held_out = [(1200, 800, 8)] * 118, [(1200, 800, 8)] * 17
    full = 2 * 118 * 1200 * 800 * 3 + 17 * 1200 * 800 * 3
    choice = AutoDownscale(2 ** 30)
    assert choice.pick(train, held_out) == 1
    assert (choice.factor, choice.needed, choice.used, choice.size) == (1, full, full,
                                                                        (1200, 800))
    # Downscaled 8-bit images keep exact box sums in 16 bits: 6 bytes per pixel.
    assert stored_bytes([(1200, 800, 8)], 2) == 600 * 400 * 6
    at = {f: 2 * stored_bytes(train, f) + stored_bytes(held_out, f) for f in (2, 3)}
    choice = AutoDownscale(at[3])
    assert choice.pick(train, held_out) == 3 and at[2] > at[3] == choice.used
    assert choice.needed == full
    # 16-bit photos take twice the 8-bit ones at full size.
    assert AutoDownscale(full).pick([(1200, 800, 16)] * 118, held_out) == 2
    # Nothing fits: refused, saying what to do.
    with pytest.raises(DatasetError, match='choose a --downscale to train anyway'):
        AutoDownscale(1000).pick(train, held_out)


def test_load_dataset_picks_the_downscale_from_the_memory(tmp_path):
    width, height = 1200, 900
    cams = [orbit_camera(a, 0.2, 0.5, width, height) for a in (0.0, 1.5, 3.0, 4.5, 5.5)]
    rng = np.random.default_rng(0)
    images = [rng.uniform(0, 1, size=(height, width, 3)) for _ in cams]
    write_nerfpp(tmp_path, {'train': (cams[:4], images[:4]), 'test': (cams[4:], images[4:])})
    full = (2 * 4 + 1) * width * height * 3                       # 8-bit, training twice
    choice = AutoDownscale(full - 1)
    ds = load_dataset(tmp_path, downscale=choice)
    assert ds.downscale == choice.factor == 2 and choice.needed == full
    for split in (ds.train, ds.test):    # one factor for every split
        assert split.images[0].shape == (height // 2, width // 2, 3)
        np.testing.assert_allclose(split.cameras[0].K[0, 0], cams[0].K[0, 0] / 2)
    assert load_dataset(tmp_path).downscale == 1                  # explicit factors stay
    assert load_dataset(tmp_path, downscale=AutoDownscale(full)).downscale == 1
