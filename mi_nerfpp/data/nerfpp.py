"""The NeRF++ dataset layout (the format of the original code release).

::

    ROOT/{train,validation,test}/
        rgb/         images: NAME.png / .jpg / .jpeg / .exr
        pose/        NAME.txt: 16 numbers, the 4x4 camera-to-world matrix (OpenCV), row-major
        intrinsics/  NAME.txt: 16 numbers, a 4x4 matrix with K in its top-left 3x3
        mask/        optional: NAME.png (any image extension), the photo's mask
                     (:mod:`mi_nerfpp.data.masks`)

Files of the three folders are paired by file name stem. ``validation`` and ``test`` may be
missing or empty; ``train`` may not.
"""
from __future__ import annotations

import os

import numpy as np

from mi_nerfpp.data import masks
from mi_nerfpp.data.cameras import Camera
from mi_nerfpp.data.dataset import (SPLITS, Dataset, Frame, make_dataset,
                                    make_splits)
from mi_nerfpp.data.errors import DatasetError
from mi_nerfpp.data.images import write_encoded_png

IMAGE_EXTENSIONS = ('.png', '.jpg', '.jpeg', '.exr')
SUBFOLDERS = ('rgb', 'pose', 'intrinsics')


def is_nerfpp(root) -> bool:
    """Whether ``root`` looks like a NeRF++ dataset (has ``train/pose``)."""
    return os.path.isdir(os.path.join(root, 'train', 'pose'))


def read_nerfpp(root, downscale: int | None = 1, background=(1.0, 1.0, 1.0)) -> Dataset:
    """Read a NeRF++ layout folder (see the module docstring).

    Args:
        root: the dataset folder.
        downscale: integer factor to shrink images by (area averaging); intrinsics follow.
            None: chosen from the image size and the memory available
            (:class:`~mi_nerfpp.data.dataset.AutoDownscale`).
        background: RGB colour transparent pixels are composited over.

    Raises:
        DatasetError: missing folders, unpaired files, malformed text files, bad images, an
            empty train split.
    """
    root = os.fspath(root)
    if not os.path.isdir(os.path.join(root, 'train')):
        raise DatasetError(f'{os.path.join(root, "train")}: missing train split folder; a NeRF++ '
                           f'dataset needs ROOT/train/{{rgb,pose,intrinsics}}/')
    splits, downscale = make_splits(
        {name: _split_frames(os.path.join(root, name)) for name in SPLITS}, downscale, background)
    return make_dataset('nerfpp', root, **splits, train_source=os.path.join(root, 'train'),
                        downscale=downscale)


def write_nerfpp(root, splits: dict[str, tuple[list[Camera], list[np.ndarray]]]) -> None:
    """Write cameras and images in the NeRF++ layout.

    Files are named ``000000.png``/``000000.txt``, ... per split. Images are written as 8-bit
    PNG by :func:`write_encoded_png` (floats in [0, 1], already in the colour encoding wanted
    on disk).

    Args:
        root: output folder (created if needed).
        splits: split name ('train', 'validation' or 'test') -> (cameras, images).

    Raises:
        ValueError: an unknown split name, cameras and images of different counts, or an image
            whose size differs from its camera's.
        FileExistsError: a split folder that already holds files.
    """
    root = os.fspath(root)
    for name, (cameras, images) in splits.items():
        if name not in SPLITS:
            raise ValueError(f'write_nerfpp: unknown split {name!r}; use one of {SPLITS}')
        if len(cameras) != len(images):
            raise ValueError(f'write_nerfpp: split {name!r} has {len(cameras)} cameras but '
                             f'{len(images)} images')
        for cam, img in zip(cameras, images):
            if np.shape(img)[:2] != (cam.height, cam.width):
                raise ValueError(f'write_nerfpp: split {name!r}, camera {cam.name!r} is '
                                 f'{cam.width}x{cam.height} but its image has shape '
                                 f'{np.shape(img)}')
        folders = [os.path.join(root, name, sub) for sub in SUBFOLDERS]
        for folder in folders:
            if os.path.isdir(folder) and os.listdir(folder):
                raise FileExistsError(f'{folder}: already holds files; write to an empty folder')
            os.makedirs(folder, exist_ok=True)
        for i, (cam, img) in enumerate(zip(cameras, images)):
            stem = f'{i:06d}'
            write_encoded_png(os.path.join(folders[0], stem + '.png'), img)
            write_camera(os.path.join(root, name), stem, cam)


