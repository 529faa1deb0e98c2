"""Images and dataset readers/writers (mi_nerfpp.data: images, nerfpp, blender, llff, formats)."""
import json
import os
import struct
import warnings
import zlib

import imageio.v3 as iio
import numpy as np
import OpenEXR
import pytest

from mi_nerfpp.data import DatasetError, detect_format, load_dataset, write_nerfpp
from mi_nerfpp.data.cameras import Camera, opencv_to_opengl, opengl_to_opencv, project
from mi_nerfpp.data.images import downscale_image, read_image, write_encoded_png
from mi_nerfpp.data.llff import llff_to_opencv

W, H = 8, 6
K_SMALL = np.array([[7.0, 0.0, 4.2], [0.0, 7.0, 2.9], [0.0, 0.0, 1.0]])


# --- helpers ----------------------------------------------------------------------------------

def look_at(center, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)):
    """OpenCV camera-to-world of a camera at ``center`` looking at ``target``, image up ~ ``up``."""
    center = np.asarray(center, dtype=np.float64)
    forward = np.asarray(target) - center
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, down, forward], axis=1)
    c2w[:3, 3] = center
    return c2w


def ring_cameras(n, radius, offset=(0.0, 0.0, 0.0), K=K_SMALL, width=W, height=H):
    cams = []
    for i in range(n):
        angle = 2 * np.pi * i / n
        center = np.asarray(offset) + radius * np.array([np.cos(angle), 0.3, np.sin(angle)])
        cams.append(Camera(K=K, c2w=look_at(center, target=offset), width=width, height=height,
                           name=f'cam{i}'))
    return cams


def random_images(n, seed, width=W, height=H):
    rng = np.random.default_rng(seed)
    return [rng.random((height, width, 3)).astype(np.float32) for _ in range(n)]


def quantized(img):
    return np.round(np.clip(img, 0, 1) * 255) / 255


def write_png16(path, pixels):
    """Minimal 16-bit PNG encoder (Pillow cannot write 16-bit colour PNGs)."""
    height, width = pixels.shape[:2]
    channels = 1 if pixels.ndim == 2 else pixels.shape[2]
    color_type = {1: 0, 2: 4, 3: 2, 4: 6}[channels]
    raw = b''.join(b'\x00' + pixels[y].astype('>u2').tobytes() for y in range(height))

    def chunk(kind, data):
        return (struct.pack('>I', len(data)) + kind + data
                + struct.pack('>I', zlib.crc32(kind + data) & 0xffffffff))

    header = struct.pack('>IIBBBBB', width, height, 16, color_type, 0, 0, 0)
    with open(path, 'wb') as f:
        f.write(b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', header) + chunk(b'IDAT', zlib.compress(raw))
                + chunk(b'IEND', b''))


def write_exr(path, channels):
    with OpenEXR.File({'compression': OpenEXR.ZIP_COMPRESSION, 'type': OpenEXR.scanlineimage},
                      channels) as f:
        f.write(str(path))


def write_nerfpp_dataset(root, n_train=4, n_test=2, radius=0.5, offset=(0.0, 0.0, 0.0)):
    cams = ring_cameras(n_train + n_test, radius, offset)
    images = random_images(n_train + n_test, seed=0)
    write_nerfpp(root, {'train': (cams[:n_train], images[:n_train]),
                        'test': (cams[n_train:], images[n_train:])})
    return cams, images


def assert_same_camera(loaded, expected, atol=1e-12):
    np.testing.assert_allclose(loaded.c2w, expected.c2w, atol=atol)
    np.testing.assert_allclose(loaded.K, expected.K, atol=atol)
    assert (loaded.width, loaded.height) == (expected.width, expected.height)


# --- images -----------------------------------------------------------------------------------

def test_png_8bit_round_trip(tmp_path):
    img = random_images(1, seed=1)[0]
    write_encoded_png(tmp_path / 'a.png', img)
    back = read_image(tmp_path / 'a.png')
    assert back.dtype == np.float32 and back.shape == (H, W, 3)
    np.testing.assert_allclose(back, quantized(img), atol=1e-6)


