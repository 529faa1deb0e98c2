"""8-bit PNG previews of renders: the beauty as sRGB, and a depth visualisation.

This module must not import drjit or mitsuba.
"""
from __future__ import annotations

import os

import imageio.v3 as iio
import numpy as np

from mi_nerfpp.core.color import to_srgb8
from mi_nerfpp.files.atomic import atomic_write_path


def write_linear_png(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """Write a scene-linear ``H x W x 3`` float image (a render's beauty) as an 8-bit sRGB PNG,
    atomically (parent directory created): clipped to [0, 1], sRGB-encoded
    (:func:`~mi_nerfpp.core.color.to_srgb8`), NaN as 0. A ``uint8`` image is already display-ready
    8-bit (such as the output of :func:`depth_to_png`) and is written as it is.

    Images already in their file encoding (dataset images) are written by
    :func:`mi_nerfpp.data.images.write_encoded_png`.
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f'expected an H x W x 3 image, got shape {rgb.shape}')
    pixels = rgb if rgb.dtype == np.uint8 else to_srgb8(rgb, 'linear')
    with atomic_write_path(path) as tmp:
        iio.imwrite(tmp, pixels, extension='.png')


def depth_to_png(depth: np.ndarray, near: float | None = None,
                 far: float | None = None) -> np.ndarray:
    """Grayscale ``H x W x 3`` uint8 visualisation of an ``H x W`` depth map.

    Inverse depth is mapped linearly so that ``near`` is white and ``far`` is
    black; both default to the range of the finite positive depths (widened
    to stay consistent with an explicitly given bound). Pixels
    beyond ``far`` (including infinite depth) are black, as are invalid
    (non-positive or NaN) depths.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f'expected an H x W depth map, got shape {depth.shape}')
    valid = np.isfinite(depth) & (depth > 0)
    lo, hi = (depth[valid].min(), depth[valid].max()) if valid.any() else (1.0, 1.0)
    if near is None:
        near = lo if far is None else min(lo, far)
    if far is None:
        far = max(hi, near)
    if not 0 < near <= far:
        raise ValueError(f'need 0 < near <= far, got near={near}, far={far}')
    inverse = np.zeros_like(depth)
    positive = depth > 0
    inverse[positive] = 1.0 / depth[positive]
    inv_near, inv_far = 1.0 / near, 1.0 / far
    if inv_near > inv_far:
        level = np.clip((inverse - inv_far) / (inv_near - inv_far), 0.0, 1.0)
    else:
        level = (inverse >= inv_far).astype(np.float64)
    gray = np.round(level * 255.0).astype(np.uint8)
    return np.repeat(gray[..., None], 3, axis=2)
