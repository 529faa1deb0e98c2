"""Per-photo masks: where they are found beside a dataset, how they are read and checked.

A mask is an image of its photo's size whose white (non-zero) pixels are kept and whose black
(zero) pixels are not, as nerfstudio reads them; what "kept" means is the run's choice
(:data:`MEANINGS`, ``--masks``). Masks are found

- per frame, as ``mask_path`` in a ``transforms.json`` (nerfstudio), relative to the JSON file;
- in a ``masks/`` folder beside ``images/`` (COLMAP and LLFF datasets, photo folders), the
  mask of ``images/a/IMG_1.JPG`` being ``masks/a/IMG_1.<any image extension>``;
- in a ``mask/`` folder per split of the NeRF++ layout (``train/mask/000001.png`` beside
  ``train/rgb/000001.png``), as :mod:`mi_nerfpp.data.synth.capture` writes them.

A mask is read as the mean of its colour channels composited over black (so that a grayscale
mask, an RGB one and a white image with the mask in its alpha all read the same), downscaled
with its photo (block means) and kept as 8-bit coverage (0-255). Bad masks end with one line
naming the file (unreadable, another size than the photo) or warn and say what was assumed
(missing for some photos: those are used whole; all black; not binary: values taken as
weights).
"""
from __future__ import annotations

import os
import warnings

import numpy as np

from mi_nerfpp.data.errors import DatasetError
from mi_nerfpp.data.images import downscale_image, read_image

# What a mask means for a run (``--masks``): 'ignore' leaves its black pixels out of the
# photometric loss (people, vehicles, the photographer's shadow); 'object' takes its white
# pixels as the object's silhouette, which the foreground volume's opacity is fitted to (a
# clean matte for compositing); 'none' leaves the masks unused.
MEANINGS = ('ignore', 'object', 'none')
# The meaning used when a dataset has masks and ``--masks`` is not given.
DEFAULT_MEANING = 'ignore'
# Folders masks are found in: beside ``images/`` (COLMAP, LLFF, photo folders) and per split
# of the NeRF++ layout.
FOLDER = 'masks'
SPLIT_FOLDER = 'mask'
EXTENSIONS = ('.png', '.jpg', '.jpeg', '.bmp', '.tif', '.tiff', '.exr', '.webp')
# A mask with more than this share of its pixels strictly between black and white (beyond the
# antialiased edges of a binary mask) is said to be soft: its values are used as they are.
SOFT_SHARE = 0.1
_SOFT_LEVELS = (0.02, 0.98)


def find_mask(folder: str, relative_image: str) -> str | None:
    """The mask in ``folder`` of the image at ``relative_image`` (its path relative to the
    image folder): the same relative path and stem with any of :data:`EXTENSIONS` (or the
    image's own name plus ``.png``, COLMAP's convention); None if there is none."""
    stem = os.path.splitext(relative_image)[0]
    candidates = [stem + e for ext in EXTENSIONS for e in (ext, ext.upper())]
    for candidate in candidates + [relative_image + '.png']:
        path = os.path.join(folder, candidate)
        if os.path.isfile(path):
            return path
    return None


def read_mask(path: str, size: tuple[int, int], image_path: str) -> np.ndarray:
    """The mask at ``path`` as float32 (H, W) in [0, 1], checked against its photo's
    ``size`` (width, height; the photo is named in the error).

    Raises:
        DatasetError: an unreadable mask, or one of another size than its photo.
    """
    try:
        pixels = read_image(path, background=(0.0, 0.0, 0.0))
    except DatasetError as e:
        raise DatasetError(f'{path}: cannot read the mask ({e}): fix or remove it') from e
    height, width = pixels.shape[:2]
    if (width, height) != tuple(size):
        raise DatasetError(f'{path}: the mask is {width}x{height} but its photo {image_path} '
                           f'is {size[0]}x{size[1]}: a mask must have its photo\'s size')
    mask = np.clip(pixels.mean(axis=2), 0.0, 1.0).astype(np.float32)
    _warn_if_unusual(path, mask)
    return mask


def stored_mask(mask: np.ndarray, factor: int) -> np.ndarray:
    """A mask of :func:`read_mask` downscaled by ``factor`` (block means, as the photo) and
    kept as 8-bit coverage (uint8, 255 = kept)."""
    small = downscale_image(mask[..., None], factor)[..., 0]
    return np.rint(np.clip(small, 0.0, 1.0) * 255.0).astype(np.uint8)


def check_coverage(paths: list[str | None], image_paths: list[str], where: str) -> None:
    """Warn when some photos of a split have masks and others do not (those are used whole)."""
    missing = [image for mask, image in zip(paths, image_paths) if mask is None]
    if missing and len(missing) < len(paths):
        warnings.warn(f'{where}: {len(missing)} of {len(paths)} photos have no mask (the first: '
                      f'{missing[0]}); they are used whole', stacklevel=3)


def _warn_if_unusual(path: str, mask: np.ndarray) -> None:
    if not np.any(mask > 0):
        warnings.warn(f'{path}: the mask is black everywhere: with --masks ignore its photo '
                      f'trains nothing, with --masks object the object is absent from it',
                      stacklevel=4)
        return
    lo, hi = _SOFT_LEVELS
    soft = float(np.mean((mask > lo) & (mask < hi)))
    if soft > SOFT_SHARE:
        warnings.warn(f'{path}: the mask is not black and white ({100 * soft:.0f} % of its '
                      f'pixels are grey): its values are used as weights (ignore) or as the '
                      f'object\'s opacity (object)', stacklevel=4)
