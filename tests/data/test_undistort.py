"""Lens distortion in transforms.json (instant-ngp, nerfstudio): undistorted once with COLMAP
(pycolmap), cached, and checked against pycolmap's own projection and undistorter.

Captures are rendered through pycolmap cameras with distortion: every pixel of a distorted
image shows what its ray (pycolmap's ``cam_from_img``) sees of a few Gaussian blobs around
known 3D points, so where a blob appears in an image is where the camera projects the point.
"""
import json
import re
import os
import signal
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import OpenEXR
import pycolmap
import pytest

import mi_nerfpp.data.undistort as undistort_module
from mi_nerfpp.data import DatasetError, load_dataset
from mi_nerfpp.data.cameras import opencv_to_opengl, project
from mi_nerfpp.data.images import _png_bit_depth, read_image
from mi_nerfpp.data.undistort import atomic_folder
from tests.helpers import orbit_camera

W, H = 96, 72
SIGMA = 1.2             # blob radius in pinhole pixels
# Where a blob shows in the undistorted image vs where our pinhole camera projects its point.
CENTROID_TOLERANCE = 0.1    # pixels (measured: at most 0.046)
REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# transforms.json lens keys -> the pycolmap camera (model, distortion parameters) that renders
# the capture; the reader has to map the keys to the same camera.
LENSES = {
    'nerfstudio OPENCV': ({'camera_model': 'OPENCV', 'k1': -0.3, 'k2': 0.08, 'p1': 0.004,
                           'p2': -0.003},
                          'OPENCV', [-0.3, 0.08, 0.004, -0.003]),
    'instant-ngp k3': ({'k1': -0.25, 'k2': 0.05, 'k3': -0.02, 'p1': 0.002, 'p2': 0.001},
                       'FULL_OPENCV', [-0.25, 0.05, 0.002, 0.001, -0.02, 0.0, 0.0, 0.0]),
    'nerfstudio OPENCV_FISHEYE': ({'camera_model': 'OPENCV_FISHEYE', 'k1': 0.06, 'k2': -0.02,
                                   'k3': 0.004, 'k4': -0.001},
                                  'OPENCV_FISHEYE', [0.06, -0.02, 0.004, -0.001]),
    'instant-ngp is_fisheye': ({'is_fisheye': True, 'k1': -0.04, 'k2': 0.01},
                               'OPENCV_FISHEYE', [-0.04, 0.01, 0.0, 0.0]),
}


def cameras(n=4):
    cams = [orbit_camera(2 * np.pi * i / n, 0.2, 3.0, W, H, focal=0.8) for i in range(n)]
    for cam in cams:
        cam.K[0, 2] += 1.7      # off-centre principal point: catches half-pixel mix-ups
        cam.K[1, 2] -= 0.9
    return cams


def colmap_camera(K, model, distortion):
    return pycolmap.Camera(model=model, width=W, height=H,
                           params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2], *distortion])


def known_points(cam, distorted):
    """World points whose blobs lie inside COLMAP's pinhole image of ``distorted``: on a 3x3
    grid of that image (10% to 90%), at depths 1.5 to 2.5."""
    pinhole = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), distorted)
    u, v = np.meshgrid(np.linspace(0.1, 0.9, 3) * pinhole.width,
                       np.linspace(0.1, 0.9, 3) * pinhole.height)
    xy = pinhole.cam_from_img(np.stack([u.ravel(), v.ravel()], axis=1))
    depth = np.linspace(1.5, 2.5, len(xy))[:, None]
    local = np.column_stack([xy * depth, depth])
    return local @ cam.c2w[:3, :3].T + cam.c2w[:3, 3], pinhole


def render(distorted, cam, points):
    """The distorted image (H, W) of Gaussian blobs (SIGMA pinhole pixels) around ``points``."""
    x, y = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays = distorted.cam_from_img(np.stack([x.ravel(), y.ravel()], axis=1))
    local = (points - cam.c2w[:3, 3]) @ cam.c2w[:3, :3]
    centres = local[:, :2] / local[:, 2:3]
    d2 = ((rays[:, None, :] - centres[None]) ** 2).sum(axis=2)
    sigma = SIGMA / distorted.focal_length_x
    return np.exp(-0.5 * d2 / sigma ** 2).sum(axis=1).reshape(H, W)


