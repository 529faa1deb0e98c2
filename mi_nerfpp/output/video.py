"""Novel-view videos of a trained model: an orbit around the scene, or the dataset's test path.

A video is rendered as frame files first (``frame_NNNNN.png``, and the multi-layer
``frame_NNNNN.exr`` on request; a tracked camera's frames carry the file's name and frame
numbers, ``shot.1001.png``: :mod:`mi_nerfpp.output.tracked_camera`), each written atomically,
then assembled. A frame whose files
exist is done, so an interrupted job resumes where it stopped. :func:`render_frames` is the one
function that renders frames to files, in one process or on each worker of a cluster
(:mod:`mi_nerfpp.jobs.cluster`).
"""
from __future__ import annotations

import contextlib
import importlib.util
import os

import imageio.v2 as iio2
import imageio.v3 as iio
import numpy as np

from mi_nerfpp.data import Camera
from mi_nerfpp.output.camera_path import DEFAULT_FPS, cameras_path
from mi_nerfpp.files.atomic import (atomic_write_path, check_writable_folder,
                                    remove_stale_temporaries, write_json)
from mi_nerfpp.files.exr import write_exr
from mi_nerfpp.files.preview import write_linear_png
from mi_nerfpp.files.readers import read_image, read_json
from mi_nerfpp.output.views import rgb


def _look_at(center, target, up):
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(z, -up)
    x /= np.linalg.norm(x)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)    # OpenCV: x right, y down, z forward
    c2w[:3, 3] = center
    return c2w


def orbit_cameras(cameras, frames, template: Camera):
    """``frames`` cameras on a circle through the capture's mean height, looking at the origin.

    The up axis is the mean of the cameras' up vectors (−y in OpenCV); the radius and height
    are the cameras' mean distance from that axis and mean height along it (model frame).
    """
    centers = np.stack([c.center for c in cameras])
    up = -np.mean([c.c2w[:3, 1] for c in cameras], axis=0)
    up /= np.linalg.norm(up)
    height = float(np.mean(centers @ up))
    radial = centers - np.outer(centers @ up, up)
    radius = float(np.mean(np.linalg.norm(radial, axis=1)))
    e1 = radial[0] / np.linalg.norm(radial[0])
    e2 = np.cross(up, e1)
    out = []
    for i in range(frames):
        a = 2 * np.pi * i / frames
        center = height * up + radius * (np.cos(a) * e1 + np.sin(a) * e2)
        out.append(Camera(template.K, _look_at(center, np.zeros(3), up), template.width,
                          template.height, f'orbit_{i:03d}'))
    return out


def resized(camera: Camera, width, height):
    """The same camera with an image of ``width`` x ``height`` pixels: the horizontal field of
    view and the pixels' shape are kept, so another aspect ratio (a 16:9 video of a 4:3
    capture) shows more or less above and below."""
    K = camera.K.copy()
    K[0] *= width / camera.width
    K[1, 1] *= width / camera.width
    K[1, 2] *= height / camera.height
    return Camera(K, camera.c2w, width, height, camera.name)


BUILT_IN_PATHS = ('orbit', 'test')
# Keyframes of the orbit when it is written as a path file (--write-path): enough for the
# editor's spline to stay close to the circle.
ORBIT_KEYFRAMES = 8


def built_in_cameras(name, dataset, frames=60, res=None):
    """The model-frame cameras of a built-in path: ``orbit`` (``frames`` cameras around the
    scene) or ``test`` (the dataset's test cameras), at the training images' size or ``res``."""
    template = dataset.train.cameras[0]
    if res:
        template = resized(template, *res)
    if name == 'orbit':
        return orbit_cameras(dataset.train.cameras, frames, template)
    cameras = [resized(c, template.width, template.height) for c in dataset.test.cameras]
    if not cameras:
        raise ValueError(f'{dataset.root} has no test cameras: use --path orbit')
    return cameras


