"""Colour: the encodings images come in, sRGB encoding and decoding, 8-bit quantization.

Renders are scene-linear with Rec.709 primaries and D65 white (:data:`COLOR_SPACE`,
:data:`REC709_CHROMATICITIES`). Training images are in one of :data:`COLOR_SPACES`: ``'srgb'``
(PNG/JPEG pixel values, sRGB-encoded) or ``'linear'`` (EXR). The sRGB transfer function is
IEC 61966-2-1: :func:`srgb_oetf` / :func:`srgb_eotf` on NumPy arrays, :func:`linear_to_srgb` /
:func:`srgb_to_linear` on Dr.Jit arrays (Dr.Jit's own, which clip to [0, 1] first).

This module must not import drjit or mitsuba at import time (the Dr.Jit functions import
it when called).
"""
from __future__ import annotations

import drjit as dr
import numpy as np

# The encodings of training images (``Dataset.color_space``, ``NeRFPPModel.color_space``).
COLOR_SPACES = ('linear', 'srgb')

# The colour space of every render: its OpenImageIO name, its description, and the Rec.709 /
# sRGB primaries and D65 white point (red xy, green xy, blue xy, white xy) of the EXR
# ``chromaticities`` attribute. 'linear' is the name OIIO's built-in colour config resolves
# (2.4 knows no 'lin_rec709'; OCIO's ACES configs call it 'Linear Rec.709 (sRGB)', which OIIO
# 2.4 does not know); the standard ``chromaticities`` attribute says which primaries it has.
COLOR_SPACE = 'linear'
COLOR_SPACE_DESCRIPTION = 'scene-linear Rec.709 (sRGB primaries, D65)'
REC709_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)

SRGB_LINEAR_CUTOFF = 0.0031308      # linear value where the curve's linear toe ends
SRGB_ENCODED_CUTOFF = 0.04045       # the same point, encoded


def srgb_oetf(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1), linear light -> encoded, for values in
    [0, 1] (float64)."""
    linear = np.asarray(linear, dtype=np.float64)
    curve = 1.055 * np.power(np.maximum(linear, SRGB_LINEAR_CUTOFF), 1 / 2.4) - 0.055
    return np.where(linear <= SRGB_LINEAR_CUTOFF, 12.92 * linear, curve)


def srgb_eotf(encoded: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear light (the inverse of :func:`srgb_oetf`,
    float64)."""
    encoded = np.asarray(encoded, dtype=np.float64)
    return np.where(encoded <= SRGB_ENCODED_CUTOFF, encoded / 12.92,
                    ((np.maximum(encoded, SRGB_ENCODED_CUTOFF) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x):
    """Dr.Jit arrays: linear light -> sRGB-encoded, clipped to [0, 1] (``dr.linear_to_srgb``)."""
    return dr.linear_to_srgb(x)


def srgb_to_linear(x):
    """Dr.Jit arrays: sRGB-encoded -> linear light, clipped to [0, 1] (``dr.srgb_to_linear``)."""
    return dr.srgb_to_linear(x)


def check_color_space(color_space: str) -> str:
    """``color_space`` if it is one of :data:`COLOR_SPACES`, else a ValueError naming them."""
    if color_space not in COLOR_SPACES:
        raise ValueError(f"unknown color space '{color_space}', expected one of {COLOR_SPACES}")
    return color_space


def encode(linear: np.ndarray, color_space: str) -> np.ndarray:
    """A scene-linear image in the encoding ``color_space`` (float32): ``'srgb'`` clips to
    [0, 1] and applies :func:`srgb_oetf`, as a camera's photo is encoded; ``'linear'`` leaves
    it as it is."""
    if check_color_space(color_space) == 'srgb':
        return srgb_oetf(np.clip(linear, 0.0, 1.0)).astype(np.float32)
    return np.asarray(linear)


def quantize8(encoded: np.ndarray) -> np.ndarray:
    """Encoded values -> 8 bits: clipped to [0, 1], NaN to 0, rounded to ``uint8`` 0..255."""
    encoded = np.nan_to_num(np.asarray(encoded, dtype=np.float64), nan=0.0)
    return np.round(np.clip(encoded, 0.0, 1.0) * 255.0).astype(np.uint8)


def to_srgb8(rgb: np.ndarray, color_space: str = 'linear') -> np.ndarray:
    """Encode an ``H x W x 3`` float image as 8-bit sRGB.

    ``color_space='linear'`` clips to [0, 1] and applies the sRGB OETF;
    ``'srgb'`` means the values are already encoded and are only clipped.
    NaN becomes 0.
    """
    check_color_space(color_space)
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f'expected an H x W x 3 image, got shape {rgb.shape}')
    encoded = np.clip(np.nan_to_num(rgb.astype(np.float64), nan=0.0), 0.0, 1.0)
    if color_space == 'linear':
        encoded = srgb_oetf(encoded)
    return quantize8(encoded)