def centroid(image, at, radius=4 * SIGMA):
    """Intensity centroid (continuous pixel coordinates) of the blob near ``at``."""
    gray = np.asarray(image, dtype=np.float64)
    gray = gray.mean(axis=2) if gray.ndim == 3 else gray
    x, y = np.meshgrid(np.arange(gray.shape[1]) + 0.5, np.arange(gray.shape[0]) + 0.5)
    window = (x - at[0]) ** 2 + (y - at[1]) ** 2 <= radius ** 2
    w = gray * window
    return np.array([(w * x).sum(), (w * y).sum()]) / w.sum()


def frame(path, cam, **extra):
    return {'file_path': path, 'transform_matrix': opencv_to_opengl(cam.c2w).tolist(), **extra}


def write_capture(root, lens_keys, model, distortion, cams=None, ext='.png'):
    """A transforms.json capture rendered through the distorted pycolmap camera; returns
    ``(cameras, {image name: (points, distorted camera, pinhole camera)})``."""
    cams = cams or cameras()
    os.makedirs(root / 'images', exist_ok=True)
    K = cams[0].K
    truth, frames = {}, []
    for i, cam in enumerate(cams):
        distorted = colmap_camera(K, model, distortion)
        points, pinhole = known_points(cam, distorted)
        image = np.clip(render(distorted, cam, points), 0.0, 1.0)
        name = f'{i:02d}'
        if ext == '.exr':
            write_exr(root / 'images' / f'{name}.exr',
                      {c: image.astype(np.float32) for c in 'RGB'})
        else:
            iio.imwrite(root / 'images' / f'{name}{ext}',
                        np.round(np.repeat(image[..., None], 3, axis=2) * 255).astype(np.uint8))
        truth[name] = (points, distorted, pinhole)
        frames.append(frame(f'images/{name}{ext}', cam))
    meta = {'fl_x': K[0, 0], 'fl_y': K[1, 1], 'cx': K[0, 2], 'cy': K[1, 2], 'w': W, 'h': H,
            **lens_keys, 'frames': frames}
    (root / 'transforms.json').write_text(json.dumps(meta))
    return cams, truth


def write_exr(path, channels):
    with OpenEXR.File({'compression': OpenEXR.ZIP_COMPRESSION, 'type': OpenEXR.scanlineimage},
                      channels) as f:
        f.write(str(path))


# --- geometry against pycolmap --------------------------------------------------------------

@pytest.mark.parametrize('lens', list(LENSES))
def test_undistorted_cameras_project_where_pycolmap_and_the_images_put_points(
        tmp_path, capsys, lens):
    lens_keys, model, distortion = LENSES[lens]
    cams, truth = write_capture(tmp_path, lens_keys, model, distortion)
    ds = load_dataset(tmp_path, llff_hold=0)
    out = capsys.readouterr().out
    cache = tmp_path / 'transforms_undistorted'
    assert f'lens distortion ({model}) in 4 images: undistorting them to pinhole cameras ' \
           f'with COLMAP into {cache}/' in out
    assert len(ds.train) == 4
    worst_shift = 0.0
    for cam, image, path in zip(ds.train.cameras, ds.train.images, ds.train.image_paths):
        points, distorted, pinhole = truth[cam.name]
        assert path == str(cache / 'images' / f'{cam.name}.png')
        world = ds.normalization.to_world_camera(cam)
        # The pose is kept; the intrinsics are COLMAP's pinhole camera for this lens.
        np.testing.assert_allclose(world.c2w, cams[int(cam.name)].c2w, atol=1e-9)
        assert (cam.width, cam.height) == (pinhole.width, pinhole.height)
        ours, depth = project(world, points)
        local = (points - world.center) @ world.c2w[:3, :3]
        np.testing.assert_allclose(ours, pinhole.img_from_cam(local), atol=1e-8)
        assert np.all(depth > 0)
        original = read_image(tmp_path / 'images' / f'{cam.name}.png')
        for pixel, point in zip(ours, local):
            # The undistorted image shows each blob where our pinhole camera projects it ...
            shown = centroid(image, pixel)
            assert np.linalg.norm(shown - pixel) < CENTROID_TOLERANCE, (shown, pixel)
            # ... and the distorted photo where pycolmap's distorted camera does, which is
            # pixels away from where its pinhole part K would (what ignoring distortion did).
            at = distorted.img_from_cam(point)
            np.testing.assert_allclose(centroid(original, at), at, atol=CENTROID_TOLERANCE)
            naive = K_of(distorted) @ (point / point[2])
            worst_shift = max(worst_shift, np.linalg.norm(naive[:2] - at))
    assert worst_shift > 2.0