def built_in_path(name, dataset, normalization, frames=60, res=None, fps=DEFAULT_FPS):
    """A built-in path (``orbit``, ``test``) as a camera path (world frame) that the viewer's
    editor loads: its frames are the video's cameras; its keyframes a few of the orbit's
    (closed loop), or every test camera."""
    cameras = built_in_cameras(name, dataset, frames, res)
    if name == 'orbit':
        keys = built_in_cameras(name, dataset, ORBIT_KEYFRAMES, res)
        return cameras_path(cameras, normalization, fps, loop=True, keyframes=keys)
    return cameras_path(cameras, normalization, fps)


VIDEO_FORMATS = ('.mp4', '.gif')


def check_video_path(path):
    """Refuse, before any frame is rendered, a video path whose format cannot be written: an
    extension other than ``.mp4`` / ``.gif``, a folder, ``.mp4`` without imageio-ffmpeg."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in VIDEO_FORMATS:
        raise ValueError(f'{path}: video must be .mp4 or .gif')
    if os.path.isdir(path):
        raise ValueError(f'{path} is a folder: give a file name to write')
    if ext == '.mp4' and importlib.util.find_spec('imageio_ffmpeg') is None:
        raise RuntimeError(f'{path}: writing MP4 needs the imageio-ffmpeg package '
                           f'(pip install imageio-ffmpeg), or ask for a .gif')


class VideoWriteError(RuntimeError):
    """The encoder could not write a video: its one line names the file, what went wrong and
    what to do; the earlier file at that path, if any, is left as it was."""


def write_video(path, frames, fps=24):
    """Write uint8 frames to ``.mp4`` (needs imageio-ffmpeg) or ``.gif``, atomically: the
    frames are encoded into a temporary file beside ``path``, checked (not empty; an MP4 that
    starts as one), and moved onto ``path`` only then, so that an earlier video stays whole
    until its successor is complete, whatever stops the encoder. The temporary files of this
    video that a killed writer left are removed first.

    Raises:
        VideoWriteError: the encoder failed or wrote no video (nothing is left behind).
    """
    check_video_path(path)
    gif = os.path.splitext(path)[1].lower() == '.gif'
    folder = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(folder):       # what a writer killed before (SIGKILL) left of this video
        remove_stale_temporaries(folder, os.path.basename(path))
    with atomic_write_path(path, utf8=gif) as tmp:      # ffmpeg writes an MP4 in its own process
        try:
            _encode(tmp, frames, fps, gif)
        except MemoryError:
            raise
        # What imageio and ffmpeg raise is open-ended (RuntimeError, ValueError, an OSError
        # without a number for a broken pipe to ffmpeg, imageio's own errors, ...): the
        # encoder failed; an OSError with a number is the system's (a full disk).
        except Exception as e:  # noqa: BLE001
            detail = e.strerror if isinstance(e, OSError) and e.errno and e.strerror else \
                f'the encoder failed: {_one_line(e)}'
            raise VideoWriteError(_encoder_failed(path, detail)) from e
        problem = _not_a_video(tmp, gif)
        if problem:
            raise VideoWriteError(_encoder_failed(path, problem))


def _encode(tmp, frames, fps, gif):
    if gif:
        # iio.imwrite, with the file at hand: imageio's Pillow plugin keeps the frames of a save
        # that failed and tries it again when it is collected (a second error, printed at
        # exit), so they are dropped.
        file = iio.imopen(tmp, 'w', legacy_mode=False)
        try:
            file.write(np.stack(frames), duration=1000 / fps, loop=0)
            file.close()
        except BaseException:
            getattr(file, 'images_to_write', []).clear()
            with contextlib.suppress(Exception):
                file.close()
            raise
        return
    with iio2.get_writer(tmp, fps=fps, codec='libx264', quality=8,
                         macro_block_size=1) as writer:
        for f in frames:
            writer.append_data(f)


def _one_line(error: BaseException) -> str:
    text = ' '.join(str(error).split()) or type(error).__name__
    return text if len(text) <= 200 else text[:197] + '...'


def _encoder_failed(path, detail) -> str:
    return (f'{path}: cannot write the video ({detail}); the earlier file, if any, is kept: '
            f'check the free disk space and the imageio-ffmpeg install, or ask for a .gif')


def _not_a_video(tmp, gif) -> str | None:
    """What is wrong with the file the encoder wrote, or None: empty, or not of its format."""
    size = os.path.getsize(tmp) if os.path.exists(tmp) else 0
    if size == 0:
        return 'the encoder wrote nothing, 0 bytes'
    with open(tmp, 'rb') as f:
        head = f.read(12)
    if gif and not head.startswith((b'GIF87a', b'GIF89a')):
        return 'the encoder wrote a file that is not a GIF'
    if not gif and head[4:8] != b'ftyp':
        return 'the encoder wrote a file that is not an MP4'
    return None


FRAME_NAME = 'frame_{:05d}'
MANIFEST = 'frames.json'


def frame_files(frames_dir, index, exr=False, name=FRAME_NAME):
    """The final files of frame ``index``: its PNG, and its EXR (all layers) with ``exr``;
    ``name``: the pattern of their name (``str.format`` of the index, no extension)."""
    base = os.path.join(frames_dir, name.format(index))
    return [base + '.png'] + ([base + '.exr'] if exr else [])


def _indices(frames):
    """Frame indices: ``range(frames)`` of a count, else the indices given."""
    return range(frames) if isinstance(frames, int) else list(frames)


def pending_frames(frames_dir, frames, exr=False, name=FRAME_NAME):
    """The indices of the frames (a count: ``0 .. frames - 1``, or the indices) whose files
    are not all written yet."""
    return [i for i in _indices(frames)
            if not all(os.path.exists(p) for p in frame_files(frames_dir, i, exr, name))]


def prepare_frames_dir(frames_dir, job: dict):
    """Create ``frames_dir`` for ``job`` (what determines the frames: run, path, size, ...), or
    check that the frames it already holds are of the same job (ValueError otherwise); remove
    the temporary files of writers that were killed."""
    check_writable_folder(frames_dir, what='frames folder')
    manifest = os.path.join(frames_dir, MANIFEST)
    if os.path.exists(manifest):
        held = read_json(manifest, what='frames manifest',
                         remedy=f'remove the folder {frames_dir} or choose another --frames-dir')
        if held != job:
            changed = ', '.join(f'{k} {held.get(k)!r} -> {job.get(k)!r}'
                                for k in list(job) + [k for k in held if k not in job]
                                if held.get(k) != job.get(k))
            raise ValueError(f'{frames_dir} holds the frames of another video ({changed}): '
                             f'remove it or choose another --frames-dir')
    write_json(manifest, job)
    remove_stale_temporaries(frames_dir)


def render_frames(renderer, cameras: dict, frames_dir, exr=False, on_frame=None,
                  name=FRAME_NAME):
    """Render the frames ``cameras`` (index -> camera) whose files are missing with
    ``renderer`` (a :class:`~mi_nerfpp.output.views.ViewRenderer`), writing each atomically: the EXR
    with all layers first (with ``exr``), then the PNG (named by ``name``, :func:`frame_files`).
    Returns the indices rendered."""
    done = []
    for index in sorted(cameras):
        files = frame_files(frames_dir, index, exr, name)
        if not all(os.path.exists(p) for p in files):
            layers, attributes = renderer.render(cameras[index], with_attributes=True)
            if exr:
                write_exr(files[1], layers, attributes=attributes)
            write_linear_png(files[0], rgb(layers))
            done.append(index)
        if on_frame is not None:
            on_frame(index)
    return done


def read_frames(frames_dir, frames, name=FRAME_NAME):
    """The PNG frames (a count, or the indices), in order, as uint8 arrays (to assemble the
    video)."""
    remedy = 'delete it and run the video again (it is rendered again)'
    return [read_image(frame_files(frames_dir, i, name=name)[0], what='video frame',
                       remedy=remedy) for i in _indices(frames)]