@pytest.mark.parametrize('channels', [1, 3, 4])
def test_png_16bit_full_precision(tmp_path, channels):
    rng = np.random.default_rng(2)
    pixels = rng.integers(0, 65536, size=(H, W, channels), dtype=np.uint16)
    write_png16(tmp_path / 'a.png', pixels if channels > 1 else pixels[..., 0])
    back = read_image(tmp_path / 'a.png', background=(0.0, 0.0, 0.0))
    values = pixels.astype(np.float64) / 65535
    rgb = np.repeat(values, 3, axis=2) if channels == 1 else values[..., :3]
    expected = rgb * values[..., 3:] if channels == 4 else rgb
    np.testing.assert_allclose(back, expected, atol=1e-6)   # far below 8-bit steps (4e-3)


def test_rgba_png_is_composited_with_straight_alpha(tmp_path):
    rgba = np.zeros((2, 2, 4), dtype=np.uint8)
    rgba[..., :3] = [200, 100, 0]
    rgba[..., 3] = [[255, 0], [51, 204]]
    iio.imwrite(tmp_path / 'a.png', rgba)
    bg = (0.2, 0.4, 0.6)
    back = read_image(tmp_path / 'a.png', background=bg)
    color = np.array([200, 100, 0]) / 255
    for (y, x), a in {(0, 0): 1.0, (0, 1): 0.0, (1, 0): 0.2, (1, 1): 0.8}.items():
        np.testing.assert_allclose(back[y, x], color * a + np.array(bg) * (1 - a), atol=1e-6)


def test_grayscale_and_jpeg(tmp_path):
    gray = (np.arange(W * H).reshape(H, W) * 5).astype(np.uint8)
    iio.imwrite(tmp_path / 'g.png', gray)
    back = read_image(tmp_path / 'g.png')
    assert back.shape == (H, W, 3)
    np.testing.assert_allclose(back[..., 1], gray / 255, atol=1e-6)
    smooth = np.full((16, 16, 3), [60, 120, 180], dtype=np.uint8)
    iio.imwrite(tmp_path / 'c.jpg', smooth, quality=95)
    np.testing.assert_allclose(read_image(tmp_path / 'c.jpg'), smooth / 255, atol=3 / 255)


def test_exr_values_are_returned_linear_and_unclipped(tmp_path):
    rng = np.random.default_rng(3)
    rgb = (rng.random((H, W, 3)) * 4).astype(np.float32)
    write_exr(tmp_path / 'a.exr', {'RGB': rgb})
    np.testing.assert_array_equal(read_image(tmp_path / 'a.exr'), rgb)
    y = rng.random((H, W)).astype(np.float32)
    write_exr(tmp_path / 'y.exr', {'Y': y})
    np.testing.assert_array_equal(read_image(tmp_path / 'y.exr'), np.repeat(y[..., None], 3, 2))


def test_exr_alpha_is_premultiplied(tmp_path):
    rgba = np.array([[[0.5, 0.25, 2.0, 0.5]]], dtype=np.float32)
    write_exr(tmp_path / 'a.exr', {'RGBA': rgba})
    back = read_image(tmp_path / 'a.exr', background=(1.0, 0.0, 0.0))
    np.testing.assert_allclose(back[0, 0], [1.0, 0.25, 2.0])


def test_unreadable_image_names_the_file(tmp_path):
    for name in ('bad.png', 'bad.exr', 'bad.jpg'):
        (tmp_path / name).write_bytes(b'not an image')
        with pytest.raises(DatasetError, match='cannot read image') as info:
            read_image(tmp_path / name)
        assert str(tmp_path / name) in str(info.value)
    with pytest.raises(DatasetError, match='cannot read image'):
        read_image(tmp_path / 'missing.png')


def test_write_encoded_png_rejects_integer_images(tmp_path):
    with pytest.raises(TypeError, match='float'):
        write_encoded_png(tmp_path / 'a.png', np.zeros((2, 2, 3), dtype=np.uint8))


