"""COLMAP models: ``sparse/0/{cameras,images,points3D}.{bin,txt}`` plus an ``images/`` folder.

::

    ROOT/
        images/            the photos, named as in images.{bin,txt} (subfolders allowed)
        masks/             optional: the photos' masks, same names and stems, any image
                           extension (:mod:`mi_nerfpp.data.masks`)
        sparse/0/          cameras, images, points3D as .bin (COLMAP's default) or .txt
                           (``sparse/`` itself holding the files works too, as does pointing
                           at the model folder)

COLMAP's camera frame is OpenCV's (x right, y down, z forward) and an image's pose is
``cam_from_world``: the quaternion ``(qw, qx, qy, qz)`` and translation ``t`` of
``x_cam = R x_world + t``; the camera-to-world matrix is its inverse. Intrinsics come from the
camera model: ``SIMPLE_PINHOLE`` and ``PINHOLE`` are read as they are; the other
perspective models (``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``, ``FULL_OPENCV``, ``FOV``,
the division models) are read as a pinhole when their distortion parameters are all zero.
Otherwise (and always for the fisheye models, which are no pinhole even without distortion
coefficients) the images are undistorted to pinhole with COLMAP's own undistorter (pycolmap)
once, into ``ROOT/undistorted/`` (reused while it is newer than the model; see
:mod:`mi_nerfpp.data.undistort`), which is then read instead.

Every ``llff_hold``-th image (in sorted name order) is held out as the test split, as for
LLFF. The sparse points are read (:func:`read_model`) but do not enter the normalization:
cameras are normalized by NeRF++'s rule like every other format.
"""
from __future__ import annotations

import dataclasses
import os
import struct
from dataclasses import dataclass, field

import numpy as np

from mi_nerfpp.data import masks
from mi_nerfpp.data.dataset import Dataset, Frame, make_dataset, make_splits
from mi_nerfpp.data.errors import DatasetError
from mi_nerfpp.data.undistort import View, is_fresh, undistort_model, undistort_views

IMAGE_FOLDER = 'images'
UNDISTORTED_FOLDER = 'undistorted'
# Where the masks of an undistorted model are undistorted to (beside UNDISTORTED_FOLDER, which
# COLMAP's undistorter replaces as a whole).
UNDISTORTED_MASKS = 'undistorted_masks'
MODEL_FILES = ('cameras', 'images', 'points3D')

# COLMAP's camera models: id -> (name, number of parameters). The first parameters are the
# focal length(s) and principal point: (f, cx, cy) for SIMPLE_* / RADIAL* / DIVISION-1-focal
# models, (fx, fy, cx, cy) for the others; the rest are distortion.
CAMERA_MODELS = {
    0: ('SIMPLE_PINHOLE', 3), 1: ('PINHOLE', 4), 2: ('SIMPLE_RADIAL', 4), 3: ('RADIAL', 5),
    4: ('OPENCV', 8), 5: ('OPENCV_FISHEYE', 8), 6: ('FULL_OPENCV', 12), 7: ('FOV', 5),
    8: ('SIMPLE_RADIAL_FISHEYE', 4), 9: ('RADIAL_FISHEYE', 5), 10: ('THIN_PRISM_FISHEYE', 12),
    11: ('RAD_TAN_THIN_PRISM_FISHEYE', 16), 12: ('SIMPLE_DIVISION', 4), 13: ('DIVISION', 5),
    14: ('SIMPLE_FISHEYE', 3), 15: ('FISHEYE', 4), 16: ('EUCM', 6),
}
MODEL_IDS = {name: (model_id, n) for model_id, (name, n) in CAMERA_MODELS.items()}
# Models with a single focal length (f, cx, cy, ...).
_SINGLE_FOCAL = {'SIMPLE_PINHOLE', 'SIMPLE_RADIAL', 'RADIAL', 'SIMPLE_RADIAL_FISHEYE',
                 'RADIAL_FISHEYE', 'SIMPLE_DIVISION', 'SIMPLE_FISHEYE'}
