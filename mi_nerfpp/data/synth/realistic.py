"""A realistic stand-in of a phone capture: a clean synthetic capture degraded as photos are.

Real photos differ from a clean render in ways no single scene explains, and defaults chosen on
clean captures can chase them (issue 58: the error map and the sparse level were chosen on
gt_plaza and cost 1.2 dB on a phone capture). :func:`realistic_copy` turns a clean NeRF++-layout
capture (:func:`mi_nerfpp.data.synth.synthesize`, whose ``gt/*.exr`` hold the linear render)
into a ``transforms.json`` dataset whose *training* photos carry, in the order a camera applies
them:

0. **weather** (off unless asked, :meth:`Realism.in_the_wild`): the sky tinted and a grey haze
   over the distance, both changing from view to view;
1. **transients**: an opaque object (a person-sized shape of one colour, shaded) in a few views;
2. **motion blur**: a straight streak of ``blur_length`` of the width in a share of the views;
3. **lens distortion**: OpenCV's ``k1 k2 p1 p2``, written into ``transforms_train.json`` (the
   reader undistorts with COLMAP, :mod:`mi_nerfpp.data.undistort`). The coefficients are
   pincushion (``k1 > 0``), so that every distorted pixel lies inside the clean render;
4. **auto-exposure and white balance**: per-view gains ``2^(e + w_c)`` in linear light (the
   first view too);
5. **sensor noise**: Poisson-Gaussian in linear light (variance ``shot · x + read``);
6. **JPEG**: clipped, sRGB-encoded, 8-bit JPEG at ``jpeg_quality``;
7. **pose error**: every training pose but the first turned by ``pose_degrees`` about a random
   axis and moved by ``pose_fraction`` of the capture's radius, as structure from motion errs.

The validation and test views stay clean pinhole PNGs at their true poses: the ground truth a
run's held-out scores are measured against. ``realistic.json`` records every value applied
(per view), and ``transients/NNNNNN.png`` the transients' masks of the training views (with
``Realism(masks=True)`` the photos also ship masks that leave the transients out). Each
degradation is switched off by setting its amount to 0 (:class:`Realism`), which is how
``benchmarks/realistic.py`` prices them one at a time.
"""
from __future__ import annotations

import dataclasses
import json
import os

import imageio.v3 as iio
import numpy as np
from scipy.ndimage import convolve
from tqdm import tqdm

from mi_nerfpp.core.color import to_srgb8
from mi_nerfpp.core.poses import corrected_c2w
from mi_nerfpp.data.cameras import opencv_to_opengl
from mi_nerfpp.data.nerfpp import _read_matrix
from mi_nerfpp.data.undistort import _pixel_map, warp
from mi_nerfpp.files.atomic import atomic_write_path, remove_entries
from mi_nerfpp.files.exr import read_exr
from mi_nerfpp.files.readers import read_image

REALISTIC_FILE = 'realistic.json'
# Where ``synth --realistic`` keeps the clean capture the stand-in is made from, inside DATA.
CLEAN_FOLDER = 'clean'
# A phone's main camera: its photo size (4032x3024, 12 MP); the stand-in is rendered at 1/4 or
# 1/2 of it.
PHONE_RES = (4032, 3024)
# The splits of the stand-in, as the transforms files name them.
SPLIT_FILES = {'train': 'transforms_train.json', 'validation': 'transforms_val.json',
               'test': 'transforms_test.json'}


