"""8-bit PNG previews of renders: sRGB encoding and a depth visualisation.

This module must not import drjit or mitsuba.
"""
from __future__ import annotations

import os

import imageio.v3 as iio
import numpy as np

from .files import atomic_write_path

COLOR_SPACES = ('linear', 'srgb')

SRGB_LINEAR_CUTOFF = 0.0031308


def srgb_oetf(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) for values in [0, 1]."""
    linear = np.asarray(linear, dtype=np.float64)
    curve = 1.055 * np.power(np.maximum(linear, SRGB_LINEAR_CUTOFF), 1 / 2.4) - 0.055
    return np.where(linear <= SRGB_LINEAR_CUTOFF, 12.92 * linear, curve)


def srgb_eotf(encoded: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear light (the inverse of :func:`srgb_oetf`)."""
    encoded = np.asarray(encoded, dtype=np.float64)
    return np.where(encoded <= 0.04045, encoded / 12.92,
                    ((np.maximum(encoded, 0.04045) + 0.055) / 1.055) ** 2.4)


def _check_rgb(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f'expected an H x W x 3 image, got shape {rgb.shape}')
    return rgb


def to_srgb8(rgb: np.ndarray, color_space: str = 'linear') -> np.ndarray:
    """Encode an ``H x W x 3`` float image as 8-bit sRGB.

    ``color_space='linear'`` clips to [0, 1] and applies the sRGB OETF;
    ``'srgb'`` means the values are already encoded and are only clipped.
    NaN becomes 0.
    """
    if color_space not in COLOR_SPACES:
        raise ValueError(f"unknown color space '{color_space}', expected one of {COLOR_SPACES}")
    rgb = _check_rgb(rgb)
    encoded = np.clip(np.nan_to_num(rgb.astype(np.float64), nan=0.0), 0.0, 1.0)
    if color_space == 'linear':
        encoded = srgb_oetf(encoded)
    return np.round(encoded * 255.0).astype(np.uint8)


def write_png(path: str | os.PathLike, rgb: np.ndarray, color_space: str = 'linear') -> None:
    """Write an ``H x W x 3`` image as PNG, atomically (parent directory created).

    Float images are encoded with :func:`to_srgb8`; ``uint8`` images (such as
    the output of :func:`depth_to_png`) are written as they are.
    """
    rgb = _check_rgb(rgb)
    pixels = rgb if rgb.dtype == np.uint8 else to_srgb8(rgb, color_space)
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
