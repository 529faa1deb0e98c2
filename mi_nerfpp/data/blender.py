"""``transforms.json`` datasets: Blender / NeRF synthetic, instant-ngp and nerfstudio.

Poses (``transform_matrix`` per frame) are camera-to-world in the OpenGL convention (x right,
y up, z backward) and are converted to OpenCV. Intrinsics come from the top level of the file,
overridden per frame where a frame has its own keys:

- focal length: ``fl_x`` / ``fl_y`` in pixels, else ``camera_angle_x`` / ``camera_angle_y``
  (radians, full field of view); fy defaults to fx;
- principal point: ``cx`` / ``cy``, default the image centre;
- ``w`` / ``h``: the image size, checked against the image when given;
- distortion (``k1 k2 k3 k4 p1 p2``) is ignored with a warning.

Splits come from ``transforms_{train,val,test}.json`` when ``transforms_train.json`` exists
(the Blender layout); otherwise a single ``transforms.json`` is split by holding out every
``llff_hold``-th frame (by sorted file path) as the test split. ``file_path`` is relative to the
JSON file and may lack its extension (``.png`` is tried). Frames whose image is missing are
skipped with a warning.
"""
from __future__ import annotations

import functools
import json
import math
import os
import warnings

import numpy as np

from .cameras import opengl_to_opencv
from .dataset import Dataset, Frame, make_dataset, make_splits
from .errors import DatasetError

SPLIT_FILES = {'train': 'transforms_train.json', 'validation': 'transforms_val.json',
               'test': 'transforms_test.json'}
SINGLE_FILE = 'transforms.json'
DISTORTION_KEYS = ('k1', 'k2', 'k3', 'k4', 'p1', 'p2')
NUMERIC_KEYS = ('fl_x', 'fl_y', 'cx', 'cy', 'w', 'h', 'camera_angle_x', 'camera_angle_y',
                *DISTORTION_KEYS)
# nerfstudio camera models that are pinhole up to lens distortion.
PINHOLE_MODELS = ('PINHOLE', 'SIMPLE_PINHOLE', 'OPENCV', 'SIMPLE_RADIAL', 'RADIAL')


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
        everything = sorted(_read_frames(single_file), key=lambda frame: frame.image_path)
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


def _read_frames(json_path: str) -> list[Frame]:
    """Frames of one transforms JSON file whose images exist."""
    try:
        with open(json_path) as f:
            meta = json.load(f)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DatasetError(f'{json_path}: cannot read JSON ({e})') from e
    if not isinstance(meta, dict) or not isinstance(meta.get('frames'), list):
        raise DatasetError(f'{json_path}: expected an object with a "frames" list')
    shared = _camera_params(meta, json_path)
    folder = os.path.dirname(json_path)
    frames, missing, distorted = [], [], False
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
        distorted |= any(params.get(k, 0.0) != 0.0 for k in DISTORTION_KEYS)
        size = (int(params['w']), int(params['h'])) if 'w' in params and 'h' in params else None
        frames.append(Frame(
            image_path=image_path,
            c2w=opengl_to_opencv(_pose_matrix(entry['transform_matrix'], source)),
            intrinsics=functools.partial(_intrinsics, params, source),
            source=source,
            name=os.path.splitext(os.path.basename(image_path))[0],
            size=size))
    if missing:
        warnings.warn(f'{json_path}: skipped {len(missing)} of {len(meta["frames"])} frames '
                      f'whose image is missing (first: {missing[0]!r})', stacklevel=3)
    if distorted:
        warnings.warn(f'{json_path}: lens distortion ({", ".join(DISTORTION_KEYS)}) is ignored; '
                      f'undistort the images first (e.g. COLMAP image_undistorter) for accurate '
                      f'results', stacklevel=3)
    return frames


def _camera_params(entry: dict, source: str) -> dict:
    """The intrinsics keys of a JSON object, numbers as floats; checks ``camera_model``."""
    model = entry.get('camera_model')
    if model is not None and model not in PINHOLE_MODELS:
        raise DatasetError(f'{source}: camera_model {model!r} is not supported (only pinhole '
                           f'models {PINHOLE_MODELS}); undistort the images to a pinhole camera')
    try:
        return {k: float(entry[k]) for k in NUMERIC_KEYS if k in entry}
    except (TypeError, ValueError) as e:
        raise DatasetError(f'{source}: intrinsics must be numbers ({e})') from e


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
    except (TypeError, ValueError) as e:
        raise DatasetError(f'{source}: transform_matrix is not a numeric matrix ({e})') from e
    if matrix.shape == (3, 4):
        matrix = np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])
    if matrix.shape != (4, 4):
        raise DatasetError(f'{source}: transform_matrix must be 4x4, got shape {matrix.shape}')
    return matrix


def _intrinsics(params: dict, source: str, width: int, height: int) -> np.ndarray:
    """3x3 K from the intrinsics keys and the image size."""
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
