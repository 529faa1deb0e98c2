"""Camera paths: keyframes, the smooth path through them, and the file that ``video`` renders.

A camera path is what the viewer's path editor draws (:mod:`mi_nerfpp.jobs.viewer`) and what
``python -m mi_nerfpp video RUN --path FILE`` renders; ``video --write-path FILE`` writes its
built-in paths (``orbit``, ``test``) in the same format, so they load into the editor.

The file is JSON::

    {"format": "mi-nerfpp-camera-path", "version": 1,
     "frame": "world", "convention": "opencv",
     "resolution": [W, H], "fps": 24, "loop": false, "seconds": 4.0,
     "keyframes": [{"c2w": [[4 x 4]], "fov_y": 50.0}, ...],
     "frames":    [{"c2w": [[4 x 4]], "fov_y": 50.0}, ...]}

``c2w`` is a camera-to-world matrix in the dataset's own (world) frame, in the OpenCV convention
of :class:`~mi_nerfpp.data.Camera` (x right, y down, z forward); ``fov_y`` the vertical field of
view in degrees, through the image edges, with the principal point at the image centre and
square pixels. ``frames`` are what is rendered, one per video frame; ``keyframes`` are what the
editor edits (the frames are sampled from them by :func:`sample_frames`: a Catmull-Rom spline
through the keyframes' positions, quaternions and fields of view, uniform in keyframe index,
closed with ``loop``). A file whose frames were not sampled from its keyframes (the orbit, whose
keyframes are a few of its frames) is rendered as its frames say.

This module must not import drjit (the cameras it builds are plain :class:`Camera` objects).
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from mi_nerfpp.data import Camera
from mi_nerfpp.files.atomic import atomic_write_path
from mi_nerfpp.files.readers import read_json

FORMAT = 'mi-nerfpp-camera-path'
VERSION = 1
DEFAULT_FPS = 24
DEFAULT_SECONDS = 4.0
DEFAULT_RESOLUTION = (640, 360)
# The most frames sampled from the keyframes (seconds x fps): 11.5 hours at 24 fps.
MAX_FRAMES = 1_000_000
# What to do about a camera path file that is not one.
PATH_REMEDY = ('fix the file, or write it again (the viewer\'s path editor, video '
               '--write-path)')
# Fields of view a pinhole camera of the path may have (degrees, vertical).
FOV_RANGE = (1.0, 170.0)


class CameraPathError(ValueError):
    """A camera path file that cannot be read (the message names the file and the problem)."""


@dataclass
class Pose:
    """A camera of a path: camera-to-world (4 x 4, OpenCV, world frame) and vertical field of
    view in degrees."""
    c2w: np.ndarray
    fov_y: float

    def __post_init__(self):
        self.c2w = np.array(self.c2w, dtype=np.float64)
        self.fov_y = float(self.fov_y)

    def to_json(self) -> dict:
        return {'c2w': [[float(v) for v in row] for row in self.c2w], 'fov_y': self.fov_y}


@dataclass
class CameraPath:
    """Keyframes, the frames sampled from them, and how the video is made of them."""
    keyframes: list = field(default_factory=list)
    frames: list = field(default_factory=list)
    resolution: tuple = DEFAULT_RESOLUTION
    fps: float = DEFAULT_FPS
    loop: bool = False
    seconds: float = DEFAULT_SECONDS

    def resample(self) -> 'CameraPath':
        """Sample the frames from the keyframes again (after an edit): ``seconds · fps``
        frames (:func:`sample_frames`)."""
        count = max(1, int(round(self.seconds * self.fps)))
        self.frames = sample_frames(self.keyframes, count, self.loop) if self.keyframes else []
        return self

    def to_json(self) -> dict:
        return {'format': FORMAT, 'version': VERSION, 'frame': 'world', 'convention': 'opencv',
                'resolution': [int(v) for v in self.resolution], 'fps': float(self.fps),
                'loop': bool(self.loop), 'seconds': float(self.seconds),
                'keyframes': [k.to_json() for k in self.keyframes],
                'frames': [f.to_json() for f in self.frames]}

    def digest(self) -> str:
        """A short hash of what the video renders (frames and resolution): frames rendered
        for another path are not reused."""
        text = json.dumps({'resolution': self.to_json()['resolution'],
                           'frames': [f.to_json() for f in self.frames]}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------- sampling

def _catmull_rom(p0, p1, p2, p3, t):
    """Uniform Catmull-Rom between ``p1`` (t = 0) and ``p2`` (t = 1)."""
    t2, t3 = t * t, t * t * t
    return 0.5 * ((2 * p1) + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t2
                  + (-p0 + 3 * p1 - 3 * p2 + p3) * t3)


def sample_frames(keyframes, count: int, loop: bool = False) -> list:
    """``count`` poses on the smooth path through ``keyframes``: a uniform Catmull-Rom spline of
    the positions, of the rotations' quaternions (normalized) and of the fields of view,
    uniform in keyframe index. An open path starts on the first keyframe and ends on the last;
    a loop returns to the first keyframe after the last (the frame after the last is the
    first, so a looped video repeats without a seam)."""
    keys = list(keyframes)
    if not keys:
        raise ValueError('a camera path needs at least one keyframe')
    if count < 1:
        raise ValueError(f'a camera path needs at least one frame, got {count}')
    if len(keys) == 1:
        return [Pose(keys[0].c2w, keys[0].fov_y) for _ in range(count)]
    n = len(keys)
    pos = np.stack([k.c2w[:3, 3] for k in keys])
    quat = Rotation.from_matrix(np.stack([k.c2w[:3, :3] for k in keys])).as_quat()
    fov = np.array([[k.fov_y] for k in keys])
    values = np.concatenate([pos, quat, fov], axis=1)       # (n, 8): position, xyzw, fov
    if loop:        # wrapped: the points before the first and after the last
        ext = np.concatenate([values[-1:], values, values[:2]])
    else:           # mirrored: the path leaves the first and reaches the last keyframe
        ext = np.concatenate([values[:1], values, values[-1:]])
    for i in range(1, len(ext)):        # each quaternion on its predecessor's side: the
        if np.dot(ext[i, 3:7], ext[i - 1, 3:7]) < 0:        # short way round
            ext[i, 3:7] = -ext[i, 3:7]
    if not loop:
        ext[0] = 2 * ext[1] - ext[2]
        ext[-1] = 2 * ext[-2] - ext[-3]
    segments = n if loop else n - 1
    out = []
    for j in range(count):
        u = segments * j / count if loop else (segments * j / (count - 1) if count > 1 else 0.0)
        i = min(int(math.floor(u)), segments - 1)
        t = u - i
        v = _catmull_rom(*ext[i:i + 4], t)
        q = v[3:7] / np.linalg.norm(v[3:7])
        c2w = np.eye(4)
        c2w[:3, :3] = Rotation.from_quat(q).as_matrix()
        c2w[:3, 3] = v[:3]
        out.append(Pose(c2w, float(np.clip(v[7], *FOV_RANGE))))
    return out


# ------------------------------------------------------------------------------- cameras

def intrinsics(fov_y: float, width: int, height: int) -> np.ndarray:
    """K of a pinhole camera of ``width`` x ``height`` square pixels, principal point at the
    centre, with the vertical field of view ``fov_y`` (degrees)."""
    f = 0.5 * height / math.tan(math.radians(fov_y) / 2)
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=np.float64)


def pose_camera(pose: Pose, width: int, height: int, normalization=None, name='') -> Camera:
    """The camera of a path pose (world frame) as a :class:`Camera` of ``width`` x ``height``
    pixels, moved into a model's frame by ``normalization`` when given."""
    camera = Camera(intrinsics(pose.fov_y, width, height), pose.c2w, width, height, name)
    return normalization.to_model_camera(camera) if normalization is not None else camera


