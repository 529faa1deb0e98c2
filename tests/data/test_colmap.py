"""COLMAP models as a dataset format: models written by pycolmap (binary and text), read by
mi_nerfpp.data.colmap, checked against the camera conventions of mi_nerfpp.data.cameras,
pycolmap's own projection and Mitsuba's sensor rays."""
import os
import struct

import mi_nerfpp  # noqa: F401  (variant)
import mitsuba as mi
import numpy as np
import pycolmap
import pytest

from mi_nerfpp.data import Camera, DatasetError, detect_format, load_dataset
from mi_nerfpp.data.cameras import mitsuba_sensor_dict, pixel_rays, project
from mi_nerfpp.data.colmap import read_model
from mi_nerfpp.data.images import write_encoded_png
from tests.helpers import orbit_camera

W, H = 48, 36
POINTS = np.array([[0.1, 0.2, -0.1], [-0.3, 0.0, 0.25], [0.2, -0.15, 0.3]])


def ground_truth_cameras(n=10):
    cams = [orbit_camera(2 * np.pi * i / n, 0.3 + 0.05 * (i % 3), 3.0 + 0.1 * i, W, H)
            for i in range(n)]
    for i, cam in enumerate(cams):
        cam.name = f'img_{i:02d}'
        cam.K[0, 2] += 1.5   # off-centre principal point: catches half-pixel mix-ups
        cam.K[1, 2] -= 0.75
    return cams


def write_colmap(root, cams, model='SIMPLE_PINHOLE', extra=(), fmt='bin', images=True):
    """A COLMAP dataset at ``root``: one camera of ``model`` shared by ``cams`` (their K),
    their poses, POINTS, and textured images; written by pycolmap."""
    K = cams[0].K
    intrinsics = {'SIMPLE_PINHOLE': [K[0, 0], K[0, 2], K[1, 2]],
                  'PINHOLE': [K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
                  'SIMPLE_RADIAL': [K[0, 0], K[0, 2], K[1, 2]],
                  'OPENCV': [K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
                  'OPENCV_FISHEYE': [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]}[model]
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(
        model=model, width=W, height=H, params=intrinsics + list(extra), camera_id=1))
    rng = np.random.default_rng(0)
    for i, cam in enumerate(cams):
        image = pycolmap.Image(name=cam.name + '.png', camera_id=1, image_id=i + 1,
                               keypoints=rng.uniform(0, W, size=(5, 2)))
        w2c = np.linalg.inv(cam.c2w)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c[:3, :4]))
    for p in POINTS:
        rec.add_point3D(p, pycolmap.Track())
    sparse = os.path.join(root, 'sparse', '0')
    os.makedirs(sparse)
    (rec.write_binary if fmt == 'bin' else rec.write_text)(sparse)
    if images:
        os.makedirs(os.path.join(root, 'images'))
        for cam in cams:
            write_encoded_png(os.path.join(root, 'images', cam.name + '.png'),
                      rng.uniform(0, 1, size=(H, W, 3)))
    return rec


@pytest.mark.parametrize('fmt', ['bin', 'txt'])
def test_round_trip_of_pycolmap_models(tmp_path, fmt):
    cams = ground_truth_cameras()
    rec = write_colmap(tmp_path, cams, 'PINHOLE', fmt=fmt, images=False)
    assert os.path.isfile(tmp_path / 'sparse' / '0' / f'images.{fmt}')
    model = read_model(tmp_path / 'sparse' / '0')
    assert len(model.images) == len(cams) and list(model.cameras) == [1]
    camera = model.cameras[1]
    assert camera.model == 'PINHOLE' and (camera.width, camera.height) == (W, H)
    assert camera.is_pinhole
    np.testing.assert_allclose(camera.K, cams[0].K, atol=1e-12)
    np.testing.assert_allclose(model.points, POINTS, atol=1e-12)
    for image in model.images.values():
        truth = cams[image.image_id - 1]
        assert image.name == truth.name + '.png'
        np.testing.assert_allclose(image.c2w, truth.c2w, atol=1e-9)
        # Our camera projects world points where pycolmap's own model does.
        ours = Camera(camera.K, image.c2w, W, H)
        theirs = rec.images[image.image_id]
        for p in POINTS:
            np.testing.assert_allclose(project(ours, p)[0][0], theirs.project_point(p),
                                       atol=1e-8)
            np.testing.assert_allclose(ours.center, theirs.projection_center(), atol=1e-9)


