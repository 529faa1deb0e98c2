"""``transforms.json`` datasets: Blender / NeRF synthetic, instant-ngp and nerfstudio.

Poses (``transform_matrix`` per frame) are camera-to-world in the OpenGL convention (x right,
y up, z backward) and are converted to OpenCV. Intrinsics come from the top level of the file,
overridden per frame where a frame has its own keys:

- focal length: ``fl_x`` / ``fl_y`` in pixels, else ``camera_angle_x`` / ``camera_angle_y``
  (radians, full field of view); fy defaults to fx;
- principal point: ``cx`` / ``cy``, default the image centre;
- ``w`` / ``h``: the image size, checked against the image when given;
- lens distortion, as nerfstudio and instant-ngp write it: ``camera_model`` ``OPENCV`` (or
  none, or another perspective model: ``k1 k2 p1 p2`` and optionally ``k3``, OpenCV's
  ``(1 + k1 r^2 + k2 r^4 + k3 r^6)`` radial and ``p1 p2`` tangential terms) or
  ``OPENCV_FISHEYE`` (or instant-ngp's ``"is_fisheye": true``: ``k1 k2 k3 k4`` of OpenCV's
  fisheye model). Frames with distortion are undistorted to pinhole cameras once, with
  COLMAP (pycolmap), into ``<json stem>_undistorted/`` next to the JSON file, which is read
  from then on while it is newer than the JSON and the images (see
  :mod:`mi_nerfpp.data.undistort`); an info line says so. Projections that are no lens
  distortion of a perspective or fisheye camera (``EQUIRECTANGULAR``, ``FISHEYE624``,
  instant-ngp's ``latlong`` / ``equirectangular`` / ``ftheta_p0``) are refused.

Splits come from ``transforms_{train,val,test}.json`` when ``transforms_train.json`` exists
(the Blender layout); otherwise a single ``transforms.json`` is split by holding out every
``llff_hold``-th frame (by sorted file path) as the test split. ``file_path`` is relative to the
JSON file and may lack its extension (``.png`` is tried). Frames whose image is missing are
skipped with a warning. A frame's ``mask_path`` (nerfstudio's key, relative to the JSON file)
names its mask (:mod:`mi_nerfpp.data.masks`); masks of distorted frames are undistorted with
their images, under ``masks/`` in the cache.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import warnings

import numpy as np

from mi_nerfpp.data import masks
from mi_nerfpp.data.cameras import opengl_to_opencv
from mi_nerfpp.data.colmap import ColmapCamera
from mi_nerfpp.data.dataset import Dataset, Frame, make_dataset, make_splits
from mi_nerfpp.data.errors import DatasetError
from mi_nerfpp.data.images import image_size
from mi_nerfpp.data.undistort import CACHE_INDEX, View, undistort_views
from mi_nerfpp.files.readers import read_json

SPLIT_FILES = {'train': 'transforms_train.json', 'validation': 'transforms_val.json',
               'test': 'transforms_test.json'}
SINGLE_FILE = 'transforms.json'
DISTORTION_KEYS = ('k1', 'k2', 'k3', 'k4', 'p1', 'p2')
NUMERIC_KEYS = ('fl_x', 'fl_y', 'cx', 'cy', 'w', 'h', 'camera_angle_x', 'camera_angle_y',
                *DISTORTION_KEYS)
# nerfstudio camera models that are pinhole up to lens distortion (OpenCV's k1 k2 k3 p1 p2).
PINHOLE_MODELS = ('PINHOLE', 'SIMPLE_PINHOLE', 'OPENCV', 'SIMPLE_RADIAL', 'RADIAL')
# ... and the fisheye one (OpenCV's fisheye model, k1 k2 k3 k4).
FISHEYE_MODEL = 'OPENCV_FISHEYE'
# instant-ngp's keys of projections that are no lens distortion.
OTHER_PROJECTION_KEYS = ('latlong', 'equirectangular', 'ftheta_p0')
# The cache of undistorted images of JSON file ``F.json``: ``F`` + this, next to it.
UNDISTORTED_SUFFIX = '_undistorted'


def is_transforms(path) -> bool:
    """Whether ``path`` is a transforms JSON file or a folder holding one."""
    if os.path.isfile(path):
        return os.path.basename(path).startswith('transforms') and path.endswith('.json')
    return any(os.path.isfile(os.path.join(path, name))
               for name in (SPLIT_FILES['train'], SINGLE_FILE))


def read_transforms(path, downscale: int | None = 1, background=(1.0, 1.0, 1.0),
                    llff_hold: int = 8) -> Dataset:
    """Read a ``transforms.json`` dataset (see the module docstring).

    Args:
        path: the dataset folder, or one of its transforms JSON files.
        downscale: integer factor to shrink images by (area averaging); intrinsics follow.
        background: RGB colour transparent pixels are composited over (Blender's synthetic
            scenes are RGBA).
        llff_hold: with a single ``transforms.json``, every ``llff_hold``-th frame is held out
            as test (0: no test split).

    Raises:
        DatasetError: missing or malformed JSON, bad poses or intrinsics, bad images, no train
            images left.
    """
    path = os.fspath(path)
    if os.path.isfile(path):
        folder, single_file = os.path.dirname(path), path
        split_layout = os.path.basename(path) in SPLIT_FILES.values()
    else:
        folder, single_file = path, os.path.join(path, SINGLE_FILE)
        split_layout = os.path.isfile(os.path.join(folder, SPLIT_FILES['train']))
    if split_layout:
        train_source = os.path.join(folder, SPLIT_FILES['train'])
        if not os.path.isfile(train_source):
            raise DatasetError(f'{train_source}: missing; the split layout needs the train file')
        frames = {name: _read_frames(os.path.join(folder, file))
                  if os.path.isfile(os.path.join(folder, file)) else []
                  for name, file in SPLIT_FILES.items()}
    elif os.path.isfile(single_file):
        everything = _read_frames(single_file, sort=True)
        held_out = set(range(0, len(everything), llff_hold)) if llff_hold > 0 else set()
        frames = {'train': [f for i, f in enumerate(everything) if i not in held_out],
                  'validation': [],
                  'test': [f for i, f in enumerate(everything) if i in held_out]}
        train_source = single_file
    else:
        raise DatasetError(f'{path}: found neither {SPLIT_FILES["train"]} nor {SINGLE_FILE}')
    splits, downscale = make_splits(frames, downscale, background)
    return make_dataset('blender', folder, **splits, train_source=train_source,
                        downscale=downscale)


def _read_frames(json_path: str, sort: bool = False) -> list[Frame]:
    """Frames of one transforms JSON file whose images exist (sorted by image path if
    ``sort``), those with lens distortion undistorted."""
    meta = read_json(json_path, what='JSON cameras file', remedy='fix the file or export the '
                     'dataset again', expect=None, error=DatasetError)
    if not isinstance(meta, dict) or not isinstance(meta.get('frames'), list):
        raise DatasetError(f'{json_path}: expected an object with a "frames" list')
    shared = _camera_params(meta, json_path)
    folder = os.path.dirname(json_path)
    frames, missing = [], []    # frames: (Frame, its lens or None)
    for i, entry in enumerate(meta['frames']):
        source = f'{json_path} (frame {i})'
        if not isinstance(entry, dict) or 'file_path' not in entry \
                or 'transform_matrix' not in entry:
            raise DatasetError(f'{source}: every frame needs "file_path" and "transform_matrix"')
        image_path = _find_image(folder, str(entry['file_path']))
        if image_path is None:
            missing.append(str(entry['file_path']))
            continue
        params = {**shared, **_camera_params(entry, source)}
        mask_path = _mask_path(folder, entry, source)
        size = (int(params['w']), int(params['h'])) if 'w' in params and 'h' in params else None
        frames.append((Frame(
            image_path=image_path,
            c2w=opengl_to_opencv(_pose_matrix(entry['transform_matrix'], source)),
            intrinsics=functools.partial(_intrinsics, params, source),
            source=source,
            name=os.path.splitext(os.path.basename(image_path))[0],
            size=size, mask_path=mask_path), _lens(params, source)))
    if missing:
        warnings.warn(f'{json_path}: skipped {len(missing)} of {len(meta["frames"])} frames '
                      f'whose image is missing (first: {missing[0]!r})', stacklevel=3)
    if sort:
        frames.sort(key=lambda pair: pair[0].image_path)
    if any(lens is not None for _, lens in frames):
        return _undistorted(json_path, frames)
    return [frame for frame, _ in frames]


def _lens(params: dict, source: str) -> tuple[str, list[float]] | None:
    """The COLMAP camera model and distortion parameters of a frame's lens, or None for a
    pinhole (see the module docstring)."""
    k1, k2, k3, k4, p1, p2 = (params.get(key, 0.0) for key in DISTORTION_KEYS)
    if not np.all(np.isfinite([k1, k2, k3, k4, p1, p2])):
        raise DatasetError(f'{source}: distortion coefficients must be finite, got '
                           f'{dict(zip(DISTORTION_KEYS, (k1, k2, k3, k4, p1, p2)))}')
    if params.get('camera_model') == FISHEYE_MODEL or params.get('is_fisheye', False):
        if p1 != 0.0 or p2 != 0.0:
            raise DatasetError(f'{source}: "p1"/"p2" (tangential distortion) are given for a '
                               f'fisheye camera ({FISHEYE_MODEL} or "is_fisheye"), whose '
                               f'OpenCV model has none: remove them or fix the camera model')
        return 'OPENCV_FISHEYE', [k1, k2, k3, k4]     # a fisheye even when all are 0
    if k4 != 0.0:
        raise DatasetError(f'{source}: "k4" = {k4:g} is given for a perspective camera: '
                           f'OpenCV\'s (and COLMAP\'s) perspective models have radial terms '
                           f'k1 k2 k3 only; for a fisheye set "camera_model": "{FISHEYE_MODEL}" '
                           f'(or "is_fisheye": true)')
    if k1 == k2 == k3 == p1 == p2 == 0.0:
        return None
    if k3 != 0.0:
        return 'FULL_OPENCV', [k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
    return 'OPENCV', [k1, k2, p1, p2]


def _undistorted(json_path: str, frames: list[tuple[Frame, tuple | None]]) -> list[Frame]:
    """The frames, those with a lens (COLMAP model and distortion, see :func:`_lens`) replaced
    by their undistorted images and pinhole cameras (see
    :func:`mi_nerfpp.data.undistort.undistort_views`)."""
    folder = os.path.dirname(os.path.abspath(json_path))
    out = os.path.join(folder, os.path.splitext(os.path.basename(json_path))[0]
                       + UNDISTORTED_SUFFIX)
    distorted = [(frame, lens) for frame, lens in frames if lens is not None]
    views = []
    for frame, (model, distortion) in distorted:
        width, height = image_size(frame.image_path)
        if frame.size is not None and tuple(frame.size) != (width, height):
            raise DatasetError(
                f'{frame.image_path}: image is {width}x{height} but {frame.source} declares '
                f'{frame.size[0]}x{frame.size[1]}: fix the metadata or resize the image')
        K = frame.intrinsics(width, height)
        camera = ColmapCamera(0, model, width, height,
                              np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *distortion]))
        views.append(View(frame.image_path, _cache_name(frame.image_path, folder), camera))
        if frame.mask_path is not None:     # undistorted the same way, under masks/
            views.append(View(frame.mask_path, os.path.join(
                masks.FOLDER, _cache_name(frame.mask_path, folder)), camera))
    pinholes = iter(undistort_views(views, out, sources=[json_path], what=json_path))
    index = os.path.join(out, CACHE_INDEX)
    result = []
    for frame, lens in frames:
        if lens is not None:
            pinhole = next(pinholes)
            mask = next(pinholes).image_path if frame.mask_path is not None else None
            frame = dataclasses.replace(
                frame, image_path=pinhole.image_path, mask_path=mask,
                intrinsics=lambda width, height, K=pinhole.K: K,
                size=(pinhole.width, pinhole.height),
                intrinsics_source=f'{index} (undistorted from {frame.source})')
        result.append(frame)
    return result


def _cache_name(image_path: str, folder: str) -> str:
    """Where an image goes in the undistortion cache: its path relative to the JSON file
    (``..`` spelled ``__parent__``), as PNG (EXR stays EXR)."""
    relative = os.path.relpath(os.path.abspath(image_path), folder)
    parts = ['__parent__' if part == os.pardir else part
             for part in relative.split(os.sep) if part not in ('', os.curdir)]
    stem, ext = os.path.splitext(os.path.join(*parts))
    return stem + ('.exr' if ext.lower() == '.exr' else '.png')


def _camera_params(entry: dict, source: str) -> dict:
    """The intrinsics keys of a JSON object, numbers as floats, with ``camera_model`` and
    ``is_fisheye`` when given; refuses projections other than perspective and fisheye."""
    model = entry.get('camera_model')
    if model is not None and model not in (*PINHOLE_MODELS, FISHEYE_MODEL):
        raise DatasetError(f'{source}: "camera_model" {model!r} is not supported: mi-nerfpp '
                           f'reads perspective ({", ".join(PINHOLE_MODELS)}) and fisheye '
                           f'({FISHEYE_MODEL}) cameras; convert the images to perspective views '
                           f'first')
    for key in OTHER_PROJECTION_KEYS:
        if key in entry:
            raise DatasetError(f'{source}: "{key}" (an instant-ngp projection that is no lens '
                               f'distortion) is not supported: mi-nerfpp reads perspective and '
                               f'OpenCV fisheye cameras; convert the images to perspective '
                               f'views first')
    params = {}
    for key in NUMERIC_KEYS:
        if key in entry:
            try:
                params[key] = float(entry[key])
            except (TypeError, ValueError, OverflowError):
                shown = json.dumps(entry[key])
                shown = shown if len(shown) <= 40 else shown[:37] + '...'
                raise DatasetError(f'{source}: intrinsics must be numbers: "{key}" is '
                                   f'{shown}') from None
    if model is not None:
        params['camera_model'] = model
    if 'is_fisheye' in entry:
        if not isinstance(entry['is_fisheye'], bool):
            raise DatasetError(f'{source}: "is_fisheye" must be true or false, got '
                               f'{entry["is_fisheye"]!r}')
        params['is_fisheye'] = entry['is_fisheye']
    return params


def _mask_path(folder: str, entry: dict, source: str) -> str | None:
    """The mask a frame's ``mask_path`` names (nerfstudio's key, relative to the JSON file),
    None if it has none."""
    if entry.get('mask_path') is None:
        return None
    path = os.path.normpath(os.path.join(folder, str(entry['mask_path'])))
    if not os.path.isfile(path):
        raise DatasetError(f'{path}: the mask that {source} names ("mask_path") is missing: '
                           f'put it there or remove "mask_path" from the frame')
    return path


def _find_image(folder: str, file_path: str) -> str | None:
    """The image a frame's ``file_path`` names, trying ``.png`` for extension-less paths."""
    path = os.path.normpath(os.path.join(folder, file_path))
    for candidate in (path, path + '.png'):
        if os.path.isfile(candidate):
            return candidate
    return None