@dataclasses.dataclass(frozen=True)
class Realism:
    """How far the stand-in departs from the clean capture; 0 switches a degradation off."""

    # Lens: OpenCV's radial and tangential terms (pincushion, see the module docstring).
    k1: float = 0.04
    k2: float = 0.01
    p1: float = 4e-4
    p2: float = -3e-4
    # Auto-exposure (stops, uniform in +-) and white balance (stops per channel, uniform in +-).
    exposure_stops: float = 0.4
    white_balance: float = 0.08
    # Sensor noise in linear light: variance shot * x + read (a phone at moderate ISO, after
    # its denoiser: ~36 dB at mid grey).
    shot_noise: float = 1e-3
    read_noise: float = 1e-5
    # JPEG quality (0: PNG, no compression).
    jpeg_quality: int = 88
    # Motion blur: the share of training views blurred and the streak's length (of the width).
    blur_share: float = 0.1
    blur_length: float = 0.008
    # Pose error: rotation (degrees) and shift (of the capture's radius), as COLMAP errs.
    pose_degrees: float = 0.3
    pose_fraction: float = 0.003
    # Transients: the share of training views with an object no other view has.
    transient_share: float = 0.05
    # Weather, per view (a collection shot over years: clear to overcast): the sky (what no
    # surface hides, depth 0) tinted by up to this many stops per channel, and a haze of a
    # per-view grey blended over the surfaces with weight haze * u * (1 - exp(-z / HAZE_DEPTH))
    # (u uniform in [0, 1]); 0: the scene looks the same in every photo.
    sky_stops: float = 0.0
    haze: float = 0.0
    # Whether the training photos ship masks (``masks/train/NNNNNN.png``, named by each frame's
    # ``mask_path``): black on the transient, white elsewhere, as a capture whose people were
    # masked (:mod:`mi_nerfpp.data.masks`). Phone captures ship none: off by default.
    masks: bool = False

    def lens(self) -> bool:
        return any(v != 0 for v in (self.k1, self.k2, self.p1, self.p2))

    @classmethod
    def in_the_wild(cls) -> 'Realism':
        """A photo collection of one place by many people over years (issue 60): the phone's
        degradations, exposure and white balance twice as wide, the weather changing the sky
        and the haze from photo to photo, and a passer-by or a vehicle in a third of the
        photos."""
        return cls(exposure_stops=0.8, white_balance=0.16, sky_stops=0.6, haze=0.5,
                   transient_share=0.3)

    def without(self, *names: str) -> 'Realism':
        """This realism with the named degradations switched off (see :data:`DEGRADATIONS`)."""
        changes = {}
        for name in names:
            if name not in DEGRADATIONS:
                raise ValueError(f'unknown degradation {name!r}: one of '
                                 f'{", ".join(DEGRADATIONS)}')
            changes.update({field: 0 for field in DEGRADATIONS[name]})
        return dataclasses.replace(self, **changes)


# Each degradation and the fields that switch it off.
DEGRADATIONS = {
    'lens': ('k1', 'k2', 'p1', 'p2'),
    'exposure': ('exposure_stops', 'white_balance'),
    'noise': ('shot_noise', 'read_noise'),
    'jpeg': ('jpeg_quality',),
    'blur': ('blur_share',),
    'poses': ('pose_degrees', 'pose_fraction'),
    'transients': ('transient_share',),
    'weather': ('sky_stops', 'haze'),
}
# The distance (world units) over which the haze of :attr:`Realism.haze` builds up.
HAZE_DEPTH = 15.0


def realistic_copy(src, out, realism: Realism = Realism(), seed: int = 0,
                   progress: bool = True) -> dict:
    """Write the stand-in of the clean NeRF++ capture ``src`` into ``out`` (see the module
    docstring) and return what ``realistic.json`` records.

    ``out`` must not exist, be empty but for ``src`` itself, or hold an earlier stand-in (its
    ``realistic.json``), which is replaced. Raises FileNotFoundError for a ``src`` that is no synthetic capture (it needs
    ``train/gt/*.exr``), FileExistsError for an ``out`` that holds something else.
    """
    src, out = os.fspath(src), os.fspath(out)
    if not os.path.isdir(os.path.join(src, 'train', 'gt')):
        raise FileNotFoundError(f'{src}: not a synthetic capture (no train/gt folder of linear '
                                f'renders); make one with python -m mi_nerfpp synth')
    _prepare(out, src)
    rng = np.random.default_rng(seed)
    record = {'format': 'mi-nerfpp-realistic', 'source': os.path.abspath(src), 'seed': seed,
              'realism': dataclasses.asdict(realism), 'views': {}}
    splits = {}
    for split in SPLIT_FILES:
        folder = os.path.join(src, split, 'pose')
        stems = sorted(os.path.splitext(n)[0] for n in os.listdir(folder)) \
            if os.path.isdir(folder) else []
        splits[split] = stems
    train = splits['train']
    c2w = [_read_matrix(os.path.join(src, 'train', 'pose', s + '.txt')) for s in train]
    centers = np.stack([m[:3, 3] for m in c2w]) if c2w else np.zeros((1, 3))
    radius = float(np.max(np.linalg.norm(centers - centers.mean(axis=0), axis=1)))
    n = len(train)
    blurred = set(rng.choice(n, int(round(realism.blur_share * n)), replace=False).tolist())
    transient = set(rng.choice(n, int(round(realism.transient_share * n)),
                               replace=False).tolist())

    bar = tqdm(total=sum(len(s) for s in splits.values()), desc='realistic stand-in',
               unit='view', disable=not progress)
    for split, stems in splits.items():
        frames, views = [], []
        os.makedirs(os.path.join(out, 'images', split), exist_ok=True)
        for i, stem in enumerate(stems):
            K = _read_matrix(os.path.join(src, split, 'intrinsics', stem + '.txt'))[:3, :3]
            pose = _read_matrix(os.path.join(src, split, 'pose', stem + '.txt'))
            if split == 'train':
                image, view, pose = _degrade(src, stem, K, pose, i, realism, rng, radius,
                                             i in blurred, i in transient, out)
                ext = '.jpg' if realism.jpeg_quality > 0 else '.png'
            else:   # the clean ground truth at its true pose
                image = read_image(os.path.join(src, split, 'rgb', stem + '.png'),
                                   what='capture image',
                                   remedy='write the capture again')[..., :3]
                view, ext = {}, '.png'
            name = os.path.join('images', split, stem + ext)
            _write_image(os.path.join(out, name), image, realism.jpeg_quality)
            h, w = image.shape[:2]
            frame = {'file_path': name, 'transform_matrix': opencv_to_opengl(pose).tolist(),
                     'fl_x': float(K[0, 0]), 'fl_y': float(K[1, 1]),
                     'cx': float(K[0, 2]), 'cy': float(K[1, 2]), 'w': w, 'h': h}
            if split == 'train' and realism.lens():
                frame.update(camera_model='OPENCV', k1=realism.k1, k2=realism.k2,
                             p1=realism.p1, p2=realism.p2)
            if split == 'train' and realism.masks:
                frame['mask_path'] = _write_mask(out, stem, view.pop('transient_mask', None),
                                                 (h, w), K, realism)
            view.pop('transient_mask', None)
            frames.append(frame)
            views.append(dict(view, name=stem))
            bar.update(1)
        record['views'][split] = views
        _write_json(os.path.join(out, SPLIT_FILES[split]), {'frames': frames})
    bar.close()
    record['radius'] = radius
    _write_json(os.path.join(out, REALISTIC_FILE), record)
    return record


