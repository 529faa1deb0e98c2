"""Datasets: a bad file or value is refused with one line naming the file (and the frame or
camera), before anything is written to the run folder."""
import json
import struct

import numpy as np
import pytest
from PIL import Image

from mi_nerfpp.data import DatasetError, load_dataset
from mi_nerfpp.data.images import read_image
from tests.robustness.common import TINY, one_clear_line, run_cli


def transforms(root, views=3, **top):
    """A tiny transforms.json dataset (camera_angle_x 0.8 unless given), 8x6 images, cameras
    along x at distance 3; returns the folder and the JSON (to edit and write again)."""
    root.mkdir(parents=True)
    frames = []
    for i in range(views):
        Image.fromarray(np.full((6, 8, 3), 100 + 20 * i, np.uint8)).save(root / f'{i}.png')
        pose = np.eye(4)
        pose[:3, 3] = [i, 0, 3]
        frames.append({'file_path': f'{i}.png', 'transform_matrix': pose.tolist()})
    meta = dict({'camera_angle_x': 0.8}, **top, frames=frames)
    (root / 'transforms.json').write_text(json.dumps(meta))
    return root, meta


def refused(capsys, tmp_path, data):
    """Optimize on ``data``: the one line after ``error: optimize: ``; nothing is written."""
    status, _, err = run_cli(capsys, 'optimize', data, '--out', tmp_path / 'run', *TINY)
    line = one_clear_line(err)
    assert status == 1 and line.startswith('error: optimize: '), line
    assert not (tmp_path / 'run').exists()
    return line[len('error: optimize: '):]


@pytest.mark.parametrize('angle', [0, -0.5, np.pi, 4.0])
def test_a_field_of_view_outside_0_to_pi_is_refused(capsys, tmp_path, angle):
    """camera_angle_x 0 was a ZeroDivisionError traceback; pi and more trained on a focal
    length of nearly 0."""
    data, _ = transforms(tmp_path / 'data', camera_angle_x=angle)
    assert refused(capsys, tmp_path, data) == (
        f'{data / "transforms.json"} (frame 1): "camera_angle_x" is {angle:g}: a field of view '
        f'in radians, more than 0 and less than pi (e.g. 0.69 for 40 degrees)')


def test_a_nan_field_of_view_is_refused(capsys, tmp_path):
    data, _ = transforms(tmp_path / 'data', camera_angle_y=float('nan'))
    assert '"camera_angle_y" is nan: a field of view in radians' in refused(capsys, tmp_path,
                                                                            data)


def colmap(root, width, height, binary=False):
    """A tiny COLMAP text (or binary) model of one PINHOLE camera of ``width`` x ``height`` and
    three images of 8x6 pixels."""
    (root / 'sparse' / '0').mkdir(parents=True)
    (root / 'images').mkdir()
    for i in range(3):
        Image.fromarray(np.full((6, 8, 3), 100, np.uint8)).save(root / 'images' / f'{i}.png')
    model = root / 'sparse' / '0'
    if not binary:
        (model / 'cameras.txt').write_text(f'1 PINHOLE {width} {height} 10 10 4 3\n')
        (model / 'images.txt').write_text(''.join(f'{i + 1} 1 0 0 0 {i} 0 3 1 {i}.png\n\n'
                                                  for i in range(3)))
        return root
    with open(model / 'cameras.bin', 'wb') as f:
        f.write(struct.pack('<Q', 1) + struct.pack('<iiQQ', 1, 1, width, height)
                + struct.pack('<4d', 10, 10, 4, 3))
    with open(model / 'images.bin', 'wb') as f:
        f.write(struct.pack('<Q', 3))
        for i in range(3):
            f.write(struct.pack('<idddddddi', i + 1, 1, 0, 0, 0, i, 0, 3, 1)
                    + f'{i}.png'.encode() + b'\0' + struct.pack('<Q', 0))
    return root


@pytest.mark.parametrize('binary', [False, True])
def test_a_colmap_camera_of_size_0x0_is_refused(capsys, tmp_path, binary):
    """Was a ZeroDivisionError traceback."""
    data = colmap(tmp_path / 'data', 0, 0, binary)
    where = (f'{data / "sparse/0/cameras.bin"}' if binary else
             f'{data / "sparse/0/cameras.txt"}:1')
    assert refused(capsys, tmp_path, data) == (
        f'{where}: camera 1 (PINHOLE) is 0x0 pixels: a camera needs a positive width and '
        f'height; re-export the model with COLMAP')


def test_a_colmap_camera_of_the_right_size_reads(tmp_path):
    data = colmap(tmp_path / 'data', 8, 6, binary=True)
    assert len(load_dataset(str(data), downscale=1).train) > 0


@pytest.mark.parametrize('where, shown', [(1e30, '1e+30'), (1e308, '1e+308'),
                                          (np.inf, None)])
