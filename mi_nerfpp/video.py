"""Novel-view videos of a trained model: an orbit around the scene, or the dataset's test path."""
from __future__ import annotations

import importlib.util
import os

import numpy as np

from .data import Camera


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
    """The same camera with its image (and intrinsics) resampled to ``width`` x ``height``."""
    K = camera.K.copy()
    K[0] *= width / camera.width
    K[1] *= height / camera.height
    return Camera(K, camera.c2w, width, height, camera.name)


def write_video(path, frames, fps=24):
    """Write uint8 frames to ``.mp4`` (needs imageio-ffmpeg) or ``.gif``."""
    import imageio.v3 as iio
    ext = os.path.splitext(path)[1].lower()
    if ext not in ('.mp4', '.gif'):
        raise ValueError(f'{path}: video must be .mp4 or .gif')
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    if ext == '.gif':
        iio.imwrite(path, np.stack(frames), duration=1000 / fps, loop=0)
        return
    import imageio.v2 as iio2
    if importlib.util.find_spec('imageio_ffmpeg') is None:
        raise RuntimeError(f'{path}: writing MP4 needs the imageio-ffmpeg package '
                           f'(pip install imageio-ffmpeg), or ask for a .gif')
    with iio2.get_writer(path, fps=fps, codec='libx264', quality=8,
                         macro_block_size=1) as writer:
        for f in frames:
            writer.append_data(f)
