"""How a split keeps its images (mi_nerfpp.data.storage): 8-bit, 16-bit and EXR files round
trip through a loaded dataset within the storage's quantization, stated per test."""
import imageio.v3 as iio
import numpy as np
import pytest

from mi_nerfpp.data import load_dataset
from mi_nerfpp.data.nerfpp import write_camera
from mi_nerfpp.data.images import downscale_image, read_image, read_stored_image
from mi_nerfpp.data.storage import FLOAT16_MAX, StoredImages, bytes_per_pixel, store, to_float
from tests.data.test_datasets import ring_cameras, write_exr, write_png16

W, H = 256, 90        # 69,120 values per image: every 8-bit and every 16-bit level fits
K = np.array([[200.0, 0.0, W / 2], [0.0, 200.0, H / 2], [0.0, 0.0, 1.0]])


def capture(root, writers):
    """A NeRF++ dataset of training images written by ``writers`` (file name -> a function of
    the path that writes it), W x H pixels each."""
    rgb = root / 'train' / 'rgb'
    rgb.mkdir(parents=True)
    cams = ring_cameras(len(writers), 0.5, K=K, width=W, height=H)
    for cam, (name, write) in zip(cams, writers.items()):
        write(rgb / name)
        write_camera(str(root / 'train'), name.rsplit('.', 1)[0], cam)
    return root


def every_level(top, channels=3):
    """Every integer level 0..top in an H x W x channels image (repeating), shuffled."""
    values = np.arange(H * W * channels) % (top + 1)
    return np.random.default_rng(top).permutation(values).reshape(H, W, channels)


def test_8bit_png_and_jpeg_are_kept_as_stored(tmp_path):
    pixels = every_level(255).astype(np.uint8)
    ds = load_dataset(capture(tmp_path, {
        'a.png': lambda p: iio.imwrite(p, pixels),
        'b.jpg': lambda p: iio.imwrite(p, pixels, quality=90)}))
    images = ds.train.images
    assert images.dtype == np.uint8 and images.scale == 255
    assert images.nbytes == 2 * H * W * 3 == 2 * H * W * bytes_per_pixel(8)
    np.testing.assert_array_equal(images.stored[0], pixels)                      # exact
    np.testing.assert_array_equal(images.stored[1], iio.imread(ds.train.image_paths[1]))
    for i, path in enumerate(ds.train.image_paths):       # floats as read_image reads them
        assert images[i].dtype == np.float32
        np.testing.assert_array_equal(images[i], read_image(path))
    np.testing.assert_array_equal(images[0], pixels / np.float32(255))


def test_16bit_png_is_kept_as_stored(tmp_path):
    pixels = every_level(65535).astype(np.uint16)
    ds = load_dataset(capture(tmp_path, {'a.png': lambda p: write_png16(p, pixels)}))
    images = ds.train.images
    assert images.dtype == np.uint16 and images.scale == 65535
    assert images.nbytes == H * W * 6
    np.testing.assert_array_equal(images.stored[0], pixels)                      # exact
    np.testing.assert_array_equal(images[0], read_image(ds.train.image_paths[0]))
    np.testing.assert_array_equal(images[0], pixels / np.float32(65535))


def test_exr_is_kept_as_half_floats_within_their_precision(tmp_path):
    rng = np.random.default_rng(0)
    # Linear values over the whole range of float16 and below it: 1e-7 .. 6e4, and 0.
    rgb = np.exp(rng.uniform(np.log(1e-7), np.log(6e4), (H, W, 3))).astype(np.float32)
    rgb[0, :4] = np.array([0.0, 1.0, 2.5, FLOAT16_MAX])[:, None]
    half = rgb.astype(np.float16)
    ds = load_dataset(capture(tmp_path, {
        'a.exr': lambda p: write_exr(p, {'RGB': rgb}),
        'b.exr': lambda p: write_exr(p, {'RGB': half})}))        # a half-float EXR
    images = ds.train.images
    assert images.dtype == np.float16 and images.nbytes == 2 * H * W * 6
    back = images[0]
    assert back.dtype == np.float32
    # float16 rounds to 11 significant bits: within 2^-11 of the value from 2^-14 (float16's
    # smallest normal) up, within 2^-25 (half its smallest subnormal step) below.
    normal = rgb >= 2.0 ** -14
    assert np.all(np.abs(back - rgb)[normal] <= 2.0 ** -11 * rgb[normal])
    assert np.all(np.abs(back - rgb)[~normal] <= 2.0 ** -25)
    assert normal.mean() > 0.5 and (~normal).mean() > 0.1       # both ranges are exercised
    np.testing.assert_array_equal(back[0, :4], rgb[0, :4])     # representable values: exact
    np.testing.assert_array_equal(images[1], half.astype(np.float32))     # half EXR: exact