def K_of(camera):
    fx, fy, cx, cy = camera.params[:4]
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


@pytest.mark.parametrize('lens', ['nerfstudio OPENCV', 'nerfstudio OPENCV_FISHEYE'])
def test_undistorted_images_equal_pycolmaps_undistorter(tmp_path, lens):
    lens_keys, model, distortion = LENSES[lens]
    _, truth = write_capture(tmp_path, lens_keys, model, distortion)
    load_dataset(tmp_path, llff_hold=0)
    for name, (_, distorted, _) in truth.items():
        photo = iio.imread(tmp_path / 'images' / f'{name}.png')
        theirs, camera = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(),
                                                  pycolmap.Bitmap.from_array(photo), distorted)
        ours = iio.imread(tmp_path / 'transforms_undistorted' / 'images' / f'{name}.png')
        assert ours.shape == theirs.to_array().shape
        # pycolmap rounds its bilinear interpolation to 8 bits, as we do.
        assert np.abs(ours.astype(int) - theirs.to_array().astype(int)).max() <= 1
        index = json.loads((tmp_path / 'transforms_undistorted' / 'cameras.json').read_text())
        entry = index['images'][f'images/{name}.png']
        assert entry['source'] == os.path.join('..', 'images', f'{name}.png')
        assert entry['distorted']['model'] == model
        np.testing.assert_allclose(entry['pinhole']['params'], camera.params, atol=1e-9)
        assert (entry['pinhole']['width'], entry['pinhole']['height']) == (camera.width,
                                                                           camera.height)


