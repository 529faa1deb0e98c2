"""Lens distortion: images undistorted to pinhole cameras with COLMAP (pycolmap), once, cached.

mi-nerfpp's cameras are pinholes. Two readers meet lens distortion, and both undistort the
images once into a cache folder next to the dataset:

- a COLMAP model whose cameras have distortion (:mod:`mi_nerfpp.data.colmap`): the whole model
  goes through COLMAP's own undistorter (:func:`undistort_model`) into ``ROOT/undistorted/``
  (``images/`` and ``sparse/`` with PINHOLE cameras);
- a ``transforms.json`` with OpenCV or OpenCV-fisheye coefficients
  (:mod:`mi_nerfpp.data.blender`): each distorted image is resampled to a pinhole camera
  (:func:`undistort_views`) into ``<json stem>_undistorted/``: the images at their paths
  relative to the JSON file, as PNG (EXR stays EXR), and ``cameras.json``, the distorted and
  the pinhole camera of every image as COLMAP camera models.

One rule makes the pinhole camera for both: COLMAP's ``undistort_camera`` with
:func:`camera_options` (the same focal lengths; the image size and principal point chosen so
that every pixel of the pinhole image lies inside the distorted one, so there are no blank
borders). The image is resampled as COLMAP's undistorter does it: each pinhole pixel centre is
unprojected with the pinhole camera and projected with the distorted one (pycolmap's
``cam_from_img`` / ``img_from_cam``), and the distorted image is interpolated bilinearly there.
:func:`undistort_views` does this in floating point so that 16-bit PNGs, EXR and alpha keep
their precision (pycolmap's bitmaps are 8-bit RGB); for 8-bit images its result equals
``pycolmap.undistort_image``'s up to rounding (tests/data/test_undistort.py checks it).

A cache is written into ``<cache>.partial`` and renamed onto ``<cache>`` only when complete
(:func:`atomic_folder`), so an interrupted run never leaves a cache that is reused; it is reused
while it is at least as new as everything it was made from (:func:`is_fresh`).
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
from dataclasses import dataclass
from typing import Iterable, Iterator

import imageio.v3 as iio
import mitsuba as mi
import numpy as np
import OpenEXR
from scipy.ndimage import map_coordinates
from tqdm import tqdm

from mi_nerfpp.data.errors import DatasetError
from mi_nerfpp.data.images import _read_exr, _read_ldr
from mi_nerfpp.files.atomic import atomic_write_path
from mi_nerfpp.files.readers import FileReadError, read_json

# The index of a transforms.json undistortion cache (written last: its time stamps the cache).
CACHE_INDEX = 'cameras.json'
PARTIAL_SUFFIX = '.partial'
# Pinhole pixels interpolated per block (bounds the memory of the pixel map of one block).
_BLOCK_PIXELS = 1 << 21
# The least share of a photo's area that its undistorted image must keep: coefficients that
# leave less (k1 = 1e6 leaves a 6x4 crop of a 32x24 photo) are refused, not trained on. COLMAP's
# pinhole camera keeps no blank pixels, so even sound wide lenses lose their corners.
MIN_KEPT_SHARE = 0.25


def camera_options():
    """COLMAP's options for the pinhole camera of a distorted one (its defaults: no blank
    pixels, so the pinhole image is cropped to where the distorted image has content)."""
    import pycolmap  # deferred: COLMAP's native library, for SfM and undistortion only
    return pycolmap.UndistortCameraOptions()


def pycolmap_camera(camera):
    """A ``pycolmap.Camera`` of a camera description with ``model`` (COLMAP's model name),
    ``width``, ``height`` and ``params`` (e.g. :class:`mi_nerfpp.data.colmap.ColmapCamera`)."""
    import pycolmap  # deferred: COLMAP's native library, for SfM and undistortion only
    return pycolmap.Camera(model=camera.model, width=int(camera.width),
                           height=int(camera.height),
                           params=np.asarray(camera.params, dtype=np.float64))


# ----------------------------------------------------------------------------- caches
def is_fresh(results: Iterable[str], sources: Iterable[str]) -> bool:
    """Whether every file of ``results`` exists and none is older than any of ``sources``."""
    results = list(results)
    if not results or not all(os.path.isfile(path) for path in results):
        return False
    newest_source = max((os.path.getmtime(path) for path in sources), default=-np.inf)
    return min(os.path.getmtime(path) for path in results) >= newest_source


@contextlib.contextmanager
def atomic_folder(out: str) -> Iterator[str]:
    """Yield an empty folder ``out + '.partial'`` to write into; on success it replaces ``out``.

    A run that fails or is killed mid-write leaves at most the ``.partial`` folder, which is
    never read and is removed by the next run; ``out`` is either the old folder or the new one.

    Raises:
        DatasetError: the folder cannot be created (e.g. the dataset is on a read-only disk).
    """
    tmp = out + PARTIAL_SUFFIX
    for path in (out, tmp):
        if os.path.lexists(path) and not os.path.isdir(path):
            raise DatasetError(f'{path}: a file stands where the undistorted images are '
                               f'written (the folder {os.path.basename(out)}/ beside the '
                               f'dataset file): move it away and run again')
    try:
        shutil.rmtree(tmp, ignore_errors=True)
        os.makedirs(tmp)
    except OSError as e:
        raise DatasetError(f'{out}: cannot write the undistorted images here ({e.strerror}); '
                           f'copy the dataset to a writable place') from e
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    shutil.rmtree(out, ignore_errors=True)
    os.replace(tmp, out)


# ----------------------------------------------------------------------------- COLMAP models
def undistort_model(model_folder: str, image_folder: str, out: str) -> None:
    """COLMAP's undistorter on a whole model: ``out/images/`` and ``out/sparse/`` with PINHOLE
    cameras, written atomically.

    Raises:
        DatasetError: COLMAP fails (the message names the model and the way out).
    """
    import pycolmap  # deferred: COLMAP's native library, for SfM and undistortion only
    with atomic_folder(out) as tmp:
        try:
            pycolmap.undistort_images(tmp, model_folder, image_folder,
                                      undistort_options=camera_options())
        except Exception as e:  # noqa: BLE001 - pycolmap raises ValueError/RuntimeError alike
            raise DatasetError(f'{model_folder}: COLMAP could not undistort the images into '
                               f'{out} ({type(e).__name__}: {e}); undistort them yourself '
                               f'(colmap image_undistorter) and point at the result') from e


# ----------------------------------------------------------------------------- single images
@dataclass
class View:
    """One image to undistort.

    Attributes:
        image_path: the distorted image.
        name: its path in the cache, relative to the cache folder (``.png``, or ``.exr``
            for EXR images).
        camera: its distorted camera as a COLMAP model (``model``, ``width``, ``height``,
            ``params``), for the image as :func:`~mi_nerfpp.data.images.read_image` returns
            it (EXIF orientation applied).
    """

    image_path: str
    name: str
    camera: object


@dataclass
class Pinhole:
    """An undistorted image and its pinhole camera."""

    image_path: str
    K: np.ndarray
    width: int
    height: int


def undistort_views(views: list[View], out: str, sources: Iterable[str] = (),
                    what: str = '', progress: bool = True) -> list[Pinhole]:
    """The undistorted images and pinhole cameras of ``views``, from the cache folder ``out``
    when it is up to date, else made there (atomically) first.

    The cache is up to date when its index is at least as new as ``sources`` (e.g. the JSON
    file the cameras come from) and every image, and it lists every view with the same image,
    the same distorted camera and the same pycolmap version. Views whose distorted cameras
    have the same image size get pinhole cameras of one size (the smallest COLMAP chooses for
    them, cropped about the centre), so the images of one split keep one size.

    Args:
        what: the dataset file named in the info line (printed when ``progress``).

    Raises:
        DatasetError: an unreadable image, two views with one cache name, a cache folder that
            cannot be written.
    """
    import pycolmap  # deferred: COLMAP's native library, for SfM and undistortion only
    out = os.path.abspath(out)
    names = {}
    for view in views:
        if view.name in names:
            raise DatasetError(f'{view.image_path} and {names[view.name]} would both be '
                               f'undistorted to {os.path.join(out, view.name)}: rename one')
        names[view.name] = view.image_path
    index_path = os.path.join(out, CACHE_INDEX)
    models = ', '.join(sorted({view.camera.model for view in views}))
    sources = list(sources) + [view.image_path for view in views]
    entries = [_entry(view, out) for view in views]
    cached = _read_index(index_path) if is_fresh([index_path], sources) else None
    held = (_cached_pinholes(cached, views, entries, out)
            if cached is not None and cached.get('pycolmap') == pycolmap.__version__ else None)
    if held is not None:
        if progress:
            print(f'{what}: lens distortion ({models}) in {len(views)} images: reading them '
                  f'undistorted to pinhole cameras from {out}/')
        return held

    if progress:
        print(f'{what}: lens distortion ({models}) in {len(views)} images: undistorting them '
              f'to pinhole cameras with COLMAP into {out}/ (once; redone when the cameras or '
              f'images change)')
    pinholes = _pinhole_cameras([view.camera for view in views])
    for view, pinhole in zip(views, pinholes):
        check_kept(view, pinhole, what)
    with atomic_folder(out) as tmp, _progress(len(views), progress) as bar:
        maps = {}
        for view, entry, pinhole in zip(views, entries, pinholes):
            pixels = _read_pixels(view.image_path)
            if pixels.shape[:2] != (view.camera.height, view.camera.width):
                raise DatasetError(f'{view.image_path}: image is {pixels.shape[1]}x'
                                   f'{pixels.shape[0]} but its camera is {view.camera.width}x'
                                   f'{view.camera.height}: fix the metadata or the image')
            key = (json.dumps(entry['distorted']), pinhole.width, pinhole.height,
                   tuple(pinhole.params))
            if key not in maps:     # one map at a time: views of one camera share it
                maps = {key: _pixel_map(pycolmap_camera(view.camera), pinhole)}
            path = os.path.join(tmp, view.name)
            os.makedirs(os.path.dirname(path), exist_ok=True)
            _write_pixels(path, warp(pixels, maps[key]))
            entry['pinhole'] = {'model': 'PINHOLE', 'width': pinhole.width,
                                'height': pinhole.height,
                                'params': [float(p) for p in pinhole.params]}
            bar.update(1)
        with open(os.path.join(tmp, CACHE_INDEX), 'w') as f:
            json.dump({'about': f'images of {os.path.basename(what)} undistorted to pinhole '
                                f'cameras by mi-nerfpp with COLMAP; redone when the cameras '
                                f'or images change',
                       'pycolmap': pycolmap.__version__,
                       'images': {view.name: entry for view, entry in zip(views, entries)}},
                      f, indent=1)
    return [_pinhole(out, view.name, entry['pinhole']) for view, entry in zip(views, entries)]


def _entry(view: View, out: str) -> dict:
    """The cache index entry of a view, without its pinhole camera (JSON values, so that an
    entry read back compares equal)."""
    camera = view.camera
    return json.loads(json.dumps({
        'source': os.path.relpath(os.path.abspath(view.image_path), out),
        'distorted': {'model': camera.model, 'width': int(camera.width),
                      'height': int(camera.height),
                      'params': [float(p) for p in camera.params]}}))


def _cached_pinholes(cached: dict, views, entries, out: str) -> list | None:
    """The pinhole cameras of ``views`` that the cache index ``cached`` holds, or None where
    it does not hold them all, or holds them damaged: then they are made again."""
    try:
        images = cached['images']
        if not all(images.get(view.name, {}).get('source') == entry['source']
                   and images[view.name].get('distorted') == entry['distorted']
                   and 'pinhole' in images[view.name]
                   and os.path.isfile(os.path.join(out, view.name))
                   for view, entry in zip(views, entries)):
            return None
        return [_pinhole(out, view.name, images[view.name]['pinhole']) for view in views]
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError):
        return None


def _read_index(path: str) -> dict | None:
    try:
        index = read_json(path, what='undistortion cache index')
    except FileReadError:       # none, or damaged: the images are undistorted again
        return None
    return index if isinstance(index.get('images'), dict) else None


def kept_share(distorted, pinhole, samples: int = 64) -> float:
    """The share of the distorted photo that its pinhole image keeps: the lesser of the share
    of its area that the pinhole image shows (the pinhole image's border mapped into the photo,
    clipped to it, as a polygon) and of its pixels (k1 = 1e6 keeps the whole view in 6x4
    pixels of a 32x24 photo); 0 where the mapping is not finite."""
    w, h = float(pinhole.width), float(pinhole.height)
    if not (w >= 1 and h >= 1):
        return 0.0
    t = (np.arange(samples) + 0.5) / samples
    zero, one = np.zeros_like(t), np.ones_like(t)
    border = np.concatenate([np.stack([t * w, zero], 1), np.stack([one * w, t * h], 1),
                             np.stack([(1 - t) * w, one * h], 1),
                             np.stack([zero, (1 - t) * h], 1)])
    with np.errstate(all='ignore'):
        rays = pinhole.cam_from_img(border)
        source = distorted.img_from_cam(np.column_stack([rays, np.ones(len(rays))]),
                                        check_cheirality=False)
    if not np.all(np.isfinite(source)):
        return 0.0
    x = np.clip(source[:, 0], 0.0, float(distorted.width))
    y = np.clip(source[:, 1], 0.0, float(distorted.height))
    area = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
    photo = float(distorted.width) * float(distorted.height)
    return min(area / photo, w * h / photo)


def check_kept(view: View, pinhole, what: str = ''):
    """Refuse a view whose undistorted image keeps less than :data:`MIN_KEPT_SHARE` of its
    photo (absurd coefficients), naming the file, the largest coefficient and the share kept."""
    distorted = pycolmap_camera(view.camera)
    try:
        share = kept_share(distorted, pinhole)
    except Exception:  # noqa: BLE001 - pycolmap refuses some parameters with ValueError/RuntimeError
        share = 0.0
    if share >= MIN_KEPT_SHARE:
        return
    names = [n.strip() for n in distorted.params_info.split(',')]
    coefficients = [(n, float(v)) for n, v in zip(names, view.camera.params)
                    if n not in ('f', 'fx', 'fy', 'cx', 'cy')]
    name, value = max(coefficients, key=lambda c: abs(c[1]) if np.isfinite(c[1]) else np.inf,
                      default=('none', 0.0))
    raise DatasetError(
        f'{what or view.image_path}: the lens distortion of {view.image_path} '
        f'({view.camera.model}, largest coefficient "{name}" = {value:g}) leaves '
        f'{100 * share:.1f} % of the photo in its undistorted image, less than the '
        f'{100 * MIN_KEPT_SHARE:.0f} % that must stay: check the coefficients (OpenCV\'s '
        f'convention, for pixel coordinates normalized by the focal length), or give the '
        f'images undistorted and drop the coefficients')


def _pinhole(out: str, name: str, camera: dict) -> Pinhole:
    fx, fy, cx, cy = (float(v) for v in camera['params'])
    return Pinhole(os.path.join(out, name), np.array([[fx, 0.0, cx], [0.0, fy, cy],
                                                      [0.0, 0.0, 1.0]]),
                   int(camera['width']), int(camera['height']))


def _pinhole_cameras(cameras) -> list:
    """COLMAP's pinhole camera of each camera; those of one source size cropped to one size."""
    import pycolmap  # deferred: COLMAP's native library, for SfM and undistortion only
    options = camera_options()
    pinholes = [pycolmap.undistort_camera(options, pycolmap_camera(c)) for c in cameras]
    common = {}
    for camera, pinhole in zip(cameras, pinholes):
        size = (int(camera.width), int(camera.height))
        w, h = common.get(size, (pinhole.width, pinhole.height))
        common[size] = (min(w, pinhole.width), min(h, pinhole.height))
    cropped = []
    for camera, pinhole in zip(cameras, pinholes):
        width, height = common[(int(camera.width), int(camera.height))]
        fx, fy, cx, cy = pinhole.params
        cropped.append(pycolmap.Camera(
            model='PINHOLE', width=width, height=height,
            params=[fx, fy, cx - (pinhole.width - width) // 2,
                    cy - (pinhole.height - height) // 2]))
    return cropped


def _pixel_map(distorted, pinhole) -> np.ndarray:
    """(2, H, W) float32 (row, column) of each pinhole pixel centre in the distorted image, in
    the array-index convention of :func:`scipy.ndimage.map_coordinates` (pixel (i, j) centred
    at integer (i, j), i.e. continuous pixel coordinates minus 0.5)."""
    width, height = pinhole.width, pinhole.height
    coords = np.empty((2, height, width), dtype=np.float32)
    rows = max(1, _BLOCK_PIXELS // width)
    for y0 in range(0, height, rows):
        x, y = np.meshgrid(np.arange(width) + 0.5, np.arange(y0, min(y0 + rows, height)) + 0.5)
        rays = pinhole.cam_from_img(np.stack([x.ravel(), y.ravel()], axis=1))
        source = distorted.img_from_cam(np.column_stack([rays, np.ones(len(rays))]),
                                        check_cheirality=False) - 0.5
        coords[0, y0:y0 + rows] = source[:, 1].reshape(x.shape)
        coords[1, y0:y0 + rows] = source[:, 0].reshape(x.shape)
    return coords


def warp(pixels: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """``pixels`` (H, W, C) resampled bilinearly at ``coords`` (:func:`_pixel_map`); outside
    the image is 0 (as in COLMAP); integer pixels are rounded back to their type."""
    channels = [map_coordinates(pixels[..., c].astype(np.float32), coords, order=1,
                                mode='constant', cval=0.0) for c in range(pixels.shape[2])]
    result = np.stack(channels, axis=-1)
    if np.issubdtype(pixels.dtype, np.integer):
        info = np.iinfo(pixels.dtype)
        result = np.clip(np.round(result), info.min, info.max).astype(pixels.dtype)
    return result


def _read_pixels(path: str) -> np.ndarray:
    """An image as stored, (H, W, C): uint8 or uint16 for PNG/JPEG (EXIF orientation applied,
    alpha kept), float32 RGB[A] for EXR (colour premultiplied, as stored)."""
    try:
        if path.lower().endswith('.exr'):
            rgb, alpha = _read_exr(path)
            pixels = rgb if alpha is None else np.concatenate([rgb, alpha], axis=2)
        else:
            pixels = _read_ldr(path)
            if pixels.dtype == np.bool_:
                pixels = pixels.astype(np.uint8) * np.uint8(255)
    except DatasetError:
        raise
    except Exception as e:  # noqa: BLE001 - decoders raise many types; all mean "unreadable"
        raise DatasetError(f'{path}: cannot read image ({type(e).__name__}: {e})') from e
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if pixels.dtype not in (np.uint8, np.uint16, np.float32) or pixels.shape[2] > 4:
        raise DatasetError(f'{path}: cannot undistort {pixels.dtype} images with '
                           f'{pixels.shape[2]} channels; use 8/16-bit PNG, JPEG or EXR')
    if pixels.dtype == np.float32 and not np.isfinite(pixels).all():
        raise DatasetError(f'{path}: has NaN or infinite pixels: fix or remove this image')
    return pixels


def _write_pixels(path: str, pixels: np.ndarray) -> None:
    """Write what :func:`_read_pixels` read: PNG (8 or 16 bit) or EXR (float32), through a
    temporary UTF-8 path (OpenEXR and Mitsuba refuse other bytes in a name)."""
    with atomic_write_path(path) as tmp:
        _write_pixels_to(path, tmp, pixels)


def _write_pixels_to(path: str, tmp: str, pixels: np.ndarray) -> None:
    if path.lower().endswith('.exr'):
        names = ('R', 'G', 'B', 'A')[:pixels.shape[2]]
        channels = {name: np.ascontiguousarray(pixels[..., i]) for i, name in enumerate(names)}
        with OpenEXR.File({'compression': OpenEXR.ZIP_COMPRESSION,
                           'type': OpenEXR.scanlineimage}, channels) as f:
            f.write(tmp)
    elif pixels.dtype == np.uint16:
        mi.Bitmap(pixels if pixels.shape[2] > 1 else pixels[..., 0]).write(tmp)
    else:
        iio.imwrite(tmp, pixels if pixels.shape[2] > 1 else pixels[..., 0], extension='.png')


def _progress(total: int, enabled: bool):
    return tqdm(total=total, desc='undistort', unit='image', disable=not enabled or total < 2,
                leave=False)
