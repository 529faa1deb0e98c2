"""Multi-layer OpenEXR output for compositing.

Renders are written as one single-part scanline EXR whose channel names follow
the ``layer.channel`` convention that Nuke, Blender and Natron read as layers
(the layers are defined in :mod:`mi_nerfpp.core.layers`, from which this table is made):

{layer_table}

Colour is scene-linear with Rec.709 primaries and D65 white (the ``chromaticities``
attribute, :mod:`mi_nerfpp.core.color`), so ``R G B = fg + (1 - fg.A)·bg + obj + shadow`` holds
in linear light (``obj`` and ``shadow`` are 0 in a scene without shapes). Every channel list
is written whatever the film's pixel format. Pixels are float32, or float16 with
``half=True``; the channels marked "always float32" stay float32 because half precision
cannot hold scene-scale distances accurately. Header attributes:
:func:`compositing_attributes` (colour space, depth convention, software) and, for renders
of a camera, the standard ``worldToCamera`` / ``worldToNDC`` matrices and the field of view
and near plane (:func:`mi_nerfpp.output.views.camera_attributes`).

This module must not import drjit or mitsuba.
"""
from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import numpy as np
import OpenEXR

from mi_nerfpp.version import __version__
from mi_nerfpp.core.color import (COLOR_SPACE, COLOR_SPACE_DESCRIPTION,
                                  REC709_CHROMATICITIES)
from mi_nerfpp.core.layers import FULL_PRECISION_CHANNELS, rst_table
from mi_nerfpp.files.atomic import atomic_write_path, readable_path

if __doc__:        # (None under python -OO)
    __doc__ = __doc__.replace('{layer_table}', rst_table())

DEPTH_CONVENTION = ('depth.Z: camera-space z of the point where the accumulated opacity '
                    'reaches 0.5, i.e. distance along the view axis, world units, positive in '
                    'front of the camera (not 1/z); distance.Y: expected distance along the ray')


def compositing_attributes() -> dict:
    """Header attributes of every render: colour space, depth convention, software."""
    return {'chromaticities': REC709_CHROMATICITIES,
            'oiio:ColorSpace': COLOR_SPACE,
            'colorSpace': COLOR_SPACE_DESCRIPTION,
            'depthConvention': DEPTH_CONVENTION,
            'software': f'mi-nerfpp {__version__}'}


HALF_MAX = float(np.finfo(np.float16).max)

COMPRESSIONS = {
    'none': OpenEXR.NO_COMPRESSION,
    'rle': OpenEXR.RLE_COMPRESSION,
    'zips': OpenEXR.ZIPS_COMPRESSION,
    'zip': OpenEXR.ZIP_COMPRESSION,
    'piz': OpenEXR.PIZ_COMPRESSION,
    'pxr24': OpenEXR.PXR24_COMPRESSION,
    'b44': OpenEXR.B44_COMPRESSION,
    'b44a': OpenEXR.B44A_COMPRESSION,
    'dwaa': OpenEXR.DWAA_COMPRESSION,
    'dwab': OpenEXR.DWAB_COMPRESSION,
}


def split_channels(image: np.ndarray, names: Sequence[str]) -> dict[str, np.ndarray]:
    """Split an ``H x W x C`` image into ``{name: H x W}`` views, one per name."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != len(names):
        raise ValueError(
            f'expected an H x W x {len(names)} image for channels {list(names)}, '
            f'got shape {image.shape}')
    if len(set(names)) != len(names):
        raise ValueError(f'duplicate channel names in {list(names)}')
    return {name: image[..., i] for i, name in enumerate(names)}


def _pixel_dtype(name: str, half: bool) -> type:
    if half and name not in FULL_PRECISION_CHANNELS:
        return np.float16
    return np.float32


def _prepare_channels(channels: Mapping[str, np.ndarray], half: bool) -> dict[str, np.ndarray]:
    """Validate the channels and convert them to contiguous EXR pixel arrays."""
    if not channels:
        raise ValueError('no channels to write')
    shape = None
    prepared = {}
    for name, pixels in channels.items():
        pixels = np.asarray(pixels)
        if pixels.ndim != 2:
            raise ValueError(f"channel '{name}' must be H x W, got shape {pixels.shape}")
        if shape is None:
            shape = pixels.shape
        elif pixels.shape != shape:
            raise ValueError(
                f"channel '{name}' has shape {pixels.shape}, expected {shape} like the others")
        if not np.all(np.isfinite(pixels)):
            raise ValueError(f"channel '{name}' contains NaN or infinite values")
        dtype = _pixel_dtype(name, half)
        if dtype is np.float16 and np.any(np.abs(pixels) > HALF_MAX):
            raise ValueError(
                f"channel '{name}' has values beyond the float16 range (|x| > {HALF_MAX:g}); "
                f"write with half=False")
        # OpenEXR ignores numpy strides, so views (e.g. from split_channels) are copied.
        prepared[name] = np.ascontiguousarray(pixels, dtype=dtype)
    return prepared


def write_exr(path: str | os.PathLike, channels: Mapping[str, np.ndarray],
              half: bool = False, compression: str = 'zip',
              attributes: Mapping | None = None) -> None:
    """Write ``{name: H x W array}`` as a single-part scanline EXR, atomically.

    ``attributes`` are extra header attributes (str, float, int, tuples of
    floats, 4x4 float32 matrices).

    Raises :class:`ValueError` for an empty mapping, arrays that are not 2-D
    or differ in shape, non-finite values (naming the channel), values that
    overflow float16 when ``half`` is set, or an unknown ``compression`` (one
    of :data:`COMPRESSIONS`).
    """
    if compression not in COMPRESSIONS:
        raise ValueError(
            f"unknown EXR compression '{compression}', expected one of {sorted(COMPRESSIONS)}")
    header = dict(attributes or {})
    header.update(compression=COMPRESSIONS[compression], type=OpenEXR.scanlineimage)
    # A new dict: OpenEXR.File replaces the values of the dict it is given
    # with Channel objects, so the caller's mapping must not reach it.
    pixels = _prepare_channels(channels, half)
    with atomic_write_path(path) as tmp:
        with OpenEXR.File(header, pixels) as exr_file:
            exr_file.write(tmp)


def read_header(path: str | os.PathLike) -> dict:
    """The header attributes of a single-part EXR."""
    with readable_path(path) as readable, \
            OpenEXR.File(readable, header_only=True) as exr_file:
        return dict(exr_file.header())


def read_exr(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read a single-part EXR into ``{name: H x W float32 array}``.

    Raises :class:`ValueError` naming ``path`` when the file is missing, is not
    an OpenEXR file, cannot be decoded, or has several parts.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ValueError(f'{path}: no such file')
    with readable_path(path) as readable:
        return _read_exr_file(path, readable)


def _read_exr_file(path, readable):
    """:func:`read_exr` of ``path`` through its UTF-8 path ``readable``."""
    if not OpenEXR.isOpenExrFile(readable):
        raise ValueError(f'{path}: not an OpenEXR file')
    try:
        with OpenEXR.File(readable, separate_channels=True) as exr_file:
            if len(exr_file.parts) != 1:
                raise ValueError(
                    f'{path}: expected a single-part EXR, found {len(exr_file.parts)} parts')
            return {name: np.asarray(channel.pixels, dtype=np.float32)
                    for name, channel in exr_file.channels().items()}
    except RuntimeError as err:
        raise ValueError(f'{path}: cannot read EXR ({err})') from err