def test_high_bit_depth_exr_and_alpha_keep_their_precision(tmp_path):
    lens_keys, model, distortion = LENSES['nerfstudio OPENCV']
    cams = cameras(2)
    K = cams[0].K
    distorted = colmap_camera(K, model, distortion)
    pinhole = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), distorted)

    def capture(folder, images):
        os.makedirs(folder / 'images')
        for name, write in images.items():
            write(folder / 'images' / name)
        (folder / 'transforms.json').write_text(json.dumps({
            'fl_x': K[0, 0], 'fl_y': K[1, 1], 'cx': K[0, 2], 'cy': K[1, 2], **lens_keys,
            'frames': [frame(f'images/{n}', cam) for n, cam in zip(images, cams)]}))
        return load_dataset(folder, background=(0.0, 0.0, 1.0), llff_hold=0)

    # A 16-bit PNG (a ramp along x in red) and an 8-bit PNG with straight alpha.
    ramp = np.linspace(0, 1, W) * 0.999
    deep = np.stack([np.round(ramp * 65535)[None, :].repeat(H, axis=0)] * 3, axis=-1)
    deep[..., 1] = deep[:, ::-1, 0]
    deep[..., 2] = 40000
    from tests.data.test_datasets import write_png16
    rgba = np.zeros((H, W, 4), np.uint8)
    rgba[..., 0], rgba[..., 3] = 255, 128
    ds = capture(tmp_path / 'png', {
        'deep.png': lambda path: write_png16(path, deep.astype(np.uint16)),
        'rgba.png': lambda path: iio.imwrite(path, rgba)})
    cache = tmp_path / 'png' / 'transforms_undistorted' / 'images'
    assert _png_bit_depth(str(cache / 'deep.png')) == 16
    cached = ds.train.images[0]
    assert cached.shape == (pinhole.height, pinhole.width, 3)
    assert np.mean(np.round(cached[..., 0] * 65535) % 257 != 0) > 0.5   # not 8-bit levels
    np.testing.assert_allclose(cached[..., 2], 40000 / 65535, atol=1e-6)
    # The ramp is linear in the distorted x: a pinhole pixel's value tells which distorted
    # pixel it came from, and that is where pycolmap's cameras map it.
    for u, v in [(40.5, 30.5), (5.5, 60.5), (pinhole.width - 3.5, 2.5)]:
        source = distorted.img_from_cam(np.append(pinhole.cam_from_img([u, v]), 1.0))
        expected = np.interp(source[0] - 0.5, np.arange(W), ramp)
        assert abs(cached[int(v), int(u), 0] - expected) < 1.5 / 65535
    # 8-bit alpha is undistorted with the colour and composited at load.
    np.testing.assert_allclose(ds.train.images[1], np.broadcast_to(
        [128 / 255, 0, 127 / 255], ds.train.images[1].shape), atol=1e-6)

    # EXR: premultiplied colour above 1, alpha 0.25 (OpenEXR's convention), kept as EXR.
    def exr(path):
        write_exr(path, {c: np.full((H, W), v, np.float32)
                         for c, v in zip('RGBA', (3.0, 0.75, 0.5, 0.25))})
    hdr = capture(tmp_path / 'exr', {'a.exr': exr, 'b.exr': exr})
    assert hdr.color_space == 'linear'
    assert hdr.train.image_paths[0] == str(tmp_path / 'exr' / 'transforms_undistorted' /
                                           'images' / 'a.exr')
    np.testing.assert_allclose(hdr.train.images[0], np.broadcast_to(
        [3.0, 0.75, 0.5 + 0.75], hdr.train.images[0].shape), atol=1e-6)


# --- the cache ------------------------------------------------------------------------------

def count_warps(monkeypatch):
    calls = []
    real = undistort_module.warp

    def counted(pixels, coords):
        calls.append(1)
        return real(pixels, coords)
    monkeypatch.setattr(undistort_module, 'warp', counted)
    return calls


def test_cache_is_reused_and_remade_when_the_json_or_an_image_changes(tmp_path, capsys,
                                                                       monkeypatch):
    lens_keys, model, distortion = LENSES['nerfstudio OPENCV']
    write_capture(tmp_path, lens_keys, model, distortion)
    cache = tmp_path / 'transforms_undistorted'
    calls = count_warps(monkeypatch)
    first = load_dataset(tmp_path, llff_hold=0)
    assert len(calls) == 4
    stamps = {p: os.stat(p).st_mtime_ns for p in cache.rglob('*') if p.is_file()}
    capsys.readouterr()

    # Second load: nothing is undistorted again, nothing in the cache is rewritten.
    again = load_dataset(tmp_path, llff_hold=0)
    assert len(calls) == 4
    assert f'reading them undistorted to pinhole cameras from {cache}/' in capsys.readouterr().out
    assert {p: os.stat(p).st_mtime_ns for p in cache.rglob('*') if p.is_file()} == stamps
    for a, b in zip(first.train.images, again.train.images):
        np.testing.assert_array_equal(a, b)

    # Other coefficients in transforms.json: remade with them.
    meta = json.loads((tmp_path / 'transforms.json').read_text())
    meta['k1'] = -0.1
    (tmp_path / 'transforms.json').write_text(json.dumps(meta))
    changed = load_dataset(tmp_path, llff_hold=0)
    assert len(calls) == 8
    index = json.loads((cache / 'cameras.json').read_text())
    assert index['images']['images/00.png']['distorted']['params'][4] == -0.1
    assert changed.train.cameras[0].width != first.train.cameras[0].width

    # transforms.json newer than the cache (edited, same lens), then an image newer than
    # the cache: remade each time, as is the rule; then reused again.
    for source, count in ((tmp_path / 'transforms.json', 12),
                          (tmp_path / 'images' / '02.png', 16)):
        earlier = os.stat(source).st_mtime - 10
        os.utime(cache / 'cameras.json', (earlier, earlier))
        load_dataset(tmp_path, llff_hold=0)
        assert len(calls) == count
    load_dataset(tmp_path, llff_hold=0)
    assert len(calls) == 16