def _prepare(out: str, src: str) -> None:
    if os.path.exists(out) and not os.path.isdir(out):
        raise FileExistsError(f'{out}: exists and is not a folder; choose another folder')
    inside = os.path.realpath(os.path.dirname(os.path.abspath(src))) == os.path.realpath(out)
    others = [n for n in os.listdir(out) if not (inside and n == os.path.basename(src))] \
        if os.path.isdir(out) else []
    if others:
        if not os.path.isfile(os.path.join(out, REALISTIC_FILE)):
            raise FileExistsError(f'{out}: folder is not empty and holds no {REALISTIC_FILE}; '
                                  f'the stand-in is written to a new folder or over its own '
                                  f'earlier copy')
        remove_entries(out, (REALISTIC_FILE, *SPLIT_FILES.values(), 'images', 'transients',
                             'masks',
                             *(os.path.splitext(f)[0] + '_undistorted'
                               for f in SPLIT_FILES.values())))
    os.makedirs(out, exist_ok=True)


def _degrade(src, stem, K, pose, index, r: Realism, rng, radius, blur, transient, out):
    """One training photo: ``(sRGB uint8 image, what was applied, the pose as given)``."""
    layers = read_exr(os.path.join(src, 'train', 'gt', stem + '.exr'))
    linear = np.stack([layers[c] for c in 'RGB'], axis=-1).astype(np.float64)
    linear = np.nan_to_num(np.maximum(linear, 0.0))
    h, w = linear.shape[:2]
    view = {}
    if r.sky_stops > 0 or r.haze > 0:
        linear = _weather(linear, layers['depth.Z'], r, rng, view)
    if transient:
        mask = _transient_mask(h, w, rng)
        color = rng.uniform(0.02, 0.6, 3)
        shade = np.linspace(1.3, 0.6, h)[:, None, None]     # lit from above
        linear = np.where(mask[..., None], color * shade, linear)
        os.makedirs(os.path.join(out, 'transients'), exist_ok=True)
        iio.imwrite(os.path.join(out, 'transients', stem + '.png'),
                    mask.astype(np.uint8) * 255)
        view['transient_pixels'] = int(mask.sum())
        view['transient_mask'] = mask
    if blur and r.blur_length > 0:
        length = max(2.0, r.blur_length * w)
        angle = float(rng.uniform(0.0, np.pi))
        linear = _motion_blur(linear, length, angle)
        view['blur'] = {'pixels': length, 'degrees': float(np.degrees(angle))}
    if r.lens():
        linear = _distort(linear, K, r)
    if r.exposure_stops > 0 or r.white_balance > 0:
        gain = 2.0 ** (rng.uniform(-r.exposure_stops, r.exposure_stops)
                       + rng.uniform(-r.white_balance, r.white_balance, 3))
        linear = linear * gain
        view['gain'] = [float(g) for g in gain]
    if r.shot_noise > 0 or r.read_noise > 0:
        sigma = np.sqrt(r.shot_noise * np.clip(linear, 0.0, 1.0) + r.read_noise)
        linear = linear + sigma * rng.standard_normal(linear.shape)
    given = pose
    if index > 0 and (r.pose_degrees > 0 or r.pose_fraction > 0):
        given = corrected_c2w(pose, np.concatenate([np.radians(r.pose_degrees) * _unit(rng),
                                                    r.pose_fraction * radius * _unit(rng)]))
    view['true_c2w'] = pose.tolist()
    view['given_c2w'] = given.tolist()
    return to_srgb8(np.clip(linear, 0.0, 1.0)), view, given


