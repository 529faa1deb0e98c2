"""How a split keeps its images in memory: compactly, at the precision of the files.

A training pixel costs what its file stored, not tens of bytes of float rays
(:class:`mi_nerfpp.training.raybank.RayBank` builds the rays of a batch from the cameras). Each split keeps
one kind of storage for all its images (:class:`StoredImages`), with the float value of a
stored value ``v``:

=========================================  ===========  =====================  =============
images (after compositing alpha at load)   stored as    float value            bytes / pixel
=========================================  ===========  =====================  =============
8-bit PNG / JPEG                           ``uint8``    ``v / 255``            3
16-bit PNG                                 ``uint16``   ``v / 65535``          6
8-bit, downscaled by K <= 16               ``uint16``   ``v / (255 K²)``       6
16-bit, or 8-bit downscaled by K > 16      ``uint16``   ``v / 65535``          6
EXR (linear, may exceed 1)                 ``float16``  ``v``                  6
EXR with a value beyond float16's range    ``float32``  ``v``                  12
=========================================  ===========  =====================  =============

Opaque 8- and 16-bit images are kept exactly as stored. A downscaled 8-bit image keeps the sum
of each K x K block (at most 255 K² <= 65280 for K <= 16), so its box average is exact too.
Alpha is composited over the background once at load and rounded to the file's levels (an
error of at most half a level, :func:`~mi_nerfpp.data.images.read_stored_image`); a 16-bit
image downscaled keeps its average rounded to 16 bits (at most 0.5 / 65535 off).

EXR (and any image that decodes to floats or to integers wider than 16 bits) is kept as
half floats: HDR values need a floating point, a 16-bit integer would need a
range (values above 1 clip) and gives dark linear values few levels (0.001 would be 1.5 %
off), while float16 keeps every value from 6e-5 to 65504 within 2^-11 (0.05 %) of itself,
and below 6e-5 within 2^-25 - and most EXR files store half floats to begin with, which come
through exactly. A split with a value beyond 65504 is kept in float32. (While a split of
float images loads, they are held in float32 until the last one has shown whether they fit.)
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mi_nerfpp.data.images import _png_bit_depth, downscale_image

# A split's store is addressed by 32-bit indices (the gathers of the training step): at most
# this many bytes.
MAX_STORED_BYTES = 2 ** 32 - 1
# Floats at most this large are kept as float16 (its largest finite value).
FLOAT16_MAX = float(np.finfo(np.float16).max)
# The largest downscale factor whose K x K block sums of 8-bit values fit 16 bits.
EXACT_SUM_FACTOR = 16


class StoredImages(Sequence):
    """The images of a split in one compact storage (see the module docstring).

    ``images[i]`` is image ``i`` as float32 (H, W, 3) - what every consumer of
    :attr:`Split.images <mi_nerfpp.data.dataset.Split.images>` reads, converted on access;
    :attr:`stored` are the arrays as kept, :attr:`scale` the divisor of integer values (1 for
    floats).
    """

    def __init__(self, stored, scale: float = 1.0):
        self.stored = list(stored)
        self.scale = float(scale)
        dtypes = {a.dtype for a in self.stored}
        if len(dtypes) > 1:
            raise ValueError(f'one storage per split, got {sorted(map(str, dtypes))}')

    @classmethod
    def of(cls, images):
        """``images`` as they are: StoredImages, or float arrays (kept as float32)."""
        if isinstance(images, StoredImages):
            return images
        return cls([np.ascontiguousarray(a, dtype=np.float32) for a in images])

    @classmethod
    def unify(cls, images: list[tuple[np.ndarray, float]]):
        """One storage for images stored one by one (``(array, scale)`` of :func:`store`,
        floats still in float32): float images as float16 if all their values are within its
        range, else float32; integers as they are if they agree, else all as ``uint16`` over
        65535 (8-bit values exactly); integers with floats all as float32."""
        if all(np.issubdtype(a.dtype, np.floating) for a, _ in images):
            half = all(np.abs(a).max(initial=0.0) <= FLOAT16_MAX for a, _ in images)
            return cls([a.astype(np.float16 if half else np.float32) for a, _ in images])
        if len({(a.dtype, s) for a, s in images}) == 1:
            return cls([a for a, _ in images], images[0][1])
        if all(np.issubdtype(a.dtype, np.integer) for a, _ in images):
            return cls([a if (a.dtype, s) == (np.uint16, 65535.0) else
                        np.round(a * (65535.0 / s)).astype(np.uint16) for a, s in images],
                       65535.0)
        return cls([to_float(a, s) for a, s in images])

    @property
    def dtype(self):
        """The stored dtype (float32 when there are no images)."""
        return self.stored[0].dtype if self.stored else np.dtype(np.float32)

    @property
    def nbytes(self) -> int:
        """Bytes the stored images take."""
        return sum(a.nbytes for a in self.stored)

    def __len__(self) -> int:
        return len(self.stored)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        return to_float(self.stored[index], self.scale)


def to_float(stored: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Stored values as float32 (integers divided by ``scale`` in float32: for 8- and 16-bit
    files exactly what :func:`~mi_nerfpp.data.images.read_image` returns)."""
    if np.issubdtype(stored.dtype, np.integer):
        return stored.astype(np.float32) / np.float32(scale)
    return stored.astype(np.float32)


def store(image: np.ndarray, factor: int = 1) -> tuple[np.ndarray, float]:
    """One image as :func:`~mi_nerfpp.data.images.read_stored_image` read it, downscaled by
    ``factor`` (box average, as :func:`~mi_nerfpp.data.images.downscale_image`) and kept as
    the module docstring says: ``(stored array, scale)``; float images are returned in
    float32, for :meth:`StoredImages.unify` to choose their storage for the whole split.

    Raises:
        ValueError: a factor the image is too small for.
    """
    factor = int(factor)
    if image.dtype == np.uint8 and factor == 1:
        return image, 255.0
    if image.dtype == np.uint8 and factor <= EXACT_SUM_FACTOR:     # the block sums, exactly
        sums = np.round(downscale_image(image.astype(np.float64), factor) * factor ** 2)
        return sums.astype(np.uint16), 255.0 * factor ** 2
    if image.dtype in (np.uint8, np.uint16):
        top = float(np.iinfo(image.dtype).max)
        small = downscale_image(image.astype(np.float32) / np.float32(top), factor)
        return np.round(small * 65535.0).astype(np.uint16), 65535.0
    # Floats stay float32 here: StoredImages.unify makes them float16 if the whole split fits.
    return downscale_image(image.astype(np.float32), factor), 1.0


def bytes_per_pixel(depth: int, factor: int = 1) -> int:
    """Bytes :func:`store` keeps per pixel of an image of ``depth`` bits per channel (8, 16;
    16 also for EXR, which is kept as float16) downscaled by ``factor``."""
    return 3 if depth == 8 and factor == 1 else 6


def stored_depth(path) -> int:
    """Bits per channel that :func:`store` keeps of the image file ``path``, from its header:
    16 for 16-bit PNG and for EXR (float16), 8 for the rest."""
    path = str(path)
    if path.lower().endswith('.exr'):
        return 16
    try:
        return 16 if _png_bit_depth(path) == 16 else 8
    except OSError:
        return 8            # unreadable: reading the image says why