def _pose_matrix(value, source: str) -> np.ndarray:
    """4x4 matrix of a ``transform_matrix`` (a 3x4 one gets the row 0 0 0 1)."""
    try:
        matrix = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise DatasetError(f'{source}: transform_matrix must be a 4x4 (or 3x4) matrix of '
                           f'numbers') from None
    if matrix.shape == (3, 4):
        matrix = np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])
    if matrix.shape != (4, 4):
        raise DatasetError(f'{source}: transform_matrix must be 4x4, got shape {matrix.shape}')
    return matrix


def _intrinsics(params: dict, source: str, width: int, height: int) -> np.ndarray:
    """3x3 K from the intrinsics keys and the image size."""
    for key in ('camera_angle_x', 'camera_angle_y'):
        if key in params and not 0 < params[key] < math.pi:
            raise DatasetError(f'{source}: "{key}" is {params[key]:g}: a field of view in '
                               f'radians, more than 0 and less than pi (e.g. 0.69 for 40 '
                               f'degrees)')
    if 'fl_x' in params:
        fx = params['fl_x']
    elif 'camera_angle_x' in params:
        fx = 0.5 * width / math.tan(0.5 * params['camera_angle_x'])
    else:
        raise DatasetError(f'{source}: no focal length; give "fl_x" (pixels) or '
                           f'"camera_angle_x" (radians)')
    if 'fl_y' in params:
        fy = params['fl_y']
    elif 'camera_angle_y' in params:
        fy = 0.5 * height / math.tan(0.5 * params['camera_angle_y'])
    else:
        fy = fx
    return np.array([[fx, 0.0, params.get('cx', 0.5 * width)],
                     [0.0, fy, params.get('cy', 0.5 * height)],
                     [0.0, 0.0, 1.0]])