def _load_and_die_after_writing(root, images):
    """Load the dataset in a child process that is killed (SIGKILL: no cleanup runs) right
    after the undistorter has written ``images`` images."""
    code = f'''
import os, signal
import mi_nerfpp.data.undistort as u
real, written = u._write_pixels, []
def write(path, pixels):
    real(path, pixels)
    written.append(path)
    if len(written) == {images}:
        os.kill(os.getpid(), signal.SIGKILL)
u._write_pixels = write
from mi_nerfpp.data import load_dataset
load_dataset({str(root)!r}, llff_hold=0)
'''
    env = {**os.environ, 'PYTHONPATH': REPO + os.pathsep + os.environ.get('PYTHONPATH', '')}
    result = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == -signal.SIGKILL, result.stderr


def test_a_crash_mid_write_leaves_no_cache_that_is_reused(tmp_path, monkeypatch):
    lens_keys, model, distortion = LENSES['nerfstudio OPENCV']
    write_capture(tmp_path, lens_keys, model, distortion)
    cache = tmp_path / 'transforms_undistorted'
    partial = tmp_path / 'transforms_undistorted.partial'
    _load_and_die_after_writing(tmp_path, 2)
    assert not cache.exists()
    assert len(list((partial / 'images').iterdir())) == 2   # the half-written cache
    calls = count_warps(monkeypatch)
    ds = load_dataset(tmp_path, llff_hold=0)
    assert len(calls) == 4 and not partial.exists()
    assert all(p.startswith(str(cache)) for p in ds.train.image_paths)

    # A complete cache, then other coefficients and a crash while remaking it: the old cache
    # is stale and is not read; the next load remakes it.
    meta = json.loads((tmp_path / 'transforms.json').read_text())
    meta['k1'] = -0.1
    (tmp_path / 'transforms.json').write_text(json.dumps(meta))
    _load_and_die_after_writing(tmp_path, 3)
    assert partial.exists()
    load_dataset(tmp_path, llff_hold=0)
    assert len(calls) == 8 and not partial.exists()
    index = json.loads((cache / 'cameras.json').read_text())
    assert {e['distorted']['params'][4] for e in index['images'].values()} == {-0.1}


def test_atomic_folder_keeps_the_old_folder_when_writing_fails(tmp_path):
    out = tmp_path / 'cache'
    with atomic_folder(str(out)) as tmp:
        (tmp_path / 'cache.partial' / 'a').write_text('old')
        assert tmp == str(out) + '.partial'
    assert (out / 'a').read_text() == 'old'
    with pytest.raises(RuntimeError):
        with atomic_folder(str(out)) as tmp:
            (tmp_path / 'cache.partial' / 'a').write_text('new')
            raise RuntimeError('interrupted')
    assert (out / 'a').read_text() == 'old' and not (tmp_path / 'cache.partial').exists()


# --- what is not undistorted, and what is refused --------------------------------------------

@pytest.mark.parametrize('lens_keys', [{}, {'camera_model': 'OPENCV', 'k1': 0.0, 'k2': 0.0,
                                            'p1': 0.0, 'p2': 0.0},
                                       {'camera_model': 'PINHOLE'}])
