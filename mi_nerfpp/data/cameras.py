"""Pinhole cameras and the coordinate conventions that meet in mi-nerfpp.

The normalization into the unit sphere is :class:`mi_nerfpp.core.frame.Normalization`.

A :class:`Camera` stores its pose as a camera-to-world matrix in the **OpenCV** convention, which
is the one the NeRF++ data format uses. Three camera-space conventions meet in this project:

==========  =======  =======  ==========================================================
convention  +x       +y       +z
==========  =======  =======  ==========================================================
OpenCV      right    down     forward (viewing direction); NeRF++ data, internal poses
OpenGL      right    up       backward; Blender / NeRF / instant-ngp ``transforms.json``
Mitsuba     left     up       forward; ``to_world`` of Mitsuba's ``perspective`` sensor
==========  =======  =======  ==========================================================

"left" and "right" are as seen in the image. Each conversion right-multiplies the
camera-to-world matrix by a diagonal axis flip: the camera's local axes change, its centre does
not. All three are right-handed, so every flip is a rotation by 180 degrees about one axis.

Pixel coordinates are continuous, x to the right and y down, with the centre of pixel (i, j)
at (i + 0.5, j + 0.5), the convention of the intrinsics matrix ``K``.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from mi_nerfpp.core.coverage import pixel_directions, views_seeing

# Camera-space axis flips, applied on the right of a camera-to-world matrix.
_OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
_OPENCV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])

# Mitsuba's perspective sensor has a single focal length; fx and fy closer than this are accepted.
SQUARE_PIXEL_TOLERANCE = 1e-3


@dataclass
class Camera:
    """A pinhole camera.

    Attributes:
        K: 3x3 intrinsics, ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.
        c2w: 4x4 camera-to-world matrix, OpenCV convention (x right, y down, z forward).
        width, height: image size in pixels.
        name: an identifier, usually the image file's stem.
    """

    K: np.ndarray
    c2w: np.ndarray
    width: int
    height: int
    name: str = ''

    def __post_init__(self):
        self.K = np.array(self.K, dtype=np.float64)
        self.c2w = np.array(self.c2w, dtype=np.float64)
        if self.K.shape != (3, 3):
            raise ValueError(f'Camera {self.name!r}: K must be 3x3, got shape {self.K.shape}')
        if self.c2w.shape != (4, 4):
            raise ValueError(f'Camera {self.name!r}: c2w must be 4x4, got shape {self.c2w.shape}')
        self.width, self.height = int(self.width), int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f'Camera {self.name!r}: image size must be positive, '
                             f'got {self.width}x{self.height}')

    @property
    def w2c(self) -> np.ndarray:
        """4x4 world-to-camera matrix (OpenCV), the inverse of :attr:`c2w`."""
        return np.linalg.inv(self.c2w)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world space, shape (3,)."""
        return self.c2w[:3, 3].copy()

    @property
    def fov_x(self) -> float:
        """Horizontal field of view in degrees, ``2 atan(width / (2 fx))``."""
        return float(np.degrees(2.0 * np.arctan(0.5 * self.width / self.K[0, 0])))

    @property
    def fov_y(self) -> float:
        """Vertical field of view in degrees, ``2 atan(height / (2 fy))``."""
        return float(np.degrees(2.0 * np.arctan(0.5 * self.height / self.K[1, 1])))

    def downscaled(self, factor: int) -> Camera:
        """The same camera for an image shrunk by an integer ``factor``.

        Pixel ``i`` of the small image covers pixels ``[factor*i, factor*(i+1))`` of the
        original (a remainder at the right/bottom edge is cropped), so continuous pixel
        coordinates simply divide by ``factor``: fx, fy, cx, cy and the skew all do.
        """
        factor = int(factor)
        if factor < 1:
            raise ValueError(f'downscale factor must be a positive integer, got {factor}')
        K = self.K.copy()
        K[:2] /= factor
        return dataclasses.replace(self, K=K, width=self.width // factor,
                                   height=self.height // factor)


# --- convention conversions -------------------------------------------------------------------

def _flip(c2w, flip: np.ndarray) -> np.ndarray:
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape[-2:] != (4, 4):
        raise ValueError(f'expected (..., 4, 4) camera-to-world matrices, got shape {c2w.shape}')
    with np.errstate(invalid='ignore', over='ignore'):     # NaN/inf poses: refused by name later
        return c2w @ flip


def opengl_to_opencv(c2w) -> np.ndarray:
    """OpenGL (x right, y up, z back) camera-to-world -> OpenCV (x right, y down, z forward)."""
    return _flip(c2w, _OPENCV_TO_OPENGL)


def opencv_to_opengl(c2w) -> np.ndarray:
    """OpenCV (x right, y down, z forward) camera-to-world -> OpenGL (x right, y up, z back)."""
    return _flip(c2w, _OPENCV_TO_OPENGL)


def opencv_to_mitsuba(c2w) -> np.ndarray:
    """OpenCV camera-to-world -> Mitsuba sensor ``to_world`` (x left, y up, z forward)."""
    return _flip(c2w, _OPENCV_TO_MITSUBA)


def mitsuba_to_opencv(c2w) -> np.ndarray:
    """Mitsuba sensor ``to_world`` (x left, y up, z forward) -> OpenCV camera-to-world."""
    return _flip(c2w, _OPENCV_TO_MITSUBA)


# --- projection -------------------------------------------------------------------------------

def pixel_rays(camera: Camera, px, py) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays through continuous pixel coordinates.

    Args:
        camera: the camera.
        px, py: array-likes of the same shape; the centre of pixel (i, j) is (i + 0.5, j + 0.5).

    Returns:
        ``(origins, dirs)``, each of shape (N, 3) with N the number of pixel positions:
        origins at the camera centre, unit directions ``normalize(R @ K^-1 [px, py, 1])``.
    """
    dirs = pixel_directions(camera, px, py)
    origins = np.broadcast_to(camera.center, dirs.shape).copy()
    return origins, dirs


def direction_coverage(camera: Camera, others) -> np.ndarray:
    """How many of the cameras ``others`` see the direction of each pixel of ``camera``.

    Directions are taken at infinity (the camera centres do not matter), so the count says
    which held-out pixels show distant content that training views saw at all: a test view's
    pixels seen by fewer than two training views are extrapolation, whatever the model.
    Returns an ``H x W`` integer array.
    """
    px, py = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    _, dirs = pixel_rays(camera, px, py)
    count = views_seeing(dirs, others)
    return count.reshape(camera.height, camera.width)


def project(camera: Camera, points) -> tuple[np.ndarray, np.ndarray]:
    """Project world points with ``K @ W2C``.

    Args:
        points: array-like of shape (N, 3) (or (3,)).

    Returns:
        ``(pixels, depth)``: continuous pixel coordinates (N, 2) and the camera-space depth
        z (N,), positive in front of the camera.
    """
    points = np.atleast_2d(np.asarray(points, dtype=np.float64))
    w2c = camera.w2c
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    uvw = cam @ camera.K.T
    return uvw[:, :2] / uvw[:, 2:3], cam[:, 2]


# --- Mitsuba ----------------------------------------------------------------------------------

def _as_matrix(transform) -> np.ndarray:
    """4x4 numpy matrix of an array-like or a Mitsuba ``ScalarTransform4f``."""
    matrix = np.asarray(getattr(transform, 'matrix', transform), dtype=np.float64)
    if matrix.shape != (4, 4):
        raise ValueError(f'transform must be a 4x4 matrix, got shape {matrix.shape}')
    return matrix


def mitsuba_sensor_dict(camera: Camera, spp: int = 1, pixel_format: str = 'rgba',
                        transform=None) -> dict:
    """A ``mi.load_dict`` description of a ``perspective`` sensor with the camera's projection.

    The field of view is set on the x axis from fx. Mitsuba's ``principal_point_offset_x/y``
    shift the film sample position before it is mapped to the near plane, in units of the film
    width/height and with the same orientation as pixel coordinates, so the principal point
    (cx, cy) becomes ``(0.5 - cx / width, 0.5 - cy / height)``.

    Note that Mitsuba 3.9's perspective sensor starts its rays on the near plane
    (``near_clip``, default 0.01, along the optical axis), not at the camera centre.

    Args:
        camera: the camera (OpenCV pose).
        spp: samples per pixel of the ``independent`` sampler.
        pixel_format: ``hdrfilm`` pixel format ('rgb', 'rgba', ...).
        transform: optional rigid 4x4 world transform (array-like or ``mi.ScalarTransform4f``)
            applied on the left of the camera pose, e.g. to place normalized cameras in a scene.

    Raises:
        ValueError: for non-square pixels (|fx - fy| / fx >= 1e-3), a skewed K, or a transform
            with scale (Mitsuba's perspective sensor supports none of these).
    """

    K = camera.K
    fx, fy = K[0, 0], K[1, 1]
    if abs(fx - fy) / abs(fx) >= SQUARE_PIXEL_TOLERANCE:
        raise ValueError(
            f'Camera {camera.name!r} has non-square pixels (fx={fx:g}, fy={fy:g}), which '
            f"Mitsuba's perspective sensor cannot represent (it has one focal length). Resample "
            f'the images to square pixels and scale fx or fy accordingly.')
    if abs(K[0, 1]) > 1e-9 * abs(fx):
        raise ValueError(f'Camera {camera.name!r} has a skewed K (K[0,1]={K[0, 1]:g}), which '
                         f"Mitsuba's perspective sensor cannot represent.")
    to_world = opencv_to_mitsuba(camera.c2w)
    if transform is not None:
        matrix = _as_matrix(transform)
        rotation = matrix[:3, :3]
        if not (np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6)
                and np.linalg.det(rotation) > 0):
            raise ValueError('transform must be rigid (rotation + translation): Mitsuba\'s '
                             'perspective sensor rejects scale in to_world. Scale the scene '
                             'instead of the sensor.')
        to_world = matrix @ to_world
    return {
        'type': 'perspective',
        'fov': camera.fov_x,
        'fov_axis': 'x',
        'principal_point_offset_x': 0.5 - K[0, 2] / camera.width,
        'principal_point_offset_y': 0.5 - K[1, 2] / camera.height,
        'to_world': mi.ScalarTransform4f(to_world),
        'sampler': {'type': 'independent', 'sample_count': int(spp)},
        'film': {
            'type': 'hdrfilm',
            'width': camera.width,
            'height': camera.height,
            'pixel_format': pixel_format,
            'rfilter': {'type': 'box'},
        },
    }