def write_camera(split_folder, stem: str, camera: Camera) -> None:
    """Write ``pose/STEM.txt`` and ``intrinsics/STEM.txt`` of one camera into a split folder
    (the folders are created if needed; the image ``rgb/STEM.*`` is the caller's)."""
    intrinsics = np.eye(4)
    intrinsics[:3, :3] = camera.K
    for sub, matrix in (('pose', camera.c2w), ('intrinsics', intrinsics)):
        os.makedirs(os.path.join(split_folder, sub), exist_ok=True)
        _write_matrix(os.path.join(split_folder, sub, stem + '.txt'), matrix)


def _split_frames(folder: str) -> list[Frame]:
    """Frames of one split folder; none if the folder is missing or all its subfolders are."""
    paths = {sub: os.path.join(folder, sub) for sub in SUBFOLDERS}
    present = {sub for sub, path in paths.items() if os.path.isdir(path)}
    if not present:
        return []
    if present != set(SUBFOLDERS):
        missing = paths[next(sub for sub in SUBFOLDERS if sub not in present)]
        raise DatasetError(f'{missing}: missing folder; a NeRF++ split needs rgb/, pose/ and '
                           f'intrinsics/ side by side')
    files = {
        'rgb': _files_by_stem(paths['rgb'], IMAGE_EXTENSIONS),
        'pose': _files_by_stem(paths['pose'], ('.txt',)),
        'intrinsics': _files_by_stem(paths['intrinsics'], ('.txt',)),
    }
    counts = {sub: len(f) for sub, f in files.items()}
    if len(set(counts.values())) > 1:
        raise DatasetError(
            f'{folder}: {counts["rgb"]} images in rgb/, {counts["pose"]} files in pose/ and '
            f'{counts["intrinsics"]} in intrinsics/: every image needs one pose and one '
            f'intrinsics file with the same name stem')
    for sub in ('pose', 'intrinsics'):
        unmatched = sorted(set(files[sub]) ^ set(files['rgb']))
        if unmatched:
            names = [files['rgb'].get(stem) or files[sub][stem] for stem in unmatched]
            raise DatasetError(f'{folder}: rgb/ and {sub}/ files are paired by file name stem, '
                               f'but these have no counterpart: {", ".join(names)}')
    frames = []
    mask_folder = os.path.join(folder, masks.SPLIT_FOLDER)
    for stem in sorted(files['rgb']):
        intrinsics_path = files['intrinsics'][stem]
        K = _read_matrix(intrinsics_path)[:3, :3]
        frames.append(Frame(
            image_path=files['rgb'][stem],
            c2w=_read_matrix(files['pose'][stem]),
            intrinsics=lambda width, height, K=K: K,
            source=files['pose'][stem],
            name=stem,
            intrinsics_source=intrinsics_path,
            mask_path=masks.find_mask(mask_folder, os.path.basename(files['rgb'][stem]))
            if os.path.isdir(mask_folder) else None))
    return frames


def _files_by_stem(folder: str, extensions: tuple[str, ...]) -> dict[str, str]:
    """Files of ``folder`` with one of ``extensions`` (any case), keyed by stem."""
    result = {}
    for entry in sorted(os.listdir(folder)):
        stem, ext = os.path.splitext(entry)
        if ext.lower() not in extensions or not os.path.isfile(os.path.join(folder, entry)):
            continue
        if stem in result:
            raise DatasetError(f'{os.path.join(folder, entry)}: another file has the same stem '
                               f'({result[stem]}); keep one file per name')
        result[stem] = os.path.join(folder, entry)
    return result


def _read_matrix(path: str) -> np.ndarray:
    """A 4x4 matrix from a text file of 16 whitespace-separated numbers (row-major)."""
    try:
        with open(path) as f:
            values = [float(v) for v in f.read().split()]
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise DatasetError(f'{path}: cannot read a 4x4 matrix ({e}); expected 16 numbers') from e
    if len(values) != 16:
        raise DatasetError(f'{path}: expected 16 numbers (a 4x4 matrix, row-major), '
                           f'found {len(values)}')
    return np.array(values).reshape(4, 4)


def _write_matrix(path: str, matrix: np.ndarray) -> None:
    with open(path, 'w') as f:
        for row in np.asarray(matrix, dtype=np.float64):
            f.write(' '.join(repr(float(v)) for v in row) + '\n')