def test_datasets_without_distortion_are_untouched(tmp_path, capsys, lens_keys):
    cams = cameras()
    os.makedirs(tmp_path / 'images')
    pixels = np.random.default_rng(0).integers(0, 256, size=(H, W, 3), dtype=np.uint8)
    for i in range(len(cams)):
        iio.imwrite(tmp_path / 'images' / f'{i:02d}.png', pixels)
    K = cams[0].K
    (tmp_path / 'transforms.json').write_text(json.dumps({
        'fl_x': K[0, 0], 'fl_y': K[1, 1], 'cx': K[0, 2], 'cy': K[1, 2], **lens_keys,
        'frames': [frame(f'images/{i:02d}.png', cam) for i, cam in enumerate(cams)]}))
    ds = load_dataset(tmp_path, llff_hold=0)
    assert 'distortion' not in capsys.readouterr().out
    assert not os.path.exists(tmp_path / 'transforms_undistorted')
    assert ds.train.image_paths == [str(tmp_path / 'images' / f'{i:02d}.png')
                                    for i in range(len(cams))]
    for cam in ds.train.cameras:
        np.testing.assert_allclose(cam.K, K, atol=1e-12)
    np.testing.assert_array_equal(ds.train.images[0], pixels / np.float32(255))


def test_a_fisheye_without_coefficients_is_still_undistorted(tmp_path):
    """OpenCV's fisheye model with k1..k4 = 0 is the equidistant projection r = f theta."""
    _, truth = write_capture(tmp_path, {'camera_model': 'OPENCV_FISHEYE'}, 'OPENCV_FISHEYE',
                             [0.0] * 4)
    ds = load_dataset(tmp_path, llff_hold=0)
    cam = ds.train.cameras[0]
    points, distorted, pinhole = truth[cam.name]
    assert (cam.width, cam.height) == (pinhole.width, pinhole.height) != (W, H)
    world = ds.normalization.to_world_camera(cam)
    local = (points - world.center) @ world.c2w[:3, :3]
    np.testing.assert_allclose(project(world, points)[0], pinhole.img_from_cam(local),
                               atol=1e-8)


@pytest.mark.parametrize('keys, field', [
    ({'camera_model': 'EQUIRECTANGULAR'}, '"camera_model" \'EQUIRECTANGULAR\''),
    ({'camera_model': 'FISHEYE624'}, '"camera_model" \'FISHEYE624\''),
    ({'latlong': True}, '"latlong"'),
    ({'equirectangular': True}, '"equirectangular"'),
    ({'ftheta_p0': 0.1}, '"ftheta_p0"'),
    ({'k1': 0.1, 'k4': 0.01}, '"k4"'),
    ({'is_fisheye': True, 'k1': 0.1, 'p1': 0.01}, '"p1"/"p2"'),
    ({'camera_model': 'OPENCV_FISHEYE', 'p2': 0.01}, '"p1"/"p2"'),
    ({'is_fisheye': 'yes'}, '"is_fisheye"'),
    ({'k1': float('nan')}, 'finite'),
])
def test_unsupported_lenses_name_the_file_and_the_field(tmp_path, keys, field):
    cams = cameras(2)
    os.makedirs(tmp_path / 'images')
    for i in range(2):
        iio.imwrite(tmp_path / 'images' / f'{i}.png', np.zeros((H, W, 3), np.uint8))
    (tmp_path / 'transforms.json').write_text(json.dumps({
        'fl_x': 70.0, **keys, 'frames': [frame(f'images/{i}.png', cam)
                                         for i, cam in enumerate(cams)]}))
    with pytest.raises(DatasetError) as info:
        load_dataset(tmp_path)
    message = str(info.value)
    assert str(tmp_path / 'transforms.json') in message and field in message, message
    assert not os.path.exists(tmp_path / 'transforms_undistorted')


def _write_lens(root, keys, n=2, size=(32, 24)):
    """A transforms.json of ``n`` black ``size`` photos with the lens ``keys``."""
    w, h = size
    os.makedirs(root / 'images', exist_ok=True)
    for i in range(n):
        iio.imwrite(root / 'images' / f'{i}.png', np.zeros((h, w, 3), np.uint8))
    cams = [orbit_camera(2 * np.pi * i / n, 0.2, 3.0, w, h, focal=0.8) for i in range(n)]
    (root / 'transforms.json').write_text(json.dumps({
        'fl_x': 30.0, 'fl_y': 30.0, 'cx': w / 2, 'cy': h / 2, 'w': w, 'h': h, **keys,
        'frames': [frame(f'images/{i}.png', cam) for i, cam in enumerate(cams)]}))


