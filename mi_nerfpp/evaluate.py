"""Rendering dataset views through the ``nerfpp`` integrator, and held-out metrics.

Views are rendered by Mitsuba with the same integrator a user renders with, from a
perspective sensor that reproduces the dataset camera (rays through pixel centres).
"""
from __future__ import annotations

import json
import os
import time

import mitsuba as mi
import numpy as np

from .data import Camera, apply_normalization, mitsuba_sensor_dict
from .exr import split_channels, write_exr
from .files import atomic_write_path
from .integrator import AOV_NAMES
from .metrics import psnr, ssim
from .preview import write_png
from .render import Sampling

CHANNELS = ['R', 'G', 'B', 'A'] + AOV_NAMES


def world_camera(model, camera: Camera) -> Camera:
    """A camera of the normalized (model) frame placed back in the original world frame."""
    return apply_normalization(camera, -model.center * model.scale, 1.0 / model.scale)


def view_scene(model, camera: Camera, sampling: Sampling, background=True):
    """A Mitsuba scene that renders ``camera`` (model frame) of ``model`` with the nerfpp integrator."""
    sensor = mitsuba_sensor_dict(world_camera(model, camera))
    sensor['sampler'] = {'type': 'stratified', 'sample_count': 1, 'jitter': False}
    # Mitsuba starts rays on the near plane: keep it at a negligible model-frame distance.
    sensor['near_clip'] = 1e-4 / model.scale
    scene = mi.load_dict({
        'type': 'scene', 'sensor': sensor,
        'integrator': {'type': 'nerfpp', 'fg_samples': sampling.fg_samples,
                       'bg_samples': sampling.bg_samples, 'fine_samples': sampling.fine_samples,
                       'near': sampling.near, 'background': background}})
    scene.integrator().model = model
    return scene


def render_view(model, camera: Camera, sampling: Sampling, background=True):
    """All layers of one view: channel name -> (H, W) float32."""
    img = mi.render(view_scene(model, camera, sampling, background))
    return split_channels(np.array(img, dtype=np.float32), CHANNELS)


def rgb(layers):
    return np.stack([layers['R'], layers['G'], layers['B']], axis=-1)


def evaluate_split(model, split, out_dir, sampling: Sampling, name='test', background=True,
                   progress=None):
    """Render every view of ``split``, write ``{name}_NNN.exr``/``.png`` and return the metrics.

    Returns a dict with per-view PSNR/SSIM, their means and the render time.
    """
    os.makedirs(out_dir, exist_ok=True)
    views = []
    t0 = time.perf_counter()
    indices = range(len(split))
    if progress is not None:
        indices = progress(indices, desc=f'evaluate {name}', unit='view', leave=False)
    for i in indices:
        layers = render_view(model, split.cameras[i], sampling, background)
        pred = rgb(layers)
        gt = split.images[i]
        base = os.path.join(out_dir, f'{name}_{i:03d}')
        write_exr(base + '.exr', layers)
        write_png(base + '.png', pred, model.color_space)
        views.append({'view': i, 'image': os.path.basename(split.image_paths[i]),
                      'psnr': float(psnr(np.clip(pred, 0, 1), gt)),
                      'ssim': float(ssim(np.clip(pred, 0, 1), gt))})
    seconds = time.perf_counter() - t0
    result = {'views': views, 'render_seconds': seconds}
    if views:
        result['psnr'] = float(np.mean([v['psnr'] for v in views]))
        result['ssim'] = float(np.mean([v['ssim'] for v in views]))
    return result


def write_json(path, data):
    """Write JSON atomically."""
    with atomic_write_path(path) as tmp, open(tmp, 'w') as f:
        json.dump(data, f, indent=2)
