"""The training pixels of a split as rays (the first stage of a training step: dataset -> rays),
built per batch from the cameras and the stored pixels, at any level of the image pyramid."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_nerfpp.core.arrays import owned
from mi_nerfpp.core.rays import Rays
from mi_nerfpp.data.storage import MAX_STORED_BYTES
from mi_nerfpp.training.errors import TrainingError


class RayBank:
    """The training pixels of a split as rays, built per batch from the cameras (Dr.Jit arrays).

    Ray ``index = (image · H + y) · W + x`` of a split of images of H x W pixels starts at the
    centre of camera ``image`` and goes through the centre of pixel (x, y), as
    :func:`~mi_nerfpp.data.pixel_rays` computes it (in Float64, then rounded to float32); its
    colour is the pixel's stored value (:mod:`mi_nerfpp.data.storage`) converted to float32
    as :attr:`Split.images <mi_nerfpp.data.dataset.Split.images>` converts it. The bank holds
    per image its camera (``fx, s, cx, fy, cy`` of K, the rotation and the centre, Float64)
    and the stored pixels: a training pixel costs the bytes its file stored (3 for 8 bits).

    Image pyramid (:meth:`level`): at ``factor`` F the images are H/F x W/F pixels (a
    remainder cropped, as :func:`~mi_nerfpp.data.images.downscale_image`); ray ``(image,
    y, x)`` goes through the centre of the F x F block of pixels at ``(F·x, F·y)``, as the
    camera :meth:`downscaled <mi_nerfpp.data.Camera.downscaled>` by F sees it, and its colour
    is the block's mean: a box-filtered downsample, read from the same stored pixels (no copy
    per level). :meth:`footprint` gives each ray's pixel width per unit distance at its level.

    Masks (``masks=True`` and a split with masks, :mod:`mi_nerfpp.data.masks`): one byte a
    pixel, the mask's coverage (255 where a photo has no mask); :meth:`mask` gives each ray's
    in [0, 1], at a pyramid level its block's mean or least.
    """

    def __init__(self, split, masks: bool = False):
        if len(split) == 0:
            raise TrainingError('the training split is empty')
        images = split.images
        if images.nbytes > MAX_STORED_BYTES:
            raise TrainingError(f'the training images take {images.nbytes / 2 ** 30:.1f} GiB '
                                f'as stored, more than the {MAX_STORED_BYTES / 2 ** 30:.0f} GiB '
                                f'a training step can address: choose a --downscale')
        h, w = images.stored[0].shape[:2]
        n = len(split)
        cams = split.cameras
        K = np.array([[c.K[0, 0], c.K[0, 1], c.K[0, 2], c.K[1, 1], c.K[1, 2]] for c in cams])
        R = np.array([c.c2w[:3, :3] for c in cams])
        center = np.array([c.c2w[:3, 3] for c in cams])
        # Owned copies (:mod:`.arrays`): a frozen step of another Trainer may outlive this one.
        self.cameras = tuple(owned(a.ravel(), _Float64) for a in (K, R, center))
        kind = images.dtype.name
        stored = [a.astype('<u2').view(np.uint8) if kind == 'uint16' else a
                  for a in images.stored]
        self.pixels = _owned_concatenation(stored, _STORE_TYPES[kind])
        self.masks = None
        if masks and split.masks is not None:
            full = np.full((h, w), 255, dtype=np.uint8)
            self.masks = _owned_concatenation([full if m is None else m for m in split.masks],
                                              _UInt8)
        self.layout = (n, h, w, kind, images.scale)
        self.factor = 1
        self.size = n * h * w

    def level(self, factor):
        """The same bank at pyramid level ``factor`` (a power of two; 1: the images as
        stored), sharing its arrays."""
        return RayBank.from_arrays(dict(self.arrays(), factor=int(factor)))

    def max_factor(self):
        """The coarsest pyramid factor that leaves the images at least one pixel."""
        h, w = self.layout[1:3]
        return 1 << (min(h, w).bit_length() - 1)

    def arrays(self):
        """The bank's Dr.Jit arrays and its layout and level as Python values (a frozen step
        takes them as inputs; another layout or level records the step anew)."""
        return {'cameras': self.cameras, 'pixels': self.pixels, 'masks': self.masks,
                'layout': self.layout, 'factor': self.factor}

    @classmethod
    def from_arrays(cls, arrays):
        """A bank over what :meth:`arrays` returned."""
        bank = cls.__new__(cls)
        bank.cameras, bank.pixels, bank.layout = (arrays['cameras'], arrays['pixels'],
                                                  arrays['layout'])
        bank.masks = arrays.get('masks')
        bank.factor = int(arrays.get('factor', 1))
        n, h, w = bank.layout[:3]
        if bank.factor < 1 or h // bank.factor < 1 or w // bank.factor < 1:
            raise ValueError(f'pyramid factor {bank.factor} leaves no pixel of {w}x{h} images')
        bank.size = n * (h // bank.factor) * (w // bank.factor)
        return bank

    def _pixel(self, i):
        """``(image, x, y)`` of rays ``i`` at this level (UInt32)."""
        f = self.factor
        h, w = self.layout[1] // f, self.layout[2] // f
        image = i // (h * w)
        within = i - image * (h * w)                  # the pixel (x, y) in its image
        y = within // w
        return image, within - y * w, y

    def _camera_plane(self, image, x, y):
        """``K⁻¹ [u', v', 1] = (u, v, 1)`` at the centre ``(u', v')`` of this level's pixel
        ``(x, y)`` (in the stored image's pixel units), by back substitution (K is upper
        triangular), in Float64; and ``k(j)``, the gather of entry j of each ray's K."""
        K = self.cameras[0]
        f = self.factor

        def k(j):
            return dr.gather(_Float64, K, image * 5 + j)
        v = (_Float64(y) * f + 0.5 * f - k(4)) / k(3)
        u = (_Float64(x) * f + 0.5 * f - k(1) * v - k(2)) / k(0)
        return u, v, k

    def batch(self, index, footprint: bool = False):
        """``(rays, colour)`` of the rays ``index``: :class:`~mi_nerfpp.core.rays.Rays` with their
        training ``image`` (and their :meth:`footprint` when asked), and the pixels' colour."""
        i = mi.UInt32(index)
        image, x, y = self._pixel(i)
        u, v, _ = self._camera_plane(image, x, y)
        _, R, center = self.cameras
        d = [dr.gather(_Float64, R, image * 9 + 3 * a) * u
             + dr.gather(_Float64, R, image * 9 + 3 * a + 1) * v
             + dr.gather(_Float64, R, image * 9 + 3 * a + 2) for a in range(3)]
        norm = dr.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        o = [dr.gather(_Float64, center, image * 3 + a) for a in range(3)]
        rays = Rays(mi.Point3f(*[mi.Float(c) for c in o]),
                    mi.Vector3f(*[mi.Float(c / norm) for c in d]), image=image,
                    footprint=self.footprint(index) if footprint else None)
        return rays, mi.Color3f(*self._color(image, x, y))

    def footprint(self, index):
        """The pixel footprint of the rays ``index``: the width of their pixel at this level
        per unit distance, ``F·sqrt(cos³θ / (fx·fy))`` (the square root of the pixel's solid
        angle, θ the ray's angle to the optical axis), as
        :func:`~mi_nerfpp.core.geometry.pixel_footprint` measures it on a Mitsuba camera."""
        image, x, y = self._pixel(mi.UInt32(index))
        u, v, k = self._camera_plane(image, x, y)
        cos = dr.rsqrt(u * u + v * v + 1.0)
        return mi.Float(self.factor * dr.sqrt(cos * cos * cos / (k(0) * k(3))))

    def images(self, index):
        """The training-image index of the rays ``index`` (UInt32)."""
        return self._pixel(mi.UInt32(index))[0]

    def mask(self, index, least: bool = False):
        """The mask coverage of the rays ``index`` in [0, 1] (Float; the bank has masks): the
        mean over their pixel block at a pyramid level, or with ``least`` its least pixel's
        (a block's colour holds what any of its pixels shows)."""
        image, x, y = self._pixel(mi.UInt32(index))
        n, h, w = self.layout[:3]
        f = self.factor
        first = image * (h * w) + (y * f) * w + x * f
        total = None
        for dy in range(f):
            for dx in range(f):
                value = mi.UInt32(dr.gather(_UInt8, self.masks, first + (dy * w + dx)))
                total = value if total is None else (
                    dr.minimum(total, value) if least else total + value)
        return mi.Float(total) / (255.0 * (1 if least else f * f))

    def _color(self, image, x, y):
        """The colour (three Floats) of this level's pixels ``(x, y)`` of ``image``: the mean
        of the stored F x F block, summed in Float64 (integers exactly) and rounded once."""
        n, h, w, kind, scale = self.layout
        f = self.factor
        first = image * (h * w) + (y * f) * w + x * f      # the block's top-left pixel
        out = []
        for c in range(3):
            total = None
            for dy in range(f):
                for dx in range(f):
                    value = self._stored(3 * (first + (dy * w + dx)) + c)
                    total = value if total is None else total + value
            if kind in ('uint8', 'uint16'):
                # In Float64, then rounded: the float32 quotient value / scale, as NumPy's.
                out.append(mi.Float(_Float64(total) / (scale * f * f)))
            else:                                   # exact for F = 1
                out.append(mi.Float(total / (f * f)))
        return out

    def _stored(self, at):
        """The stored value at flat position ``at``: UInt32 for integer stores, Float64 for
        float stores."""
        kind = self.layout[3]
        if kind == 'uint8':
            return mi.UInt32(dr.gather(_UInt8, self.pixels, at))
        if kind == 'uint16':                      # little-endian byte pairs
            return (mi.UInt32(dr.gather(_UInt8, self.pixels, 2 * at))
                    | (mi.UInt32(dr.gather(_UInt8, self.pixels, 2 * at + 1)) << 8))
        return _Float64(dr.gather(_STORE_TYPES[kind], self.pixels, at))


_Float64 = dr.float64_array_t(mi.Float)
_UInt8 = dr.uint8_array_t(mi.Float)
# The Dr.Jit array a split's stored dtype is kept in (16-bit integers as their bytes).
_STORE_TYPES = {'uint8': _UInt8, 'uint16': _UInt8, 'float16': dr.float16_array_t(mi.Float),
                'float32': mi.Float}


def _owned_concatenation(arrays, tp):
    """The NumPy ``arrays`` one after the other in one Dr.Jit array of type ``tp`` that owns its
    memory (:func:`~mi_nerfpp.core.arrays.owned`), copied one array at a time: no concatenated
    copy of them all is ever made."""
    out = dr.empty(tp, sum(a.size for a in arrays))
    offset = 0
    for a in arrays:
        src = tp(np.ascontiguousarray(a).ravel())
        dr.scatter(out, src, dr.arange(mi.UInt32, a.size) + dr.opaque(mi.UInt32, offset))
        dr.eval(out)
        dr.sync_thread()      # the copy is done before NumPy may move on
        offset += a.size
    return out