def path_cameras(path: CameraPath, normalization=None, resolution=None) -> list:
    """The frames of ``path`` as cameras (model frame with ``normalization``), at its resolution
    or ``resolution`` (the vertical field of view kept)."""
    width, height = resolution or path.resolution
    return [pose_camera(p, width, height, normalization, f'frame_{i:05d}')
            for i, p in enumerate(path.frames)]


def camera_pose(camera: Camera, normalization=None) -> Pose:
    """The pose of a camera (model frame with ``normalization``: moved back to the world)."""
    if normalization is not None:
        camera = normalization.to_world_camera(camera)
    return Pose(camera.c2w, camera.fov_y)


def cameras_path(cameras, normalization=None, fps=DEFAULT_FPS, loop=False,
                 keyframes=None) -> CameraPath:
    """A path whose frames are ``cameras`` (a built-in path of ``video``: the orbit, the test
    cameras), at their resolution, and whose keyframes are the cameras ``keyframes`` (default:
    ``cameras`` themselves), so that it loads into the viewer's editor."""
    cameras = list(cameras)
    if not cameras:
        raise ValueError('a camera path needs at least one camera')
    frames = [camera_pose(c, normalization) for c in cameras]
    keys = frames if keyframes is None else [camera_pose(c, normalization) for c in keyframes]
    return CameraPath([Pose(k.c2w, k.fov_y) for k in keys], frames,
                      (cameras[0].width, cameras[0].height), float(fps), bool(loop),
                      len(frames) / float(fps))


