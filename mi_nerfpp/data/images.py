"""Reading and writing dataset images as float RGB arrays.

Every image is returned as ``float32`` of shape (H, W, 3) by :func:`read_image`, or at the
file's own precision by :func:`read_stored_image` (what a dataset keeps, :mod:`.storage`):

- PNG and JPEG (8 or 16 bit) are scaled to [0, 1] and stay in their stored (sRGB) encoding;
  16-bit PNGs go through ``mi.Bitmap`` because Pillow (behind imageio) truncates 16-bit colour
  PNGs to 8 bits.
- EXR values are returned as stored (linear, possibly above 1).
- JPEG/PNG EXIF orientation is applied (the pixels come out as a viewer shows them).
- Non-finite pixels (NaN, inf: EXR only) are refused, naming the file and a pixel.
- Grayscale is repeated into three channels.
- An alpha channel is composited over a background colour: PNG/JPEG alpha is straight,
  ``rgb * a + bg * (1 - a)``; EXR colour is premultiplied by alpha (OpenEXR's convention, and
  what Mitsuba writes), ``rgb + bg * (1 - a)``.
"""
from __future__ import annotations

import os

import imageio.v3 as iio
import mitsuba as mi
import numpy as np
import OpenEXR
from PIL import Image

from mi_nerfpp.core.color import quantize8
from mi_nerfpp.data.errors import DatasetError
from mi_nerfpp.files.atomic import readable_path

_PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'
_EXIF_ORIENTATION = 0x0112


def read_image(path, background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """Read an image as a float32 (H, W, 3) array (see the module docstring for the rules).

    Args:
        path: a PNG, JPEG or EXR file (other formats imageio reads work the same as PNG).
        background: RGB colour that transparent pixels are composited over.

    Raises:
        DatasetError: ``"{path}: cannot read image ({reason})"`` if the file cannot be decoded.
    """
    return _read(path, background, keep_integers=False)


def read_stored_image(path, background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """Read an image as :func:`read_image` does, at the file's own precision: ``uint8`` (8-bit
    PNG/JPEG, value / 255) or ``uint16`` (16-bit PNG, value / 65535), (H, W, 3); float32 for
    EXR and for other integer types. Alpha is composited over ``background`` in float as by
    :func:`read_image` and the result rounded to the file's integer levels (an error of at most
    half a level, 0.5 / 255 for 8 bits; float32 if a --background outside [0, 1] takes it
    outside them); opaque integer pixels come back exactly as stored.
    """
    return _read(path, background, keep_integers=True)


def _read(path, background, keep_integers: bool) -> np.ndarray:
    path = os.fspath(path)
    levels = None       # the integer levels of the file (255, 65535), for keep_integers
    try:
        if path.lower().endswith('.exr'):
            color, alpha = _read_exr(path)
            premultiplied = True
        else:
            raw = _read_ldr(path)
            if raw.dtype in (np.bool_, np.uint8):
                levels = np.uint8
            elif raw.dtype == np.uint16:
                levels = np.uint16
            color, alpha = _split_alpha(_to_unit_range(raw))
            premultiplied = False
    except DatasetError:
        raise
    except Exception as e:  # noqa: BLE001 - decoders raise many types; all mean "unreadable"
        raise DatasetError(f'{path}: cannot read image ({type(e).__name__}: {e})') from e
    bad = ~np.isfinite(color).all(axis=2)
    if alpha is not None:
        bad |= ~np.isfinite(alpha[..., 0])
    if bad.any():
        y, x = np.argwhere(bad)[0]
        raise DatasetError(f'{path}: {int(bad.sum())} pixel(s) are NaN or infinite (the first '
                           f'at x={x}, y={y}): fix or remove this image')
    if alpha is not None:
        bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
        color = (color if premultiplied else color * alpha) + bg * (1.0 - alpha)
    # A composite over a --background outside [0, 1] leaves the file's levels: kept in float.
    if keep_integers and levels is not None and color.min() >= 0 and color.max() <= 1:
        return np.round(color * np.float64(np.iinfo(levels).max)).astype(levels)
    return np.ascontiguousarray(color, dtype=np.float32)


def write_encoded_png(path, img) -> None:
    """Write a float image whose values are already in the file's encoding as an 8-bit PNG
    (a dataset image: sRGB-encoded photo values stay as they are).

    Args:
        path: output file.
        img: float array (H, W), (H, W, 1), (H, W, 3) or (H, W, 4) with values in [0, 1]
            (clipped, then rounded to 8 bits, :func:`~mi_nerfpp.core.color.quantize8`). No colour
            conversion: a scene-linear render is written by
            :func:`mi_nerfpp.files.preview.write_linear_png`, which encodes it.
    """
    img = np.asarray(img)
    if not np.issubdtype(img.dtype, np.floating):
        raise TypeError(f'write_encoded_png expects a float image in [0, 1], got dtype '
                        f'{img.dtype}')
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] in (3, 4))):
        raise ValueError(f'write_encoded_png expects (H, W[, 1|3|4]) pixels, got shape '
                         f'{img.shape}')
    iio.imwrite(os.fspath(path), quantize8(img), extension='.png')