def test_downscale_image_averages_blocks():
    img = np.arange(7 * 9 * 3, dtype=np.float32).reshape(7, 9, 3)
    small = downscale_image(img, 2)
    assert small.shape == (3, 4, 3)
    np.testing.assert_allclose(small[1, 2], img[2:4, 4:6].mean(axis=(0, 1)))


# --- NeRF++ layout ----------------------------------------------------------------------------

def test_nerfpp_round_trip(tmp_path):
    cams, images = write_nerfpp_dataset(tmp_path)
    assert sorted(os.listdir(tmp_path / 'train' / 'rgb')) == [f'{i:06d}.png' for i in range(4)]
    assert detect_format(tmp_path) == 'nerfpp'
    ds = load_dataset(tmp_path)
    assert (ds.format, ds.color_space, ds.root) == ('nerfpp', 'srgb', str(tmp_path))
    assert (len(ds.train), len(ds.validation), len(ds.test)) == (4, 0, 2)
    np.testing.assert_array_equal(ds.normalization.center, 0.0)
    assert ds.normalization.scale == 1.0
    for split, offset in ((ds.train, 0), (ds.test, 4)):
        for i, (cam, img) in enumerate(zip(split.cameras, split.images)):
            assert_same_camera(cam, cams[offset + i], atol=0.0)   # text keeps every bit
            np.testing.assert_allclose(img, quantized(images[offset + i]), atol=1e-6)
    assert ds.train.image_paths[0] == str(tmp_path / 'train' / 'rgb' / '000000.png')


def test_nerfpp_pose_is_opencv_camera_to_world(tmp_path):
    """A hand-written pose: camera at z = -0.5 looking along world -z, image down = world -y."""
    for sub in ('rgb', 'pose', 'intrinsics'):
        os.makedirs(tmp_path / 'train' / sub)
    write_encoded_png(tmp_path / 'train' / 'rgb' / 'a.png', np.zeros((H, W, 3)))
    (tmp_path / 'train' / 'pose' / 'a.txt').write_text(
        '1 0 0 0\n0 -1 0 0\n0 0 -1 -0.5\n0 0 0 1\n')
    (tmp_path / 'train' / 'intrinsics' / 'a.txt').write_text(
        '7 0 4 0 0 7 3 0 0 0 1 0 0 0 0 1')
    cam = load_dataset(tmp_path).train.cameras[0]
    np.testing.assert_array_equal(cam.center, [0, 0, -0.5])
    np.testing.assert_array_equal(cam.c2w[:3, 2], [0, 0, -1])   # 3rd column = viewing direction
    # A point in front of the camera (further along -z) projects to the principal point ...
    np.testing.assert_allclose(project(cam, [0, 0, -2])[0][0], [4, 3])
    # ... and world +y (image down is world -y here) lands above it.
    assert project(cam, [0, 0.1, -2])[0][0][1] < 3


def test_nerfpp_normalizes_cameras_outside_the_unit_sphere(tmp_path):
    offset = np.array([10.0, -3.0, 7.0])
    cams, _ = write_nerfpp_dataset(tmp_path, radius=5.0, offset=offset)
    ds = load_dataset(tmp_path)
    loaded = ds.train.cameras + ds.test.cameras
    centers = np.stack([cam.center for cam in loaded])
    np.testing.assert_allclose(centers.mean(axis=0), 0.0, atol=1e-12)
    assert np.linalg.norm(centers, axis=1).max() == pytest.approx(1 / 1.1)
    np.testing.assert_allclose(ds.normalization.center, np.mean([c.center for c in cams], axis=0))
    for original, cam in zip(cams, loaded):
        norm = ds.normalization
        np.testing.assert_allclose(cam.center / norm.scale + norm.center, original.center)
        np.testing.assert_allclose(cam.c2w[:3, :3], original.c2w[:3, :3])


