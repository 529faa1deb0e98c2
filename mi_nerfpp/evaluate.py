"""Held-out evaluation of a model: per-view layers and metrics, ``metrics.json``, ``render.xml``.

Views are rendered through the ``nerfpp`` integrator (:class:`mi_nerfpp.views.ViewRenderer`,
one scene per split), compared with the dataset images (PSNR, SSIM) and written as layered
EXRs and PNG previews.
"""
from __future__ import annotations

import dataclasses
import json
import os
import time

import numpy as np

from .exr import write_exr
from .files import atomic_write_path
from .frame import SCENE_NEAR_CLIP
from .metrics import psnr, ssim
from .preview import write_png
from .render import Sampling
from .scene_xml import write_render_xml
from .views import ViewRenderer, encoded_rgb


def evaluate_split(model, split, out_dir, sampling: Sampling, name='test', background=True,
                   progress=None):
    """Render every view of ``split``, write ``{name}_NNN.exr``/``.png`` and return the metrics.

    Returns a dict with per-view PSNR/SSIM, their means and the render time.
    """
    os.makedirs(out_dir, exist_ok=True)
    renderer = ViewRenderer(model, sampling, background)
    views = []
    t0 = time.perf_counter()
    indices = range(len(split))
    if progress is not None:
        indices = progress(indices, desc=f'evaluate {name}', unit='view', leave=False)
    for i in indices:
        layers, attributes = renderer.render(split.cameras[i], with_attributes=True)
        pred = encoded_rgb(layers, model.color_space)
        gt = split.images[i]
        base = os.path.join(out_dir, f'{name}_{i:03d}')
        write_exr(base + '.exr', layers, attributes=attributes)
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


def finish_run(out, model, held_out, cfg, checkpoint_path, metrics):
    """Evaluate the held-out views; write metrics.json (with ``metrics``) and render.xml.

    ``cfg`` is the run's :class:`~mi_nerfpp.train.TrainConfig`. Returns the metrics written.
    """
    from tqdm import tqdm

    metrics = dict(metrics, config=dataclasses.asdict(cfg))
    background = cfg.model == 'nerfpp'
    if len(held_out):
        metrics['test'] = evaluate_split(model, held_out, os.path.join(out, 'test'),
                                         cfg.sampling, background=background, progress=tqdm)
        norm = model.normalization
        write_render_xml(os.path.join(out, 'render.xml'), checkpoint_path,
                         norm.to_world_camera(held_out.cameras[0]), cfg.sampling,
                         near_clip=norm.to_world_distance(SCENE_NEAR_CLIP),
                         background=background)
    write_json(os.path.join(out, 'metrics.json'), metrics)
    return metrics


def write_json(path, data):
    """Write JSON atomically."""
    with atomic_write_path(path) as tmp, open(tmp, 'w') as f:
        json.dump(data, f, indent=2)