def downscale_image(img: np.ndarray, factor: int) -> np.ndarray:
    """Shrink an (H, W, C) image by an integer factor, averaging factor x factor blocks.

    A remainder of fewer than ``factor`` rows/columns at the bottom/right edge is cropped,
    matching :meth:`Camera.downscaled <mi_nerfpp.data.cameras.Camera.downscaled>`.
    """
    factor = int(factor)
    if factor < 1:
        raise ValueError(f'downscale factor must be a positive integer, got {factor}')
    if factor == 1:
        return img
    h, w = img.shape[0] // factor, img.shape[1] // factor
    if h == 0 or w == 0:
        raise ValueError(f'cannot downscale a {img.shape[1]}x{img.shape[0]} image by {factor}')
    blocks = img[:h * factor, :w * factor].reshape(h, factor, w, factor, *img.shape[2:])
    return blocks.mean(axis=(1, 3), dtype=np.float64).astype(img.dtype)


def _png_bit_depth(path: str) -> int | None:
    """Bit depth from a PNG's IHDR chunk, or None if the file is not a PNG."""
    with open(path, 'rb') as f:
        head = f.read(25)
    if len(head) < 25 or not head.startswith(_PNG_SIGNATURE) or head[12:16] != b'IHDR':
        return None
    return head[24]


def _read_ldr(path: str) -> np.ndarray:
    """Raw integer (or bool) pixels of a PNG/JPEG/..., 16-bit PNGs at full precision."""
    if _png_bit_depth(path) == 16:
        with readable_path(path) as readable:       # Mitsuba takes UTF-8 names only
            return np.array(mi.Bitmap(readable))
    return iio.imread(path, plugin='pillow', rotate=True)     # rotate: EXIF orientation


def image_size(path) -> tuple[int, int]:
    """(width, height) of an image as :func:`read_image` returns it (EXIF orientation applied),
    from the file header where Pillow can read it, without decoding the pixels.

    Raises:
        DatasetError: the file cannot be read.
    """
    path = os.fspath(path)
    if not path.lower().endswith('.exr'):
        try:
            with Image.open(path) as img:
                width, height = img.size
                # EXIF orientations 5-8 turn the image by 90 degrees.
                if img.getexif().get(_EXIF_ORIENTATION, 1) in (5, 6, 7, 8):
                    width, height = height, width
            return width, height
        except Exception:  # noqa: BLE001 - not readable by Pillow: decode it below
            pass
    height, width = read_image(path).shape[:2]
    return width, height


def _to_unit_range(pixels: np.ndarray) -> np.ndarray:
    """Integer pixels scaled to float32 [0, 1], as (H, W, C)."""
    if pixels.dtype == np.bool_:
        pixels = pixels.astype(np.float32)
    elif np.issubdtype(pixels.dtype, np.integer):
        pixels = pixels.astype(np.float32) / np.float32(np.iinfo(pixels.dtype).max)
    else:
        pixels = pixels.astype(np.float32)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if pixels.ndim != 3:
        raise ValueError(f'unexpected pixel array shape {pixels.shape}')
    return pixels


def _split_alpha(pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(H, W, C) with C in 1..4 -> (rgb (H, W, 3), alpha (H, W, 1) or None)."""
    channels = pixels.shape[2]
    if channels in (1, 2):
        rgb = np.repeat(pixels[..., :1], 3, axis=2)
    elif channels in (3, 4):
        rgb = pixels[..., :3]
    else:
        raise ValueError(f'{channels} channels (expected 1 to 4)')
    alpha = pixels[..., -1:] if channels in (2, 4) else None
    return rgb, alpha


def _read_exr(path: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Colour (H, W, 3) and optional alpha (H, W, 1) of an EXR's default (unnamed) layer."""

    with readable_path(path) as readable, OpenEXR.File(readable, separate_channels=True) as f:
        channels = {name: np.asarray(ch.pixels, dtype=np.float32)
                    for name, ch in f.channels().items()}
    if all(c in channels for c in 'RGB'):
        rgb = np.stack([channels['R'], channels['G'], channels['B']], axis=-1)
    elif 'Y' in channels:
        rgb = np.repeat(channels['Y'][..., None], 3, axis=2)
    else:
        raise DatasetError(f'{path}: cannot read image (no R, G, B or Y channel; found '
                           f'{sorted(channels)}): write the colour into the default layer')
    alpha = channels['A'][..., None] if 'A' in channels else None
    return rgb, alpha