def test_nerfpp_validation_split_and_downscale(tmp_path):
    cams = ring_cameras(3, 0.5)
    images = random_images(3, seed=4)
    write_nerfpp(tmp_path, {'train': (cams[:2], images[:2]), 'validation': (cams[2:], images[2:])})
    ds = load_dataset(tmp_path, downscale=2)
    assert (len(ds.train), len(ds.validation), len(ds.test)) == (2, 1, 0)
    cam, img = ds.validation.cameras[0], ds.validation.images[0]
    assert img.shape == (H // 2, W // 2, 3) and (cam.width, cam.height) == (W // 2, H // 2)
    np.testing.assert_allclose(cam.K[:2], K_SMALL[:2] / 2)
    np.testing.assert_allclose(img, downscale_image(quantized(images[2]), 2), atol=1e-6)


def test_nerfpp_exr_images_are_linear(tmp_path):
    write_nerfpp_dataset(tmp_path, n_test=0)
    rgb_dir = tmp_path / 'train' / 'rgb'
    for name in os.listdir(rgb_dir):
        write_exr(rgb_dir / name.replace('.png', '.exr'),
                  {'RGB': np.full((H, W, 3), 2.5, dtype=np.float32)})
        os.remove(rgb_dir / name)
    ds = load_dataset(tmp_path)
    assert ds.color_space == 'linear'
    assert ds.train.images[0].max() == 2.5


def test_write_nerfpp_refuses_to_mix_with_existing_files(tmp_path):
    write_nerfpp_dataset(tmp_path)
    with pytest.raises(FileExistsError):
        write_nerfpp_dataset(tmp_path)
    with pytest.raises(ValueError, match='unknown split'):
        write_nerfpp(tmp_path / 'other', {'val': ([], [])})


def _break(root, case):
    """Damage a freshly written NeRF++ dataset; returns the path the error must name."""
    train = root / 'train'
    if case == 'missing_folder':
        for name in os.listdir(train / 'intrinsics'):
            os.remove(train / 'intrinsics' / name)
        os.rmdir(train / 'intrinsics')
        return train / 'intrinsics'
    if case == 'count_mismatch':
        os.remove(train / 'pose' / '000001.txt')
        return train
    if case == 'unpaired_stem':
        os.rename(train / 'pose' / '000001.txt', train / 'pose' / 'zzz.txt')
        return train / 'pose' / 'zzz.txt'
    if case == 'different_sizes':
        write_encoded_png(train / 'rgb' / '000002.png', np.zeros((H + 2, W, 3)))
        return train / 'rgb' / '000002.png'
    if case == 'unreadable_image':
        (train / 'rgb' / '000001.png').write_bytes(b'\x89PNG truncated')
        return train / 'rgb' / '000001.png'
    if case == 'non_finite_pose':
        (train / 'pose' / '000003.txt').write_text('1 0 0 nan 0 1 0 0 0 0 1 0 0 0 0 1')
        return train / 'pose' / '000003.txt'
    if case == 'short_matrix':
        (train / 'intrinsics' / '000000.txt').write_text('7 0 4 0 7 3 0 0 1')
        return train / 'intrinsics' / '000000.txt'
    if case == 'non_finite_intrinsics':
        (train / 'intrinsics' / '000002.txt').write_text('inf 0 4 0 0 7 3 0 0 0 1 0 0 0 0 1')
        return train / 'intrinsics' / '000002.txt'
    if case == 'mixed_exr_png':
        write_exr(root / 'test' / 'rgb' / '000000.exr', {'RGB': np.zeros((H, W, 3), np.float32)})
        os.remove(root / 'test' / 'rgb' / '000000.png')
        return root / 'test' / 'rgb' / '000000.exr'
    if case == 'scaled_pose':
        (train / 'pose' / '000000.txt').write_text('2 0 0 0 0 2 0 0 0 0 2 0 0 0 0 1')
        return train / 'pose' / '000000.txt'
    if case == 'empty_train':
        for sub in ('rgb', 'pose', 'intrinsics'):
            for name in os.listdir(train / sub):
                os.remove(train / sub / name)
        return train
    raise AssertionError(case)


@pytest.mark.parametrize('case', ['missing_folder', 'count_mismatch', 'unpaired_stem',
                                  'different_sizes', 'unreadable_image', 'non_finite_pose',
                                  'short_matrix', 'non_finite_intrinsics', 'mixed_exr_png',
                                  'scaled_pose', 'empty_train'])
def test_nerfpp_bad_input_names_the_offending_path(tmp_path, case):
    write_nerfpp_dataset(tmp_path)
    offending = _break(tmp_path, case)
    with pytest.raises(DatasetError) as info:
        load_dataset(tmp_path)
    assert str(offending) in str(info.value)


def test_unrecognized_or_missing_dataset(tmp_path):
    with pytest.raises(DatasetError, match='not a recognized dataset') as info:
        load_dataset(tmp_path)
    assert str(tmp_path) in str(info.value)
    with pytest.raises(DatasetError, match='no such file'):
        load_dataset(tmp_path / 'nowhere')


# --- transforms.json --------------------------------------------------------------------------

def blender_frame(file_path, c2w_opencv, **extra):
    return {'file_path': file_path,
            'transform_matrix': opencv_to_opengl(c2w_opencv).tolist(), **extra}


def test_blender_split_layout(tmp_path):
    cams = ring_cameras(3, 0.6)
    angle_x = 2 * np.arctan(0.5 * W / 7.0)
    os.makedirs(tmp_path / 'train')
    os.makedirs(tmp_path / 'test')
    rgba = np.zeros((H, W, 4))
    rgba[..., 0] = 1.0
    rgba[:, : W // 2, 3] = 1.0          # left half opaque red, right half transparent
    for name in ('train/r_0', 'train/r_1', 'test/r_0'):
        write_encoded_png(tmp_path / f'{name}.png', rgba)
    for split, frames in (('train', [blender_frame('./train/r_0', cams[0].c2w),
                                     blender_frame('./train/r_1', cams[1].c2w)]),
                          ('test', [blender_frame('./test/r_0', cams[2].c2w)])):
        (tmp_path / f'transforms_{split}.json').write_text(
            json.dumps({'camera_angle_x': angle_x, 'frames': frames}))
    assert detect_format(tmp_path) == 'blender'
    ds = load_dataset(tmp_path, background=(0.0, 0.0, 1.0))
    assert (len(ds.train), len(ds.validation), len(ds.test)) == (2, 0, 1)
    expected_K = np.array([[7.0, 0, W / 2], [0, 7.0, H / 2], [0, 0, 1]])
    for cam, original in zip(ds.train.cameras + ds.test.cameras, cams):
        np.testing.assert_allclose(cam.c2w, original.c2w, atol=1e-12)
        np.testing.assert_allclose(cam.K, expected_K, atol=1e-12)
    img = ds.train.images[0]
    np.testing.assert_allclose(img[0, 0], [1, 0, 0])
    np.testing.assert_allclose(img[0, -1], [0, 0, 1])
    assert ds.test.image_paths[0] == str(tmp_path / 'test' / 'r_0.png')


def test_blender_opengl_pose_semantics(tmp_path):
    """OpenGL identity rotation at z = 0.5: looks along world -z, image up = world +y."""
    write_encoded_png(tmp_path / 'a.png', np.zeros((H, W, 3)))
    gl = np.eye(4)
    gl[2, 3] = 0.5
    frames = [{'file_path': 'a.png', 'transform_matrix': gl.tolist()}]
    (tmp_path / 'transforms_train.json').write_text(
        json.dumps({'camera_angle_x': 1.0, 'frames': frames}))
    cam = load_dataset(tmp_path).train.cameras[0]
    np.testing.assert_array_equal(cam.c2w, [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 0.5],
                                            [0, 0, 0, 1]])
    cx, cy = W / 2, H / 2
    np.testing.assert_allclose(project(cam, [0, 0, -1])[0][0], [cx, cy])
    assert project(cam, [0.1, 0, -1])[0][0][0] > cx   # world +x is image right
    assert project(cam, [0, 0.1, -1])[0][0][1] < cy   # world +y is image up


def test_instant_ngp_single_file(tmp_path):
    cams = ring_cameras(10, 0.7)
    os.makedirs(tmp_path / 'images')
    frames = []
    for i, cam in enumerate(cams):
        if i != 3:      # frame 3's image is missing
            write_encoded_png(tmp_path / 'images' / f'{i:02d}.png', np.full((H, W, 3), i / 10))
        extra = {'fl_x': 9.0} if i == 5 else {}
        frames.append(blender_frame(f'images/{i:02d}.png', cam.c2w, **extra))
    frames.reverse()    # frame order in the file must not matter
    # Distortion keys that are all zero (as nerfstudio writes them for pinholes) change
    # nothing; distortion itself is tested in tests/data/test_undistort.py.
    meta = {'fl_x': 7.0, 'fl_y': 7.5, 'cx': 4.2, 'cy': 2.9, 'w': W, 'h': H,
            'k1': 0.0, 'k2': 0.0, 'p1': 0.0, 'p2': 0.0, 'frames': frames}
    (tmp_path / 'transforms.json').write_text(json.dumps(meta))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        ds = load_dataset(tmp_path)
    messages = ' | '.join(str(w.message) for w in caught)
    assert 'distortion' not in messages and 'skipped 1 of 10' in messages
    assert not os.path.exists(tmp_path / 'transforms_undistorted')
    assert ds.train.image_paths[0] == str(tmp_path / 'images' / '01.png')
    # 9 images left, sorted by path; every 8th (0 and 8) is held out as test.
    assert [c.name for c in ds.test.cameras] == ['00', '09']
    assert [c.name for c in ds.train.cameras] == ['01', '02', '04', '05', '06', '07', '08']
    assert len(ds.validation) == 0
    by_name = {c.name: c for c in ds.train.cameras + ds.test.cameras}
    np.testing.assert_allclose(by_name['01'].K, [[7.0, 0, 4.2], [0, 7.5, 2.9], [0, 0, 1]])
    np.testing.assert_allclose(by_name['05'].K[0, 0], 9.0)     # per-frame override
    np.testing.assert_allclose(by_name['02'].c2w, cams[2].c2w, atol=1e-12)
    np.testing.assert_allclose(ds.train.images[0], 0.1, atol=1 / 255)


def test_transforms_bad_input(tmp_path):
    (tmp_path / 'transforms.json').write_text('{"frames": [')
    with pytest.raises(DatasetError, match='cannot read JSON') as info:
        load_dataset(tmp_path)
    assert str(tmp_path / 'transforms.json') in str(info.value)

    frames = [blender_frame(f'missing{i}.png', np.eye(4)) for i in range(3)]
    (tmp_path / 'transforms.json').write_text(json.dumps({'camera_angle_x': 1, 'frames': frames}))
    with pytest.warns(UserWarning, match='skipped 3 of 3'):
        with pytest.raises(DatasetError, match='train split has no images') as info:
            load_dataset(tmp_path)
    assert str(tmp_path / 'transforms.json') in str(info.value)

    write_encoded_png(tmp_path / 'a.png', np.zeros((H, W, 3)))
    frames = [blender_frame('a.png', np.eye(4))]
    (tmp_path / 'transforms.json').write_text(
        json.dumps({'fl_x': 7, 'w': W + 1, 'h': H, 'frames': frames}))
    with pytest.raises(DatasetError, match='declares') as info:
        load_dataset(tmp_path)
    assert str(tmp_path / 'a.png') in str(info.value)

    (tmp_path / 'transforms.json').write_text(json.dumps({'frames': frames}))
    with pytest.raises(DatasetError, match='no focal length') as info:
        load_dataset(tmp_path)
    assert str(tmp_path / 'transforms.json') in str(info.value)

    nan_pose = np.eye(4)
    nan_pose[0, 3] = np.nan
    (tmp_path / 'transforms.json').write_text(json.dumps(
        {'fl_x': 7, 'frames': [{'file_path': 'a.png', 'transform_matrix': nan_pose.tolist()}]}))
    with pytest.raises(DatasetError, match='non-finite') as info:
        load_dataset(tmp_path)
    assert str(tmp_path / 'transforms.json') in str(info.value)


# --- LLFF -------------------------------------------------------------------------------------

def llff_row(down, right, back, center, hwf=(H, W, 7.0)):
    pose = np.column_stack([down, right, back, center, hwf])
    return np.concatenate([pose.ravel(), [0.1, 2.0]])


def write_llff(root, rows, image_size=(W, H)):
    os.makedirs(root / 'images')
    np.save(root / 'poses_bounds.npy', np.stack(rows))
    for i in range(len(rows)):
        write_encoded_png(root / 'images' / f'IMG_{i:04d}.png',
                  np.full((image_size[1], image_size[0], 3), 0.5))


def test_llff_axis_convention(tmp_path):
    # Camera 0 at z = 0.5 looking at the origin (along -z) with image up = world +y:
    # down = -y, right = +x, backward = +z.
    row0 = llff_row(down=[0, -1, 0], right=[1, 0, 0], back=[0, 0, 1], center=[0, 0, 0.5])
    # Camera 1 at x = 0.5 looking at the origin (along -x), image up = +y: right = -z.
    row1 = llff_row(down=[0, -1, 0], right=[0, 0, -1], back=[1, 0, 0], center=[0.5, 0, 0])
    row2 = llff_row(down=[0, -1, 0], right=[-1, 0, 0], back=[0, 0, -1], center=[0, 0, -0.5])
    write_llff(tmp_path, [row0, row1, row2])
    assert detect_format(tmp_path) == 'llff'
    ds = load_dataset(tmp_path)
    assert ds.format == 'llff'
    assert [c.name for c in ds.test.cameras] == ['IMG_0000']        # every 8th: index 0
    assert [c.name for c in ds.train.cameras] == ['IMG_0001', 'IMG_0002']
    cam0 = ds.test.cameras[0]
    np.testing.assert_array_equal(cam0.c2w, [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 0.5],
                                             [0, 0, 0, 1]])
    np.testing.assert_allclose(cam0.c2w, look_at([0, 0, 0.5]), atol=1e-12)
    np.testing.assert_allclose(ds.train.cameras[0].c2w, look_at([0.5, 0, 0]), atol=1e-12)
    np.testing.assert_allclose(cam0.K, [[7, 0, W / 2], [0, 7, H / 2], [0, 0, 1]])