# ------------------------------------------------------------------------------- files

def write_path(filename, path: CameraPath):
    """Write ``path`` to ``filename`` (JSON, atomically)."""
    with atomic_write_path(filename) as tmp, open(tmp, 'w') as f:
        json.dump(path.to_json(), f, indent=1)


def _pose(data, where):
    if not isinstance(data, dict) or 'c2w' not in data or 'fov_y' not in data:
        raise ValueError(f'{where}: expected {{"c2w": 4x4, "fov_y": degrees}}')
    try:
        c2w = np.array(data['c2w'], dtype=np.float64)
        fov = float(data['fov_y'])
    except (TypeError, ValueError):
        raise ValueError(f'{where}: c2w must be 4x4 numbers and fov_y a number') from None
    if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
        raise ValueError(f'{where}: c2w must be a finite 4x4 matrix')
    rotation = c2w[:3, :3]
    if not (np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-4)
            and np.linalg.det(rotation) > 0 and np.allclose(c2w[3], [0, 0, 0, 1])):
        raise ValueError(f'{where}: c2w must be a rotation and a translation')
    if not FOV_RANGE[0] <= fov <= FOV_RANGE[1]:
        raise ValueError(f'{where}: fov_y must be {FOV_RANGE[0]:g} to {FOV_RANGE[1]:g} '
                         f'degrees, got {fov:g}')
    return Pose(c2w, fov)


def _positive(value) -> bool:
    """Whether ``value`` is a finite positive JSON number (not true or false)."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return False
    try:
        return 0 < float(value) < math.inf
    except OverflowError:       # an integer beyond floats
        return False


def read_path(filename) -> CameraPath:
    """Read a camera path file; raises :class:`CameraPathError` naming the file and what is
    wrong. A file without frames has them sampled from its keyframes."""
    data = read_json(filename, what='camera path file', remedy=PATH_REMEDY, expect=None,
                     error=CameraPathError)
    try:
        if not isinstance(data, dict) or data.get('format') != FORMAT:
            raise ValueError(f'not a camera path file (no "format": "{FORMAT}")')
        if data.get('version') != VERSION:
            raise ValueError(f'version {data.get("version")!r} is not {VERSION}')
        if data.get('frame', 'world') != 'world' or data.get('convention',
                                                              'opencv') != 'opencv':
            raise ValueError('only "frame": "world" and "convention": "opencv" are read')
        resolution = data.get('resolution', list(DEFAULT_RESOLUTION))
        if (not isinstance(resolution, list) or len(resolution) != 2
                or not all(isinstance(v, int) and v > 0 for v in resolution)):
            raise ValueError(f'resolution must be [width, height] in pixels, got {resolution!r}')
        fps = data.get('fps', DEFAULT_FPS)
        if not _positive(fps):
            raise ValueError(f'fps must be a positive number, got {fps!r}')
        for key in ('keyframes', 'frames'):
            if not isinstance(data.get(key, []), list):
                raise ValueError(f'"{key}" must be a list of poses')
        keyframes = [_pose(k, f'keyframe {i}') for i, k in enumerate(data.get('keyframes', []))]
        frames = [_pose(k, f'frame {i}') for i, k in enumerate(data.get('frames', []))]
        seconds = data.get('seconds')
        if seconds is None:
            seconds = len(frames) / fps if frames else DEFAULT_SECONDS
        if not _positive(seconds):
            raise ValueError(f'seconds must be a positive number, got {seconds!r}')
        if not frames and not float(seconds) * float(fps) <= MAX_FRAMES:
            raise ValueError(f'seconds x fps is {float(seconds) * float(fps):g} frames; a path '
                             f'sampled from its keyframes has at most {MAX_FRAMES:,}')
        path = CameraPath(keyframes, frames, tuple(resolution), float(fps),
                          bool(data.get('loop', False)), float(seconds))
        if not frames:
            if not keyframes:
                raise ValueError('it has neither keyframes nor frames')
            path.resample()
    except ValueError as e:
        raise CameraPathError(f'{filename}: {e}') from None
    return path