# Models that are no pinhole even with zero extra parameters: the fisheye projections
# (r = f * theta, which the distortion coefficients only adjust; pycolmap's
# Camera.is_perspective_fisheye) and EUCM. FOV's omega = 0 is a pinhole.
_ALWAYS_DISTORTED = {'SIMPLE_RADIAL_FISHEYE', 'RADIAL_FISHEYE', 'OPENCV_FISHEYE',
                     'THIN_PRISM_FISHEYE', 'RAD_TAN_THIN_PRISM_FISHEYE', 'SIMPLE_FISHEYE',
                     'FISHEYE', 'EUCM'}


@dataclass
class ColmapCamera:
    """One COLMAP camera: its model name, image size and parameters."""

    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray

    @property
    def is_pinhole(self) -> bool:
        """Whether the model projects like a pinhole (no distortion) with these parameters."""
        return self.model not in _ALWAYS_DISTORTED and not self._has_coefficients

    @property
    def is_bare_fisheye(self) -> bool:
        """A fisheye whose distortion coefficients are all zero (or that has none):
        COLMAP's undistorter takes it for undistorted and leaves it as it is."""
        return self.model in _ALWAYS_DISTORTED and self.model != 'EUCM' \
            and not self._has_coefficients

    @property
    def _has_coefficients(self) -> bool:
        n_intrinsic = 3 if self.model in _SINGLE_FOCAL else 4
        return bool(np.any(self.params[n_intrinsic:] != 0))

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsics of the pinhole part (focal lengths and principal point)."""
        p = self.params
        fx, fy, cx, cy = ((p[0], p[0], p[1], p[2]) if self.model in _SINGLE_FOCAL
                          else (p[0], p[1], p[2], p[3]))
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


@dataclass
class ColmapImage:
    """One registered image: ``x_cam = R(qvec) x_world + tvec`` (OpenCV camera frame)."""

    image_id: int
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str

    @property
    def c2w(self) -> np.ndarray:
        """4x4 camera-to-world matrix, OpenCV convention."""
        R = quaternion_to_rotation(self.qvec)
        c2w = np.eye(4)
        c2w[:3, :3] = R.T
        c2w[:3, 3] = -R.T @ self.tvec
        return c2w


@dataclass
class ColmapModel:
    """A sparse COLMAP reconstruction as read from disk."""

    folder: str
    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (N, 3) world xyz


def quaternion_to_rotation(q) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``(w, x, y, z)`` (normalized first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


# ----------------------------------------------------------------------------- detection
def find_model(path) -> str | None:
    """The folder holding ``cameras`` and ``images`` (.bin or .txt) for a dataset ``path``:
    ``path`` itself, ``path/sparse/0`` or ``path/sparse``; None if there is none."""
    path = os.fspath(path)
    for folder in (path, os.path.join(path, 'sparse', '0'), os.path.join(path, 'sparse')):
        if _model_extension(folder) is not None:
            return folder
    return None


def is_colmap(path) -> bool:
    """Whether ``path`` is a folder with a COLMAP sparse model."""
    return os.path.isdir(path) and find_model(path) is not None


def _model_extension(folder: str) -> str | None:
    for ext in ('.bin', '.txt'):
        if all(os.path.isfile(os.path.join(folder, name + ext)) for name in ('cameras', 'images')):
            return ext
    return None


# ----------------------------------------------------------------------------- reading
def read_model(folder) -> ColmapModel:
    """Read ``cameras``, ``images`` and (if present) ``points3D`` of a COLMAP model folder,
    binary or text.

    Raises:
        DatasetError: missing or malformed files, an unknown camera model, an image whose
            camera is missing.
    """
    folder = os.fspath(folder)
    ext = _model_extension(folder)
    if ext is None:
        raise DatasetError(f'{folder}: no COLMAP model (cameras.bin + images.bin or '
                           f'cameras.txt + images.txt)')
    readers = {'.bin': (_read_cameras_bin, _read_images_bin, _read_points_bin),
               '.txt': (_read_cameras_txt, _read_images_txt, _read_points_txt)}[ext]
    model = ColmapModel(folder, {}, {})
    for reader, name in zip(readers, MODEL_FILES):
        path = os.path.join(folder, name + ext)
        if name == 'points3D' and not os.path.isfile(path):
            continue
        try:
            result = reader(path)
        except DatasetError:
            raise
        except (OSError, ValueError, IndexError, struct.error, UnicodeDecodeError) as e:
            raise DatasetError(f'{path}: cannot read this COLMAP {name} file '
                               f'({type(e).__name__}: {e}); re-export the model with COLMAP') \
                from e
        if name == 'cameras':
            model.cameras = result
        elif name == 'images':
            model.images = result
        else:
            model.points = result
    for image in model.images.values():
        if image.camera_id not in model.cameras:
            raise DatasetError(f'{os.path.join(folder, "images" + ext)}: image {image.name!r} '
                               f'uses camera {image.camera_id}, which cameras{ext} does not '
                               f'define')
    return model


def _camera(camera_id, model, width, height, params, source) -> ColmapCamera:
    if isinstance(model, int):
        if model not in CAMERA_MODELS:
            raise DatasetError(f'{source}: camera {camera_id} has unknown camera model id '
                               f'{model}; supported: {", ".join(MODEL_IDS)}')
        model = CAMERA_MODELS[model][0]
    if model not in MODEL_IDS:
        raise DatasetError(f'{source}: camera {camera_id} has unsupported camera model '
                           f'{model!r}; supported: {", ".join(MODEL_IDS)}')
    if not (0 < int(width) < 2 ** 31 and 0 < int(height) < 2 ** 31):
        raise DatasetError(f'{source}: camera {camera_id} ({model}) is {width}x{height} pixels: '
                           f'a camera needs a positive width and height; re-export the model '
                           f'with COLMAP')
    params = np.asarray(params, dtype=np.float64)
    if len(params) != MODEL_IDS[model][1]:
        raise DatasetError(f'{source}: camera {camera_id} ({model}) has {len(params)} '
                           f'parameters, the model has {MODEL_IDS[model][1]}')
    return ColmapCamera(int(camera_id), model, int(width), int(height), params)


class _Reader:
    def __init__(self, path):
        with open(path, 'rb') as f:
            self.data = f.read()
        self.pos = 0

    def read(self, fmt):
        values = struct.unpack_from('<' + fmt, self.data, self.pos)
        self.pos += struct.calcsize('<' + fmt)
        return values

    def skip(self, n):
        self.pos += n

    def string(self):
        end = self.data.index(b'\0', self.pos)
        text = self.data[self.pos:end].decode('utf-8')
        self.pos = end + 1
        return text


def _read_cameras_bin(path):
    r, cameras = _Reader(path), {}
    (count,) = r.read('Q')
    for _ in range(count):
        camera_id, model_id, width, height = r.read('iiQQ')
        if model_id not in CAMERA_MODELS:
            raise DatasetError(f'{path}: camera {camera_id} has unknown camera model id '
                               f'{model_id}; supported: {", ".join(MODEL_IDS)}')
        params = r.read('d' * CAMERA_MODELS[model_id][1])
        cameras[camera_id] = _camera(camera_id, model_id, width, height, params, path)
    return cameras


def _read_images_bin(path):
    r, images = _Reader(path), {}
    (count,) = r.read('Q')
    for _ in range(count):
        image_id, *pose, camera_id = r.read('idddddddi')
        name = r.string()
        (n_points,) = r.read('Q')
        r.skip(24 * n_points)  # x, y (double) and point3D_id (int64) per observation
        images[image_id] = ColmapImage(image_id, np.array(pose[:4]), np.array(pose[4:]),
                                       camera_id, name)
    return images


def _read_points_bin(path):
    r = _Reader(path)
    (count,) = r.read('Q')
    points = np.empty((count, 3))
    for i in range(count):
        points[i] = r.read('Qddd')[1:]
        r.skip(3 + 8)  # rgb (uint8 x 3), reprojection error (double)
        (track_length,) = r.read('Q')
        r.skip(8 * track_length)  # image_id, point2D_idx (int32 each)
    return points


def _text_lines(path):
    """(line number, line) of a COLMAP text file, comments dropped, empty lines kept."""
    with open(path, encoding='utf-8') as f:
        return [(i + 1, line.strip()) for i, line in enumerate(f) if not line.startswith('#')]


def _read_cameras_txt(path):
    cameras = {}
    for number, line in _text_lines(path):
        if not line:
            continue
        parts = line.split()
        if len(parts) < 4:
            raise DatasetError(f'{path}:{number}: expected CAMERA_ID MODEL WIDTH HEIGHT '
                               f'PARAMS..., got {line!r}')
        cameras[int(parts[0])] = _camera(int(parts[0]), parts[1], int(parts[2]), int(parts[3]),
                                         [float(v) for v in parts[4:]], f'{path}:{number}')
    return cameras


def _read_images_txt(path):
    images, lines, i = {}, _text_lines(path), 0
    while i < len(lines):
        number, line = lines[i]
        if not line:
            i += 1
            continue
        parts = line.split(maxsplit=9)
        if len(parts) != 10:
            raise DatasetError(f'{path}:{number}: expected IMAGE_ID QW QX QY QZ TX TY TZ '
                               f'CAMERA_ID NAME, got {line!r}')
        values = [float(v) for v in parts[1:8]]
        images[int(parts[0])] = ColmapImage(int(parts[0]), np.array(values[:4]),
                                            np.array(values[4:]), int(parts[8]), parts[9])
        i += 2  # the next line lists the image's 2D points (possibly empty)
    return images


def _read_points_txt(path):
    rows = [line.split()[1:4] for _, line in _text_lines(path) if line]
    return np.array(rows, dtype=np.float64).reshape(-1, 3)


# ----------------------------------------------------------------------------- datasets
def pinhole_model(root, model_folder: str | None = None, progress: bool = True) -> tuple[
        ColmapModel, str]:
    """The model of dataset ``root`` with pinhole cameras, and its image folder.

    A model with distortion is undistorted (once; see the module docstring).

    Raises:
        DatasetError: no model, no image folder, undistortion failing.
    """
    root = os.fspath(root)
    model_folder = model_folder or find_model(root)
    if model_folder is None:
        raise DatasetError(f'{root}: no COLMAP model found (looked for sparse/0/, sparse/ '
                           f'and the folder itself holding cameras.bin|txt and images.bin|txt)')
    model = read_model(model_folder)
    image_folder = os.path.join(root, IMAGE_FOLDER)
    if not os.path.isdir(image_folder):
        raise DatasetError(f'{image_folder}: missing folder; a COLMAP dataset keeps the images '
                           f'its model names in {IMAGE_FOLDER}/ next to sparse/')
    distorted = sorted({f'{c.camera_id} ({c.model})' for c in model.cameras.values()
                        if not c.is_pinhole})
    if not distorted:
        return model, image_folder
    bare = sorted({f'{c.camera_id} ({c.model})' for c in model.cameras.values()
                   if c.is_bare_fisheye})
    if bare:
        raise DatasetError(f'{model_folder}: cameras {", ".join(bare)} are fisheyes without '
                           f'distortion coefficients, which COLMAP\'s undistorter leaves as '
                           f'they are; undistort the images to pinhole yourself, or export the '
                           f'model as transforms.json (OPENCV_FISHEYE), which mi-nerfpp '
                           f'undistorts')
    out = os.path.join(root, UNDISTORTED_FOLDER)
    undistorted_model = os.path.join(out, 'sparse')
    if not _up_to_date(undistorted_model, model_folder):
        if progress:
            print(f'{root}: cameras {", ".join(distorted)} have lens distortion; undistorting '
                  f'the images to pinhole with COLMAP into {out}/ (done once)')
        undistort_model(model_folder, image_folder, out)
    return read_model(undistorted_model), os.path.join(out, IMAGE_FOLDER)


def _up_to_date(result_folder: str, source_folder: str) -> bool:
    """Whether the undistorted model in ``result_folder`` is newer than the model files."""
    if _model_extension(result_folder) is None:
        return False
    return is_fresh([os.path.join(result_folder, f) for f in os.listdir(result_folder)],
                    [os.path.join(source_folder, f) for f in os.listdir(source_folder)])


def colmap_frames(model: ColmapModel, image_folder: str) -> list[Frame]:
    """Frames of the registered images of a pinhole model, sorted by image name.

    Raises:
        DatasetError: distorted cameras, images missing from ``image_folder``.
    """
    frames = []
    source = os.path.join(model.folder, 'images')
    for image in sorted(model.images.values(), key=lambda im: im.name):
        camera = model.cameras[image.camera_id]
        if not camera.is_pinhole:
            raise DatasetError(f'{model.folder}: camera {camera.camera_id} ({camera.model}) '
                               f'has lens distortion {camera.params.tolist()}; undistort the '
                               f'images first (colmap image_undistorter)')
        path = os.path.join(image_folder, image.name)
        if not os.path.isfile(path):
            raise DatasetError(f'{path}: image {image.name!r} of the COLMAP model {source} is '
                               f'missing: put the images the model was made from in '
                               f'{image_folder}')
        frames.append(Frame(
            image_path=path, c2w=image.c2w,
            intrinsics=lambda width, height, K=camera.K, cam=camera, path=path: _scaled_K(
                K, cam, width, height, path),
            source=f'{source} (image {image.name!r})', name=os.path.splitext(image.name)[0],
            intrinsics_source=f'{os.path.join(model.folder, "cameras")} (camera '
                              f'{camera.camera_id})'))
    return frames


def with_masks(root: str, model: ColmapModel, frames: list[Frame],
               progress: bool = True) -> list[Frame]:
    """The frames with the masks of ``ROOT/masks/`` (:mod:`mi_nerfpp.data.masks`; the
    frames unchanged when there is no such folder). When ``model`` was undistorted, the masks
    are undistorted the same way, once, into ``ROOT/undistorted_masks/``."""
    folder = os.path.join(root, masks.FOLDER)
    if not os.path.isdir(folder):
        return frames
    by_name = {image.name: image for image in model.images.values()}
    found = {frame.image_path: masks.find_mask(folder, by_name[name].name)
             for frame, name in zip(frames, sorted(by_name))}
    original = read_model(find_model(root))
    if all(c.is_pinhole for c in original.cameras.values()):
        return [dataclasses.replace(f, mask_path=found[f.image_path]) for f in frames]
    # Undistorted with the original cameras, as the images were (the same pinhole rule).
    distorted = {image.name: original.cameras[image.camera_id]
                 for image in original.images.values()}
    views = [View(mask, os.path.splitext(name)[0] + '.png', distorted[name])
             for name, mask in zip(sorted(by_name), found.values()) if mask is not None]
    pinholes = iter(undistort_views(views, os.path.join(root, UNDISTORTED_MASKS),
                                    sources=[find_model(root)], what=f'{folder} (masks)',
                                    progress=progress))
    return [dataclasses.replace(f, mask_path=next(pinholes).image_path
                                if found[f.image_path] is not None else None) for f in frames]


def _scaled_K(K, camera: ColmapCamera, width: int, height: int, path: str) -> np.ndarray:
    """K for an image of the given size (COLMAP's, rescaled if the image was resized
    uniformly, e.g. the ``images_4`` convention)."""
    sx, sy = width / camera.width, height / camera.height
    if abs(sx - sy) > 0.01 * max(sx, sy) + 1.0 / min(camera.width, camera.height):
        raise DatasetError(f'{path}: image is {width}x{height} but its COLMAP camera '
                           f'{camera.camera_id} is {camera.width}x{camera.height}; the aspect '
                           f'ratios differ (is the photo rotated by its EXIF orientation?)')
    return np.diag([sx, sy, 1.0]) @ K


def read_colmap(path, downscale: int | None = 1, background=(1.0, 1.0, 1.0),
                llff_hold: int = 8) -> Dataset:
    """Read a COLMAP dataset (see the module docstring).

    Args:
        path: the dataset folder (with ``images/`` and ``sparse/0/``).
        downscale: integer factor to shrink images by (None: chosen from the image size).
        background: RGB colour transparent pixels are composited over.
        llff_hold: every ``llff_hold``-th registered image is the test split (0: none).

    Raises:
        DatasetError: see :func:`pinhole_model` and :func:`colmap_frames`; a model with no
            registered images.
    """
    root = os.fspath(path)
    model, image_folder = pinhole_model(root)
    frames = colmap_frames(model, image_folder)
    if not frames:
        raise DatasetError(f'{model.folder}: the COLMAP model has no registered images; run '
                           f'the reconstruction again (python -m mi_nerfpp colmap PHOTOS)')
    frames = with_masks(root, model, frames)
    held_out = set(range(0, len(frames), llff_hold)) if llff_hold > 0 else set()
    if len(held_out) == len(frames):
        held_out = set()
    splits, chosen = make_splits({
        'train': [f for i, f in enumerate(frames) if i not in held_out],
        'validation': [],
        'test': [f for i, f in enumerate(frames) if i in held_out]}, downscale, background)
    return make_dataset('colmap', root, **splits, train_source=model.folder, downscale=chosen)