def test_llff_matches_nerf_load_llff_conversion():
    """NeRF's load_llff turns [down, right, back] into OpenGL [right, up, back]."""
    rng = np.random.default_rng(6)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    pose = np.column_stack([q, rng.normal(size=3)])
    nerf_gl = np.concatenate([pose[:, 1:2], -pose[:, 0:1], pose[:, 2:]], axis=1)
    expected = opengl_to_opencv(np.vstack([nerf_gl, [0, 0, 0, 1]]))
    np.testing.assert_allclose(llff_to_opencv(pose), expected, atol=1e-15)


def test_llff_rescales_focal_for_resized_images(tmp_path):
    rows = [llff_row([0, -1, 0], [1, 0, 0], [0, 0, 1], [0, 0, 0.2 * i], hwf=(3 * H, 3 * W, 21.0))
            for i in range(2)]
    write_llff(tmp_path, rows)
    cam = load_dataset(tmp_path, llff_hold=0).train.cameras[0]
    np.testing.assert_allclose(cam.K[0, 0], 7.0)


def test_llff_bad_input(tmp_path):
    write_llff(tmp_path, [llff_row([0, -1, 0], [1, 0, 0], [0, 0, 1], [0, 0, 0.5])] * 2)
    os.remove(tmp_path / 'images' / 'IMG_0001.png')
    with pytest.raises(DatasetError, match='1 images but') as info:
        load_dataset(tmp_path)
    assert str(tmp_path / 'images') in str(info.value)
    np.save(tmp_path / 'poses_bounds.npy', np.zeros((1, 15)))
    with pytest.raises(DatasetError, match='N x 17') as info:
        load_dataset(tmp_path)
    assert str(tmp_path / 'poses_bounds.npy') in str(info.value)
