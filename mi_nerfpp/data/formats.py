"""Format detection: one entry point, :func:`load_dataset`, for every supported layout."""
from __future__ import annotations

import os

from mi_nerfpp.data.blender import is_transforms, read_transforms
from mi_nerfpp.data.colmap import is_colmap, read_colmap
from mi_nerfpp.data.dataset import AutoDownscale, Dataset
from mi_nerfpp.data.errors import DatasetError
from mi_nerfpp.data.llff import is_llff, read_llff
from mi_nerfpp.data.nerfpp import is_nerfpp, read_nerfpp


def detect_format(path) -> str:
    """The format of the dataset at ``path``: 'nerfpp', 'blender', 'llff' or 'colmap'.

    Checked in that order: a folder with ``train/pose/`` (NeRF++), a ``transforms*.json`` file
    or a folder with ``transforms_train.json`` / ``transforms.json`` (Blender, instant-ngp,
    nerfstudio), a ``poses_bounds.npy`` file or a folder with one (LLFF), a folder with a
    COLMAP model in ``sparse/0/``, ``sparse/`` or itself (COLMAP; LLFF folders often hold their
    COLMAP model too, and their ``poses_bounds.npy`` wins).

    Raises:
        DatasetError: the path does not exist or matches no format.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise DatasetError(f'{path}: no such file or folder')
    if os.path.isdir(path) and is_nerfpp(path):
        return 'nerfpp'
    if is_transforms(path):
        return 'blender'
    if is_llff(path):
        return 'llff'
    if is_colmap(path):
        return 'colmap'
    raise DatasetError(
        f'{path}: not a recognized dataset. Expected a NeRF++ folder '
        f'(train/{{rgb,pose,intrinsics}}/), a Blender/instant-ngp/nerfstudio folder '
        f'(transforms_train.json or transforms.json), an LLFF folder (poses_bounds.npy + '
        f'images/) or a COLMAP folder (sparse/0/ + images/); for a folder of photos without '
        f'poses, run python -m mi_nerfpp colmap PHOTOS --out DATA first')


def load_dataset(path, downscale: int | None | AutoDownscale = 1, background=(1.0, 1.0, 1.0),
                 llff_hold: int = 8) -> Dataset:
    """Read the dataset at ``path`` in whichever supported format it is.

    Cameras come back in the OpenCV convention, normalized into the unit sphere when they
    were not inside it (see :class:`Dataset`).

    Args:
        path: dataset folder (or its transforms JSON / ``poses_bounds.npy``).
        downscale: integer factor to shrink images by (area averaging); intrinsics follow.
            None or an :class:`~mi_nerfpp.data.dataset.AutoDownscale`: the images' own
            resolution unless they do not fit in memory, else the smallest factor at which
            they do; the factor used is ``Dataset.downscale``.
        background: RGB colour transparent pixels are composited over.
        llff_hold: for formats without explicit splits (LLFF, COLMAP, a single
            ``transforms.json``),
            every ``llff_hold``-th image is held out as test (0: none).

    Raises:
        DatasetError: anything wrong with the data; the message names the file and the fix.
    """
    if downscale is not None and not isinstance(downscale, AutoDownscale):
        if int(downscale) != downscale or downscale < 1:
            raise ValueError(f'downscale must be a positive integer, got {downscale!r}')
        downscale = int(downscale)
    fmt = detect_format(path)
    if fmt == 'nerfpp':
        return read_nerfpp(path, downscale, background)
    if fmt == 'blender':
        return read_transforms(path, downscale, background, llff_hold)
    if fmt == 'colmap':
        return read_colmap(path, downscale, background, llff_hold)
    return read_llff(path, downscale, background, llff_hold)