def test_a_camera_too_far_to_normalize_is_refused_naming_its_frame(capsys, tmp_path, where,
                                                                   shown):
    """A camera at 1e30 trained and died in evaluation with Mitsuba's near_clip/far_clip
    text; 1e308 said 'normalization scale must be positive' without the pose file."""
    data, meta = transforms(tmp_path / 'data')
    meta['frames'][1]['transform_matrix'][0][3] = where
    (data / 'transforms.json').write_text(json.dumps(meta))
    line = refused(capsys, tmp_path, data)
    if shown is None:                      # inf: the pose check names non-finite values
        assert line == (f'{data / "transforms.json"} (frame 1): camera pose has non-finite '
                        f'values (NaN or inf): remove this camera or fix its pose')
        return
    assert line == (f'{data / "transforms.json"} (frame 1): the camera is {shown} world units '
                    f'from the origin, beyond 1e+12, where positions cannot be normalized in '
                    f'floating point: fix this pose or remove the camera')


def test_a_camera_far_off_the_others_is_refused_naming_its_frame(capsys, tmp_path):
    """One camera at 1e9 would squeeze the others into a 1e-9 of the unit sphere."""
    data, meta = transforms(tmp_path / 'data', views=4)
    meta['frames'][2]['transform_matrix'][1][3] = 1e9
    (data / 'transforms.json').write_text(json.dumps(meta))
    line = refused(capsys, tmp_path, data)
    assert line.startswith(f'{data / "transforms.json"} (frame 2): the camera is 1e+09 world '
                           f'units from the middle of the capture, ')
    assert line.endswith('times the typical camera (1.5): a wrong pose? It would squeeze the '
                         'other cameras into a speck of the unit sphere; fix this pose or '
                         'remove the camera')


def test_cameras_spread_within_the_limit_read(tmp_path):
    data, meta = transforms(tmp_path / 'data', views=4)
    meta['frames'][2]['transform_matrix'][1][3] = 500.0      # 333 x the typical distance
    (data / 'transforms.json').write_text(json.dumps(meta))
    assert len(load_dataset(str(data), downscale=1).train) > 0


# ----------------------------------------------------------------------------- images, poses

def test_jpg_exif_orientation_is_applied(tmp_path):
    pixels = np.zeros((8, 12, 3), np.uint8)
    pixels[:4, :6] = 255                                # a white top-left quadrant
    image = Image.fromarray(pixels)
    exif = image.getexif()
    exif[0x0112] = 3                                    # orientation 3: rotated 180 degrees
    image.save(tmp_path / 'x.jpg', exif=exif, quality=100)
    read = read_image(tmp_path / 'x.jpg')
    assert read.shape == (8, 12, 3)
    assert read[6, 9].min() > 0.9 and read[1, 1].max() < 0.1     # now bottom-right


def test_nan_pixel_in_a_training_exr_names_the_file(tmp_path):
    channels = {c: np.full((4, 5), 0.5, np.float32) for c in 'RGB'}
    channels['G'][2, 3] = np.nan
    path = tmp_path / 'img.exr'
    import OpenEXR
    with OpenEXR.File({'type': OpenEXR.scanlineimage}, channels) as f:   # write_exr refuses NaN
        f.write(str(path))
    with pytest.raises(DatasetError, match=r'img\.exr: 1 pixel\(s\) are NaN or infinite '
                                           r'\(the first at x=3, y=2\)'):
        read_image(path)


def _llff(root, poses, size=(6, 4)):
    (root / 'images').mkdir(parents=True)
    for i in range(len(poses) if hasattr(poses, '__len__') else 2):
        Image.fromarray(np.full((size[1], size[0], 3), 128, np.uint8)).save(
            root / 'images' / f'{i:03d}.png')


def test_garbage_poses_bounds_gets_a_clear_message(capsys, tmp_path):
    data = tmp_path / 'llff'
    _llff(data, [0, 1])
    (data / 'poses_bounds.npy').write_bytes(b'this is not numpy at all' * 10)
    with pytest.raises(DatasetError, match='not a NumPy array file .*N x 17 float array'):
        load_dataset(str(data))
    np.save(data / 'poses_bounds.npy', np.array([{'a': 1}], dtype=object), allow_pickle=True)
    status, _, err = run_cli(capsys, 'optimize', data, '--out', tmp_path / 'run', *TINY)
    assert status == 1 and 'poses_bounds.npy: not a NumPy array file' in one_clear_line(err)


def test_one_pixel_images_are_refused_before_training(tmp_path):
    data = tmp_path / 'llff'
    poses = np.zeros((2, 17))
    for i in range(2):
        pose = np.zeros((3, 5))
        pose[:, :3] = np.eye(3)
        pose[:, 3] = [i, 0, 0]
        pose[:, 4] = [1, 1, 1.0]
        poses[i, :15] = pose.ravel()
    _llff(data, poses, size=(1, 1))
    np.save(data / 'poses_bounds.npy', poses)
    with pytest.raises(DatasetError, match='image is 1x1 pixels.* at least 3x3'):
        load_dataset(str(data))