def test_exr_beyond_half_floats_is_kept_in_float32(tmp_path):
    rgb = np.full((H, W, 3), 0.3, np.float32)
    rgb[5, 7] = [1e5, 2.0, 3.0]                                 # the sun: above 65504
    ds = load_dataset(capture(tmp_path, {
        'a.exr': lambda p: write_exr(p, {'RGB': rgb}),
        'b.exr': lambda p: write_exr(p, {'RGB': rgb * 0.5})}))
    assert ds.train.images.dtype == np.float32
    np.testing.assert_array_equal(ds.train.images[0], rgb)
    np.testing.assert_array_equal(ds.train.images[1], rgb * np.float32(0.5))


def test_rgba_is_composited_once_and_kept_within_half_a_level(tmp_path):
    rng = np.random.default_rng(1)
    rgba = rng.integers(0, 256, (H, W, 4)).astype(np.uint8)
    bg = (0.2, 0.5, 0.9)
    root = capture(tmp_path, {'a.png': lambda p: iio.imwrite(p, rgba)})
    ds = load_dataset(root, background=bg)
    path = ds.train.image_paths[0]
    composite = read_image(path, background=bg)                # in float, as before
    assert ds.train.images.dtype == np.uint8
    np.testing.assert_array_equal(ds.train.images.stored[0],
                                  np.round(composite.astype(np.float64) * 255))
    assert np.abs(ds.train.images[0] - composite).max() <= 0.5 / 255 + 1e-7
    # A background outside [0, 1] leaves the 8-bit levels: the composite is kept in float.
    over = read_stored_image(path, background=(2.0, 0.0, 0.0))
    assert over.dtype == np.float32
    np.testing.assert_array_equal(over, read_image(path, background=(2.0, 0.0, 0.0)))


@pytest.mark.parametrize('factor', [2, 16])
def test_downscaled_8bit_images_keep_their_exact_box_sums(tmp_path, factor):
    pixels = every_level(255).astype(np.uint8)
    ds = load_dataset(capture(tmp_path, {'a.png': lambda p: iio.imwrite(p, pixels)}),
                      downscale=factor)
    images = ds.train.images
    assert images.dtype == np.uint16 and images.scale == 255 * factor ** 2
    exact = downscale_image(pixels.astype(np.float64), factor) * factor ** 2
    np.testing.assert_array_equal(images.stored[0], exact)
    # The box average as read_image + downscale_image computed it (float64 mean of float32
    # values, rounded to float32): within one float32 step.
    np.testing.assert_array_max_ulp(images[0], downscale_image(read_image(
        ds.train.image_paths[0]), factor), maxulp=1)


def test_images_downscaled_otherwise_keep_16_bits():
    rng = np.random.default_rng(2)
    deep = rng.integers(0, 65536, (H, W, 3)).astype(np.uint16)
    shallow = rng.integers(0, 256, (H, W, 3)).astype(np.uint8)
    for pixels, factor in ((deep, 2), (shallow, 17)):
        stored, scale = store(pixels, factor)
        assert stored.dtype == np.uint16 and scale == 65535
        top = np.float32(np.iinfo(pixels.dtype).max)
        expected = downscale_image(pixels.astype(np.float32) / top, factor)
        assert np.abs(to_float(stored, scale) - expected).max() <= 0.5 / 65535 + 1e-7


def test_a_split_of_8_and_16_bit_images_keeps_16_bits_and_8_bit_values_exactly(tmp_path):
    shallow = every_level(255).astype(np.uint8)
    deep = every_level(65535).astype(np.uint16)
    ds = load_dataset(capture(tmp_path, {'a.png': lambda p: iio.imwrite(p, shallow),
                                         'b.png': lambda p: write_png16(p, deep)}))
    images = ds.train.images
    assert images.dtype == np.uint16 and images.scale == 65535
    np.testing.assert_array_equal(images.stored[0], shallow.astype(np.uint16) * 257)
    for i, path in enumerate(ds.train.image_paths):
        np.testing.assert_array_equal(images[i], read_image(path))


def test_float_images_given_to_a_split_stay_float32():
    a = np.random.default_rng(3).random((4, 5, 3))
    images = StoredImages.of([a])
    assert images.dtype == np.float32 and len(images) == 1
    np.testing.assert_array_equal(images[0], a.astype(np.float32))
    assert [x.shape for x in images] == [(4, 5, 3)] and images[:1][0].shape == (4, 5, 3)