def test_colmap_dataset_cameras_match_pycolmap_and_mitsuba_rays(tmp_path):
    cams = ground_truth_cameras(16)
    rec = write_colmap(tmp_path, cams)
    assert detect_format(tmp_path) == 'colmap'
    ds = load_dataset(tmp_path)
    assert ds.format == 'colmap' and ds.downscale == 1
    # Every 8th image (sorted by name) is held out, as for LLFF.
    assert [c.name for c in ds.test.cameras] == ['img_00', 'img_08']
    assert len(ds.train) == 14 and ds.train.images[0].shape == (H, W, 3)
    by_name = {c.name: c for c in cams}
    for split in (ds.train, ds.test):
        for cam in split.cameras:
            world = ds.normalization.to_world_camera(cam)
            np.testing.assert_allclose(world.c2w, by_name[cam.name].c2w, atol=1e-9)
            np.testing.assert_allclose(world.K, by_name[cam.name].K, atol=1e-12)
    # Rays through pixels: pycolmap's camera model, ours, and Mitsuba's sensor agree.
    cam = ds.normalization.to_world_camera(ds.train.cameras[3])
    image = next(im for im in rec.images.values() if im.name == cam.name + '.png')
    px = np.array([0.5, 10.25, 47.5, 30.0])
    py = np.array([0.5, 20.75, 35.5, 3.0])
    R_wc = image.cam_from_world().rotation.matrix().T
    theirs = np.array([R_wc @ np.append(rec.cameras[1].cam_from_img([x, y]), 1.0)
                       for x, y in zip(px, py)])
    theirs /= np.linalg.norm(theirs, axis=1, keepdims=True)
    _, ours = pixel_rays(cam, px, py)
    np.testing.assert_allclose(ours, theirs, atol=1e-9)
    sensor = mi.load_dict(mitsuba_sensor_dict(cam))
    ray, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f(px / W, py / H), mi.Point2f(0.5, 0.5))
    np.testing.assert_allclose(np.array(ray.d, dtype=np.float64).T.reshape(-1, 3), theirs,
                               atol=2e-5)


def test_zero_distortion_is_read_as_pinhole(tmp_path):
    cams = ground_truth_cameras()
    write_colmap(tmp_path, cams, 'SIMPLE_RADIAL', extra=[0.0], fmt='txt')
    ds = load_dataset(tmp_path, llff_hold=0)
    assert not os.path.exists(tmp_path / 'undistorted')
    np.testing.assert_allclose(ds.train.cameras[0].K, cams[0].K, atol=1e-12)


def test_distorted_model_is_undistorted_once(tmp_path, capsys):
    cams = ground_truth_cameras()
    write_colmap(tmp_path, cams, 'OPENCV', extra=[-0.08, 0.02, 0.001, -0.001])
    ds = load_dataset(tmp_path, llff_hold=0)
    assert 'lens distortion' in capsys.readouterr().out
    undistorted = read_model(tmp_path / 'undistorted' / 'sparse')
    assert {c.model for c in undistorted.cameras.values()} == {'PINHOLE'}
    # Undistortion keeps the poses; the images are resampled to the pinhole camera's size.
    by_name = {c.name: c for c in cams}
    first = ds.train.cameras[0]
    assert ds.train.images[0].shape == (first.height, first.width, 3)
    assert ds.train.image_paths[0].startswith(str(tmp_path / 'undistorted' / 'images'))
    for cam in ds.train.cameras:
        world = ds.normalization.to_world_camera(cam)
        np.testing.assert_allclose(world.c2w, by_name[cam.name].c2w, atol=1e-9)
    # A point projects in the undistorted camera where COLMAP's undistorted model puts it.
    pin = undistorted.cameras[1]
    for p in POINTS:
        x = np.linalg.inv(by_name['img_00'].c2w) @ np.append(p, 1.0)
        theirs = pycolmap.Camera(model='PINHOLE', width=pin.width, height=pin.height,
                                 params=pin.params).img_from_cam(x[:3] / x[2])
        ours = project(ds.normalization.to_world_camera(ds.train.cameras[0]), p)[0][0]
        np.testing.assert_allclose(ours, theirs, atol=1e-8)
    stamp = os.path.getmtime(tmp_path / 'undistorted' / 'sparse' / 'cameras.bin')
    load_dataset(tmp_path, llff_hold=0)
    assert 'lens distortion' not in capsys.readouterr().out
    assert os.path.getmtime(tmp_path / 'undistorted' / 'sparse' / 'cameras.bin') == stamp


