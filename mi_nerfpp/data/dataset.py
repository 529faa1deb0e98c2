"""The in-memory dataset every reader produces, and the checks and normalization they share.

A reader turns its file format into :class:`Frame` records (an image path, a pose and a rule
for the intrinsics); :func:`make_split` loads and validates the images and poses of one split,
and :func:`make_dataset` checks the splits together and normalizes the cameras into the unit
sphere as NeRF++ requires.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable

import numpy as np

from mi_nerfpp.core.budget import images_budget
from mi_nerfpp.core.frame import Normalization
from mi_nerfpp.data import masks
from mi_nerfpp.data.cameras import Camera
from mi_nerfpp.data.errors import DatasetError
from mi_nerfpp.data.images import image_size, read_stored_image
from mi_nerfpp.data.storage import (MAX_STORED_BYTES, StoredImages,
                                    bytes_per_pixel, store, stored_depth)

SPLITS = ('train', 'validation', 'test')

# The automatic downscale counts the training images twice: as loaded, and in the store that
# the training step gathers its pixels from (:class:`mi_nerfpp.training.raybank.RayBank`).
TRAIN_COPIES = 2
# Camera positions a capture may have. Beyond this distance from the origin (world units) the
# centres cannot be normalized in floating point (their spread is lost to rounding, squares
# overflow); a camera farther than this many times the typical camera's distance from the
# capture's centre (a wrong pose) would squeeze the others into a speck of the unit sphere.
MAX_CAMERA_DISTANCE = 1e12
MAX_CAMERA_SPREAD = 1e3


@dataclass
class Split:
    """Cameras and their images for one split; all images of a split have the same size.

    Attributes:
        cameras: one :class:`Camera` per image (OpenCV pose, normalized world).
        image_paths: the image files the images were read from.
        images: the images, already downscaled and composited over the background, kept
            compactly (:class:`~mi_nerfpp.data.storage.StoredImages`): ``images[i]`` is a
            float32 (H, W, 3) array, ``images.stored`` the arrays as kept. Float arrays given
            here are kept as float32.
        masks: per image its mask as 8-bit coverage (uint8 (H, W), 255 = kept; see
            :mod:`.masks`) or None where it has none; None when no image of the split has one.
    """

    cameras: list[Camera]
    image_paths: list[str]
    images: StoredImages
    masks: list[np.ndarray | None] | None = None

    def __post_init__(self):
        self.images = StoredImages.of(self.images)

    def __len__(self) -> int:
        return len(self.cameras)


@dataclass
class Dataset:
    """A posed image collection split into train / validation / test.

    Attributes:
        train, validation, test: the splits (validation and test may be empty).
        format: the reader that produced it: 'nerfpp', 'blender', 'llff' or 'colmap'.
        root: the folder (or file) it was read from.
        color_space: 'srgb' (PNG/JPEG pixel values) or 'linear' (EXR).
        normalization: the :class:`~mi_nerfpp.core.frame.Normalization` already applied to every
            camera; the identity when the cameras were inside the unit sphere as read.
        downscale: the factor the images were shrunk by (chosen by :class:`AutoDownscale`
            when the reader was given ``downscale=None`` or one).
    """

    train: Split
    validation: Split
    test: Split
    format: str
    root: str
    color_space: str
    normalization: Normalization
    downscale: int = 1

    @property
    def has_masks(self) -> bool:
        """Whether any photo of any split has a mask (:mod:`.masks`)."""
        return any(split.masks is not None for split in (self.train, self.validation, self.test))


@dataclass
class Frame:
    """One image as a reader describes it, before the image is loaded.

    Attributes:
        image_path: the image file.
        c2w: 4x4 camera-to-world, OpenCV convention.
        intrinsics: maps the image's (width, height) in pixels to its 3x3 K (some formats
            define focal lengths relative to the image size).
        source: where the pose came from, for error messages.
        name: camera name (usually the image stem).
        size: (width, height) the format declares, checked against the image; None if none.
        intrinsics_source: where the intrinsics came from, if not from ``source``.
        mask_path: the photo's mask (:mod:`.masks`), None if it has none.
    """

    image_path: str
    c2w: np.ndarray
    intrinsics: Callable[[int, int], np.ndarray]
    source: str
    name: str
    size: tuple[int, int] | None = None
    intrinsics_source: str | None = None
    mask_path: str | None = None


MIN_IMAGE_SIZE = 3    # the smallest SSIM window (mi_nerfpp.training.metrics.SSIM_MIN_WIN_SIZE)


def make_split(frames: list[Frame], downscale: int = 1, background=(1.0, 1.0, 1.0)) -> Split:
    """Load and validate the images and cameras of one split; the images are kept compactly
    (:mod:`.storage`).

    Raises:
        DatasetError: unreadable images, images of different sizes, an image whose size differs
            from the one its metadata declares, non-finite or non-rigid poses, bad intrinsics.
    """
    cameras, paths, images, split_masks = [], [], [], []
    first_size = None
    for frame in frames:
        c2w = np.asarray(frame.c2w, dtype=np.float64)
        _check_pose(c2w, frame.source)
        image = read_stored_image(frame.image_path, background)
        height, width = image.shape[:2]
        if frame.size is not None and tuple(frame.size) != (width, height):
            raise DatasetError(
                f'{frame.image_path}: image is {width}x{height} but {frame.source} declares '
                f'{frame.size[0]}x{frame.size[1]}: fix the metadata or resize the image')
        if first_size is None:
            first_size = (width, height)
        elif (width, height) != first_size:
            raise DatasetError(
                f'{frame.image_path}: image is {width}x{height} but {paths[0]} in the same split '
                f'is {first_size[0]}x{first_size[1]}: all images of a split must have the same '
                f'size')
        K = np.asarray(frame.intrinsics(width, height), dtype=np.float64)
        _check_intrinsics(K, frame.intrinsics_source or frame.source)
        camera = Camera(K=K, c2w=c2w, width=width, height=height, name=frame.name)
        _check_downscale(frame.image_path, width, height, downscale)
        image, scale = store(image, downscale)
        if downscale != 1:
            camera = camera.downscaled(downscale)
        cameras.append(camera)
        paths.append(frame.image_path)
        images.append((image, scale))
        split_masks.append(None if frame.mask_path is None else masks.stored_mask(
            masks.read_mask(frame.mask_path, (width, height), frame.image_path), downscale))
    mask_paths = [frame.mask_path for frame in frames]
    masks.check_coverage(mask_paths, paths, os.path.dirname(paths[0]) if paths else '')
    return Split(cameras=cameras, image_paths=paths, images=StoredImages.unify(images),
                 masks=split_masks if any(m is not None for m in split_masks) else None)


def _check_downscale(path, width, height, downscale):
    """Refuse a ``downscale`` that leaves an image of ``width`` x ``height`` under
    :data:`MIN_IMAGE_SIZE` pixels a side, naming the largest factor that fits."""
    if min(width, height) // downscale >= MIN_IMAGE_SIZE:
        return
    largest = min(width, height) // MIN_IMAGE_SIZE
    fix = (f'the largest --downscale that fits is {largest}' if largest >= 1 else
           'the image is too small at any --downscale: use larger images')
    after = f' after --downscale {downscale} (of {width}x{height})' if downscale != 1 else ''
    raise DatasetError(
        f'{path}: image is {width // downscale}x{height // downscale} pixels{after}; training '
        f'and evaluation (SSIM) need at least {MIN_IMAGE_SIZE}x{MIN_IMAGE_SIZE}: {fix}')


def stored_bytes(images, factor: int) -> int:
    """Bytes that images of ``(width, height, depth)`` (bits per channel, 8 or 16) take in
    their store (:mod:`.storage`) when downscaled by ``factor``."""
    return sum((w // factor) * (h // factor) * bytes_per_pixel(depth, factor)
               for w, h, depth in images)


@dataclass
class AutoDownscale:
    """``downscale=AutoDownscale(budget)``: the images are kept at their own resolution if
    they fit ``budget`` bytes, else shrunk by the smallest factor at which they do.

    The images counted are the training images :data:`TRAIN_COPIES` times and the held-out
    ones once, as stored (:func:`stored_bytes`, sizes and bit depths read from the file
    headers before any image is decoded); a training store must also stay under
    :data:`~mi_nerfpp.data.storage.MAX_STORED_BYTES`. ``budget`` None: what
    :func:`mi_nerfpp.core.budget.images_budget` leaves beside the process; a training run
    passes what its plan leaves (:attr:`mi_nerfpp.core.budget.Plan.images`).

    After loading, ``factor`` is the factor chosen, ``needed`` the bytes the images take at
    their own resolution, ``used`` at the factor chosen and ``size`` the (width, height) of
    the first training image as read (what :func:`mi_nerfpp.jobs.run.prepare` announces).
    """
    budget: int | None = None
    factor: int | None = None
    needed: int | None = None
    used: int | None = None
    size: tuple[int, int] | None = None

    def choose(self, frames: dict[str, list[Frame]]) -> int:
        """The factor for the splits' ``frames`` (split name -> frames): :meth:`pick` of their
        images' sizes and bit depths."""
        info = {name: [(*image_size(f.image_path), stored_depth(f.image_path)) for f in fs]
                for name, fs in frames.items()}
        where = frames['train'][0].image_path if frames.get('train') else 'the images'
        return self.pick(info.get('train', []),
                         [i for name, images in info.items() if name != 'train' for i in images],
                         where)

    def pick(self, train, held_out, where='the images') -> int:
        """The factor for training and held-out images of ``(width, height, depth)``, recorded
        here. Raises :class:`DatasetError` (naming ``where``) when no factor makes them fit."""
        if self.budget is None:
            self.budget = images_budget()

        def cost(factor):
            return TRAIN_COPIES * stored_bytes(train, factor) + stored_bytes(held_out, factor)

        def fits(factor):
            return (cost(factor) <= self.budget
                    and stored_bytes(train, factor) <= MAX_STORED_BYTES)

        # The largest factor that leaves images of at least MIN_IMAGE_SIZE pixels.
        largest = max(1, min([min(w, h) for w, h, _ in train + held_out], default=1)
                      // MIN_IMAGE_SIZE)
        factor = 1
        while factor < largest and not fits(factor):
            factor += 1
        self.factor, self.needed, self.used = factor, cost(1), cost(factor)
        self.size = train[0][:2] if train else None
        if not fits(factor):
            raise DatasetError(
                f'{where}: the {len(train) + len(held_out)} images need {self.used / 2**30:.1f} '
                f'GiB of memory even downscaled by {factor}, and {self.budget / 2**30:.1f} GiB '
                f'are left for them: use fewer images or free memory, or choose a --downscale '
                f'to train anyway')
        return factor


def make_splits(frames: dict[str, list[Frame]], downscale: int | None | AutoDownscale = 1,
                background=(1.0, 1.0, 1.0)) -> tuple[dict[str, Split], int]:
    """:func:`make_split` of each split of ``frames`` (split name -> frames), all shrunk by one
    factor: ``downscale``, or the one :class:`AutoDownscale` chooses (None: with its default
    budget).

    Returns:
        ``({split name: Split}, factor used)``.
    """
    check_camera_positions([f for name in SPLITS for f in frames.get(name, [])])
    if downscale is None:
        downscale = AutoDownscale()
    if isinstance(downscale, AutoDownscale):
        downscale = downscale.choose(frames)
    splits = {name: make_split(frames.get(name, []), downscale, background) for name in SPLITS}
    return splits, downscale


def make_dataset(format: str, root: str, train: Split, validation: Split, test: Split,
                 train_source: str, downscale: int = 1) -> Dataset:
    """Assemble the splits, normalizing all cameras into the unit sphere when needed.

    One normalization (NeRF++'s rule, :meth:`Normalization.for_cameras`) computed over the cameras of
    all splits is applied to every split, so that all of them share one world.

    Args:
        train_source: where the train split was looked for, named when it is empty.

    Raises:
        DatasetError: an empty train split, or EXR mixed with PNG/JPEG images.
    """
    if not len(train):
        raise DatasetError(f'{train_source}: the train split has no images; add posed '
                           f'training images there')
    splits = {'train': train, 'validation': validation, 'test': test}
    paths = [p for split in splits.values() for p in split.image_paths]
    is_exr = [p.lower().endswith('.exr') for p in paths]
    if any(is_exr) and not all(is_exr):
        raise DatasetError(f'{root}: mixes EXR (linear) and PNG/JPEG (sRGB) images, e.g. '
                           f'{paths[is_exr.index(True)]} and {paths[is_exr.index(False)]}: '
                           f'use one kind of image for the whole dataset')
    all_cameras = [cam for split in splits.values() for cam in split.cameras]
    try:
        normalization = Normalization.for_cameras(all_cameras)
    except ValueError as e:
        raise DatasetError(f'{root}: {e}') from e
    for split in splits.values():
        split.cameras = [normalization.to_model_camera(cam) for cam in split.cameras]
    return Dataset(**splits, format=format, root=os.fspath(root),
                   color_space='linear' if all(is_exr) else 'srgb', normalization=normalization,
                   downscale=int(downscale))


def check_camera_positions(frames: list[Frame]) -> None:
    """Refuse camera centres that cannot be normalized (see :data:`MAX_CAMERA_DISTANCE`) and
    a camera far off the others (:data:`MAX_CAMERA_SPREAD` times the median distance from the
    median centre), naming its pose's source. Poses that are not 4x4 and finite are left to
    :func:`make_split`, which names what is wrong with them."""
    placed = []
    for frame in frames:
        c2w = np.asarray(frame.c2w, dtype=np.float64)
        if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
            continue
        largest = float(np.max(np.abs(c2w[:3, 3])))
        distance = largest * float(np.linalg.norm(c2w[:3, 3] / largest)) if largest else 0.0
        if not distance <= MAX_CAMERA_DISTANCE:
            raise DatasetError(f'{frame.source}: the camera is {distance:.3g} world units from '
                               f'the origin, beyond {MAX_CAMERA_DISTANCE:g}, where positions '
                               f'cannot be normalized in floating point: fix this pose or '
                               f'remove the camera')
        placed.append((frame, c2w[:3, 3]))
    if len(placed) < 3:
        return
    centres = np.stack([c for _, c in placed])
    offsets = np.linalg.norm(centres - np.median(centres, axis=0), axis=1)
    typical = float(np.median(offsets))
    far = int(np.argmax(offsets))
    if typical > 0 and offsets[far] > MAX_CAMERA_SPREAD * typical:
        raise DatasetError(f'{placed[far][0].source}: the camera is {offsets[far]:.3g} world '
                           f'units from the middle of the capture, {offsets[far] / typical:.3g} '
                           f'times the typical camera ({typical:.3g}): a wrong pose? It would '
                           f'squeeze the other cameras into a speck of the unit sphere; fix '
                           f'this pose or remove the camera')


def _check_pose(c2w: np.ndarray, source: str) -> None:
    if c2w.shape != (4, 4):
        raise DatasetError(f'{source}: camera-to-world matrix must be 4x4, got shape {c2w.shape}')
    if not np.all(np.isfinite(c2w)):
        raise DatasetError(f'{source}: camera pose has non-finite values (NaN or inf): remove '
                           f'this camera or fix its pose')
    rotation = c2w[:3, :3]
    if (not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-3)
            or np.linalg.det(rotation) < 0 or not np.allclose(c2w[3], [0, 0, 0, 1])):
        raise DatasetError(f'{source}: camera pose is not a rigid transform (its rotation has '
                           f'scale, shear or a mirror, or its last row is not 0 0 0 1): '
                           f'store poses as rotation + translation')


def _check_intrinsics(K: np.ndarray, source: str) -> None:
    if not np.all(np.isfinite(K)):
        raise DatasetError(f'{source}: intrinsics have non-finite values (NaN or inf)')
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise DatasetError(f'{source}: intrinsics are not a pinhole K = [[fx, s, cx], '
                           f'[0, fy, cy], [0, 0, 1]] with fx, fy > 0 (got {K.tolist()})')