def _write_mask(out: str, stem: str, transient, size, K: np.ndarray, r: Realism) -> str:
    """Write the mask of training photo ``stem`` of ``size`` (height, width): black on its
    ``transient`` (None: none), through the photo's lens; returns its path relative to
    ``out``."""
    keep = np.ones(size) if transient is None else 1.0 - transient
    if r.lens():
        keep = _distort(np.repeat(keep[..., None], 3, axis=2), K, r)[..., 0]
    name = os.path.join('masks', 'train', stem + '.png')
    os.makedirs(os.path.join(out, 'masks', 'train'), exist_ok=True)
    with atomic_write_path(os.path.join(out, name)) as tmp:
        iio.imwrite(tmp, np.where(keep > 0.5, 255, 0).astype(np.uint8), extension='.png')
    return name


def _weather(linear, depth, r: Realism, rng, view) -> np.ndarray:
    """One photo's weather (:attr:`Realism.sky_stops`, :attr:`Realism.haze`), recorded in
    ``view``."""
    sky = (depth <= 0)[..., None]
    tint = 2.0 ** rng.uniform(-r.sky_stops, r.sky_stops, 3)
    amount = r.haze * rng.uniform(0.0, 1.0)
    grey = rng.uniform(0.3, 0.8)
    weight = (amount * (1.0 - np.exp(-np.maximum(depth, 0.0) / HAZE_DEPTH)))[..., None]
    view['weather'] = {'sky_gain': [float(t) for t in tint], 'haze': float(amount),
                       'haze_grey': float(grey)}
    return np.where(sky, linear * tint, (1.0 - weight) * linear + weight * grey)


def _unit(rng) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _transient_mask(h: int, w: int, rng) -> np.ndarray:
    """A person-sized shape standing on the image's lower part: a body and a head."""
    y, x = np.mgrid[0:h, 0:w] + 0.5
    height = rng.uniform(0.3, 0.5) * h
    cx = rng.uniform(0.15, 0.85) * w
    foot = rng.uniform(0.8, 1.0) * h
    body = (((x - cx) / (0.16 * height)) ** 2 + ((y - (foot - 0.38 * height))
                                                  / (0.38 * height)) ** 2) <= 1.0
    head = ((x - cx) ** 2 + (y - (foot - 0.86 * height)) ** 2) <= (0.1 * height) ** 2
    return body | head


def _motion_blur(image: np.ndarray, length: float, angle: float) -> np.ndarray:
    """``image`` convolved with a straight streak of ``length`` pixels at ``angle``."""
    size = int(np.ceil(length)) | 1
    kernel = np.zeros((size, size))
    c = size // 2
    for t in np.linspace(-0.5, 0.5, 8 * size):
        kernel[int(round(c + t * length * np.sin(angle))),
               int(round(c + t * length * np.cos(angle)))] += 1.0
    kernel /= kernel.sum()
    return np.stack([convolve(image[..., i], kernel, mode='nearest')
                     for i in range(image.shape[2])], axis=-1)


def _distort(image: np.ndarray, K: np.ndarray, r: Realism) -> np.ndarray:
    """The pinhole ``image`` (intrinsics ``K``) as the OpenCV lens of ``r`` records it."""
    import pycolmap  # deferred: COLMAP's native library, as in data.undistort
    h, w = image.shape[:2]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    pinhole = pycolmap.Camera(model='PINHOLE', width=w, height=h, params=[fx, fy, cx, cy])
    lens = pycolmap.Camera(model='OPENCV', width=w, height=h,
                           params=[fx, fy, cx, cy, r.k1, r.k2, r.p1, r.p2])
    # Each distorted pixel unprojected through the lens and projected by the pinhole.
    return warp(image.astype(np.float32), _pixel_map(pinhole, lens)).astype(np.float64)


def _write_image(path: str, image: np.ndarray, quality: int) -> None:
    with atomic_write_path(path) as tmp:
        if path.endswith('.jpg'):
            iio.imwrite(tmp, image, extension='.jpg', quality=int(quality))
        else:
            iio.imwrite(tmp, image, extension='.png')


def _write_json(path: str, data) -> None:
    with atomic_write_path(path) as tmp, open(tmp, 'w') as f:
        json.dump(data, f, indent=1)
        f.write('\n')