@pytest.mark.parametrize('model, extra', [('OPENCV_FISHEYE', [0.0] * 4), ('OPENCV_FISHEYE',
                                                                          [0.01, 0, 0, 0])])
def test_fisheye_is_never_read_as_a_pinhole(tmp_path, model, extra):
    """OPENCV_FISHEYE is the equidistant projection r = f theta even with k1..k4 = 0 (it was
    once read as a pinhole then). COLMAP's undistorter takes a fisheye without coefficients for
    undistorted and copies it: that is refused, naming the model and a way out."""
    cams = ground_truth_cameras()
    rec = write_colmap(tmp_path, cams, model, extra=extra)
    camera = read_model(tmp_path / 'sparse' / '0').cameras[1]
    assert not camera.is_pinhole
    if not any(extra):
        assert camera.is_bare_fisheye
        with pytest.raises(DatasetError, match=r'sparse/0: cameras 1 \(OPENCV_FISHEYE\) are '
                                               r'fisheyes without distortion coefficients'):
            load_dataset(tmp_path)
        return
    ds = load_dataset(tmp_path, llff_hold=0)
    pinhole = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), rec.cameras[1])
    by_name = {c.name: c for c in cams}
    for cam in ds.train.cameras:
        world = ds.normalization.to_world_camera(cam)
        w2c = np.linalg.inv(by_name[cam.name].c2w)
        np.testing.assert_allclose(project(world, POINTS)[0],
                                   pinhole.img_from_cam(POINTS @ w2c[:3, :3].T + w2c[:3, 3]),
                                   atol=1e-8)


def test_errors_name_the_file_and_the_fix(tmp_path):
    cams = ground_truth_cameras()
    write_colmap(tmp_path, cams)
    os.remove(tmp_path / 'images' / 'img_03.png')
    with pytest.raises(DatasetError, match=r'img_03\.png.*missing.*put the images'):
        load_dataset(tmp_path)
    # An unknown camera model id in cameras.bin.
    bad = tmp_path / 'sparse' / '0' / 'cameras.bin'
    data = bytearray(bad.read_bytes())
    struct.pack_into('<i', data, 12, 99)  # count (8 bytes), camera_id (4), model_id
    bad.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r'cameras\.bin: camera 1 has unknown camera model '
                                           r'id 99'):
        load_dataset(tmp_path)
    # Images resized to another aspect ratio than the model's camera.
    other = tmp_path / 'other'
    write_colmap(other, cams)
    write_encoded_png(other / 'images' / 'img_01.png', np.zeros((H, W + 10, 3)))
    with pytest.raises(DatasetError, match=r'img_01\.png: image is 58x36 but its COLMAP camera '
                                           r'1 is 48x36'):
        load_dataset(other)
    empty = tmp_path / 'empty'
    os.makedirs(empty / 'sparse' / '0')
    (empty / 'sparse' / '0' / 'cameras.txt').write_text('# no cameras\n')
    (empty / 'sparse' / '0' / 'images.txt').write_text('# no images\n')
    os.makedirs(empty / 'images')
    with pytest.raises(DatasetError, match='no registered images'):
        load_dataset(empty)
