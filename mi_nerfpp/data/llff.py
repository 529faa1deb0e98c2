"""LLFF datasets: ``poses_bounds.npy`` plus an ``images/`` folder.

``poses_bounds.npy`` holds one row of 17 numbers per image (images sorted by file name): a 3x5
matrix ``[R | t | hwf]`` flattened row-major, then the near and far scene depth bounds (unused
here). ``R``'s columns are the camera's **down, right, backward** axes in world space, ``t`` its
centre, ``hwf`` the image height, width and focal length in pixels; the principal point is the
image centre. Every ``llff_hold``-th image is held out as the test split, as in NeRF. Masks are
read from an optional ``masks/`` folder beside ``images/`` (:mod:`mi_nerfpp.data.masks`).
"""
from __future__ import annotations

import functools
import os

import numpy as np

from mi_nerfpp.data import masks
from mi_nerfpp.data.dataset import Dataset, Frame, make_dataset, make_splits
from mi_nerfpp.data.errors import DatasetError
from mi_nerfpp.files.readers import FileReadError, read_npy

POSES_FILE = 'poses_bounds.npy'
IMAGE_FOLDER = 'images'
IMAGE_EXTENSIONS = ('.png', '.jpg', '.jpeg')


def is_llff(path) -> bool:
    """Whether ``path`` is a ``poses_bounds.npy`` file or a folder holding one."""
    if os.path.isfile(path):
        return os.path.basename(path) == POSES_FILE
    return os.path.isfile(os.path.join(path, POSES_FILE))


def llff_to_opencv(pose) -> np.ndarray:
    """LLFF 3x4 ``[down | right | backward | centre]`` -> 4x4 OpenCV camera-to-world.

    OpenCV's camera axes are right = LLFF column 1, down = LLFF column 0 and
    forward = -(LLFF column 2).
    """
    pose = np.asarray(pose, dtype=np.float64)
    c2w = np.eye(4)
    c2w[:3, 0] = pose[:, 1]
    c2w[:3, 1] = pose[:, 0]
    c2w[:3, 2] = -pose[:, 2]
    c2w[:3, 3] = pose[:, 3]
    return c2w


def read_llff(path, downscale: int | None = 1, background=(1.0, 1.0, 1.0),
              llff_hold: int = 8) -> Dataset:
    """Read an LLFF dataset (see the module docstring).

    Args:
        path: the dataset folder, or its ``poses_bounds.npy``.
        downscale: integer factor to shrink images by (area averaging); intrinsics follow.
        background: RGB colour transparent pixels are composited over.
        llff_hold: every ``llff_hold``-th image (0, 8, 16, ...) is the test split (0: none).
            There is no validation split.

    Raises:
        DatasetError: a missing or malformed ``poses_bounds.npy``, a missing ``images/``
            folder, pose and image counts that differ, bad images.
    """
    path = os.fspath(path)
    root = os.path.dirname(path) if os.path.isfile(path) else path
    poses_path = os.path.join(root, POSES_FILE)
    expected = ('an N x 17 float array (3x5 pose + 2 bounds per image) saved with numpy.save, '
                "as LLFF's imgs2poses.py writes it")
    try:
        poses_bounds = read_npy(poses_path, what='camera poses')
    except FileReadError as e:
        if e.detail == 'not found':
            raise DatasetError(f'{poses_path}: not found') from None
        raise DatasetError(f'{poses_path}: not a NumPy array file ({e.detail}); expected '
                           f'{expected}') from None
    if not np.issubdtype(poses_bounds.dtype, np.number):
        raise DatasetError(f'{poses_path}: holds {poses_bounds.dtype} data; '
                           f'expected {expected}')
    if poses_bounds.ndim != 2 or poses_bounds.shape[1] != 17:
        raise DatasetError(f'{poses_path}: expected an N x 17 array (3x5 pose + 2 bounds per '
                           f'image), got shape {poses_bounds.shape}')
    image_folder = os.path.join(root, IMAGE_FOLDER)
    if not os.path.isdir(image_folder):
        raise DatasetError(f'{image_folder}: missing folder; LLFF keeps the images that '
                           f'{POSES_FILE} describes in {IMAGE_FOLDER}/')
    images = sorted(os.path.join(image_folder, name) for name in os.listdir(image_folder)
                    if os.path.splitext(name)[1].lower() in IMAGE_EXTENSIONS)
    if len(images) != len(poses_bounds):
        raise DatasetError(f'{image_folder}: {len(images)} images but {poses_path} has '
                           f'{len(poses_bounds)} poses: they must correspond one to one, '
                           f'in sorted file name order')
    frames = []
    mask_folder = os.path.join(root, masks.FOLDER)
    for i, (row, image) in enumerate(zip(poses_bounds.astype(np.float64), images)):
        pose = row[:15].reshape(3, 5)
        source = f'{poses_path} (row {i})'
        frames.append(Frame(
            image_path=image,
            c2w=llff_to_opencv(pose[:, :4]),
            intrinsics=functools.partial(_intrinsics, pose[:, 4], source, image),
            source=source,
            name=os.path.splitext(os.path.basename(image))[0],
            mask_path=masks.find_mask(mask_folder, os.path.basename(image))
            if os.path.isdir(mask_folder) else None))
    held_out = set(range(0, len(frames), llff_hold)) if llff_hold > 0 else set()
    splits, downscale = make_splits({
        'train': [f for i, f in enumerate(frames) if i not in held_out],
        'test': [f for i, f in enumerate(frames) if i in held_out]}, downscale, background)
    return make_dataset('llff', root, **splits, train_source=poses_path, downscale=downscale)


def _intrinsics(hwf, source: str, image: str, width: int, height: int) -> np.ndarray:
    """K for an image of the given size: LLFF's focal, rescaled if the image was resized."""
    h0, w0, focal = hwf
    if not (h0 > 0 and w0 > 0 and focal > 0):
        raise DatasetError(f'{source}: height, width and focal must be positive, got {hwf}')
    if abs(width / height - w0 / h0) > 0.01 * w0 / h0:
        raise DatasetError(f'{image}: image is {width}x{height} but {source} describes a '
                           f'{w0:g}x{h0:g} image; the aspect ratios differ')
    f = focal * width / w0
    return np.array([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]])