@pytest.mark.parametrize('keys, coefficient', [
    ({'k1': 1e6}, '"k1" = 1e+06'), ({'k1': -1e6}, '"k1" = -1e+06'),
    ({'k1': 1e308}, '"k1" = 1e+308'), ({'p1': 1e6}, '"p1" = 1e+06'),
    ({'camera_model': 'OPENCV_FISHEYE', 'k1': 1e6, 'k2': 1e6, 'k3': 1e6, 'k4': 1e6}, '= 1e+06'),
])
def test_absurd_distortion_is_refused_naming_the_file_the_coefficient_and_the_share(
        tmp_path, keys, coefficient):
    """k1 = 1e6 undistorted a 32x24 photo to a 6x4 crop and trained on it (issue 49, item 1)."""
    _write_lens(tmp_path, keys)
    with pytest.raises(DatasetError) as info:
        load_dataset(tmp_path)
    message = str(info.value)
    assert message.startswith(str(tmp_path / 'transforms.json'))
    assert str(tmp_path / 'images' / '0.png') in message and coefficient in message, message
    share = float(re.search(r'leaves ([\d.]+) % of the photo', message).group(1))
    assert share < 100 * undistort_module.MIN_KEPT_SHARE
    assert not os.path.exists(tmp_path / 'transforms_undistorted')


def test_random_distortion_coefficients_are_trained_on_only_when_enough_of_the_photo_stays(
        tmp_path):
    """Property: for random coefficients (small ones, and one of a magnitude from 1e-4 to 1e8,
    either sign), a dataset either loads, with undistorted images that keep at least
    MIN_KEPT_SHARE of each photo, or is refused in one message naming the file and the share
    kept."""
    rng = np.random.default_rng(49)
    refused = loaded = 0
    for case in range(12):
        names = ['k1', 'k2', 'p1', 'p2'] if case % 2 else ['k1', 'k2', 'k3', 'k4']
        keys = {'camera_model': 'OPENCV' if case % 2 else 'OPENCV_FISHEYE'}
        large = rng.integers(len(names))
        for k, name in enumerate(names):
            keys[name] = float(rng.choice([-1, 1])
                               * 10 ** rng.uniform(-4, 8 if k == large else -2))
        root = tmp_path / f'case{case}'
        _write_lens(root, keys)
        try:
            dataset = load_dataset(root)
        except DatasetError as e:
            assert str(root / 'transforms.json') in str(e) and '% of the photo' in str(e)
            refused += 1
            continue
        loaded += 1
        distorted = pycolmap.Camera(model=keys['camera_model'], width=32, height=24,
                                    params=[30.0, 30.0, 16.0, 12.0] + [keys[n] for n in names])
        pinhole = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), distorted)
        assert undistort_module.kept_share(distorted, pinhole) >= \
            undistort_module.MIN_KEPT_SHARE
        assert dataset.train.cameras[0].width * dataset.train.cameras[0].height >= \
            undistort_module.MIN_KEPT_SHARE * 32 * 24
    assert refused >= 2 and loaded >= 2           # the draws reach both sides


def test_sound_lenses_keep_most_of_the_photo():
    for _, (_, model, distortion) in LENSES.items():
        distorted = colmap_camera(cameras(1)[0].K, model, distortion)
        pinhole = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), distorted)
        assert undistort_module.kept_share(distorted, pinhole) > 0.6, model


@pytest.mark.parametrize('where', ['', '.partial'])
def test_a_file_where_the_undistortion_cache_goes_is_named(tmp_path, where):
    """A file at the cache folder said ".partial: Not a directory" and left the .partial folder
    (issue 49, item 6)."""
    _write_lens(tmp_path, {'k1': -0.1})
    blocker = tmp_path / f'transforms_undistorted{where}'
    blocker.write_text('not a folder')
    with pytest.raises(DatasetError, match=re.escape(f'{blocker}: a file stands where the '
                                                     f'undistorted images are written')):
        load_dataset(tmp_path)
    assert blocker.read_text() == 'not a folder'
    assert sorted(os.listdir(tmp_path)) == sorted(['images', 'transforms.json', blocker.name])
