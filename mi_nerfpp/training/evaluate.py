"""Held-out evaluation of a model: per-view layers and metrics, ``metrics.json``, ``render.xml``.

Views are rendered through the ``nerfpp`` integrator (:class:`mi_nerfpp.output.views.ViewRenderer`,
one scene per split), compared with the dataset images (PSNR, SSIM) and written as layered
EXRs and PNG previews.
"""
from __future__ import annotations

import os
import time

import numpy as np

from mi_nerfpp.core.appearance import fit_affine, left_right
from mi_nerfpp.core.color import srgb_eotf, srgb_oetf
from mi_nerfpp.core.coverage import SEEN_BY
from mi_nerfpp.core.frame import SCENE_NEAR_CLIP
from mi_nerfpp.core.render import Sampling
from mi_nerfpp.data.cameras import direction_coverage
from mi_nerfpp.files.atomic import write_json
from mi_nerfpp.files.exr import write_exr
from mi_nerfpp.files.preview import write_linear_png
from mi_nerfpp.output.scene_xml import write_render_xml
from mi_nerfpp.output.views import ViewRenderer, encoded_rgb, rgb
from mi_nerfpp.training.appearance_fit import fit_code
from mi_nerfpp.training.metrics import (SOFT_ALPHA, SOFT_ALPHA_WARNING, masked_psnr, psnr,
                                        psnr_from_mse, soft_alpha_fraction, ssim)

# A held-out pixel is inside its mask (kept, or the object's) from this 8-bit coverage on.
MASK_INSIDE = 128


def evaluate_split(model, split, out_dir, sampling: Sampling | None = None, name='test',
                   background: bool | None = None, progress=None, fit_appearance=False,
                   masks: str = 'none'):
    """Render every view of ``split``, write ``{name}_NNN.exr``/``.png`` and return the metrics.

    Views are rendered with the model's render settings (the sample counts it was trained
    with, its background); ``sampling`` and ``background`` override them. Returns a dict with
    per-view PSNR/SSIM, their means and the render time; when the background is rendered
    also per view and on average ``soft_alpha``, the fraction of pixels whose foreground
    opacity is neither in nor out of the matte (:func:`soft_alpha_fraction`). Renders are
    neutral (no appearance transform). ``progress``: a wrapper of the views' iterable
    (``tqdm``-like: ``progress(iterable, desc=..., unit=..., leave=...)``) for a progress bar. ``fit_appearance``: held-out photos have their own
    exposure, so they are scored as NeRF-W does - a per-channel gain and bias is fitted (linear
    least squares in linear light, :func:`~mi_nerfpp.core.appearance.fit_affine`) on the left half
    of each view and the right half is scored; that score is then ``psnr`` and the neutral
    full-image scores are kept as ``psnr_neutral`` / ``ssim_neutral``.

    ``masks`` (what the split's masks mean, :mod:`mi_nerfpp.data.masks`; views without a mask
    are left out of these): 'ignore' adds ``psnr_masked``, the PSNR over each view's kept
    pixels; 'object' adds ``psnr_masked`` over the object's pixels and ``matte_iou``, the
    intersection over union of the rendered foreground matte (``fg.A > 0.5``) and the mask.
    """
    os.makedirs(out_dir, exist_ok=True)
    renderer = ViewRenderer(model, sampling, background)
    background = renderer.scene.integrator().background
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
        write_linear_png(base + '.png', rgb(layers))
        view = {'view': i, 'image': os.path.basename(split.image_paths[i]),
                'psnr': float(psnr(np.clip(pred, 0, 1), gt)),
                'ssim': float(ssim(np.clip(pred, 0, 1), gt))}
        if background:
            view['soft_alpha'] = soft_alpha_fraction(layers['fg.A'])
        mask = split.masks[i] if masks != 'none' and split.masks is not None else None
        if mask is not None:
            inside = mask >= MASK_INSIDE
            view['psnr_masked'] = float(masked_psnr(np.clip(pred, 0, 1), gt, inside))
            if masks == 'object':
                view['matte_iou'] = matte_iou(layers['fg.A'], inside)
        if fit_appearance:
            view['psnr_neutral'], view['ssim_neutral'] = view['psnr'], view['ssim']
            linear = rgb(layers)
            if model.embedding is not None:     # NeRF-W: the code fitted on the left half
                view['code'] = fit_code(model, split.cameras[i], gt, seed=i)
                model.render_code = view['code']
                try:
                    linear = rgb(renderer.render(split.cameras[i]))
                finally:
                    model.render_code = None
            view['psnr'], view['ssim'], view['gain'], view['bias'] = _fitted_right_half(
                linear, gt, model.color_space)
        views.append(view)
    seconds = time.perf_counter() - t0
    result = {'views': views, 'render_seconds': seconds}
    if fit_appearance:
        result['scoring'] = ('appearance fitted on the left half of each view (its '
                             + ('code, then ' if model.embedding is not None else '')
                             + 'colour transform), right half scored')
    for key in ('psnr', 'ssim', 'psnr_neutral', 'ssim_neutral', 'soft_alpha', 'psnr_masked',
                'matte_iou'):
        scores = [v[key] for v in views if key in v and np.isfinite(v[key])]
        if scores:
            result[key] = float(np.mean(scores))
    return result


def matte_iou(alpha: np.ndarray, inside: np.ndarray) -> float:
    """Intersection over union of the foreground matte ``alpha > 0.5`` and the boolean
    ``inside`` (1 where both are empty)."""
    matte = np.asarray(alpha) > 0.5
    union = np.count_nonzero(matte | inside)
    return float(np.count_nonzero(matte & inside) / union) if union else 1.0


def _fitted_right_half(linear, gt, color_space):
    """NeRF-W scoring of one view: ``(psnr, ssim, gain, bias)`` of the right half after the
    affine colour transform fitted on the left half (in linear light)."""
    srgb = color_space == 'srgb'
    target = srgb_eotf(gt) if srgb else gt
    (pred_l, pred_r), (gt_l, _) = left_right(linear), left_right(target)
    gain, bias = fit_affine(pred_l, gt_l)
    fitted = pred_r * gain + bias
    fitted = srgb_oetf(np.clip(fitted, 0, 1)) if srgb else np.clip(fitted, 0, 1)
    right = left_right(gt)[1]
    fitted = fitted.astype(np.float32)
    return (float(psnr(fitted, right)), float(ssim(fitted, right)), gain.tolist(),
            bias.tolist())


def matte_warning(test_metrics):
    """A warning (str) when the held-out foreground matte is soft, else None.

    ``test_metrics``: the dict of :func:`evaluate_split`. A soft matte means that a surface is
    split between the volumes - typically the ground inside the unit sphere painted by the
    background with a half-transparent foreground over it - which the background's random
    initialization decides (on the default capture with the squared-error loss: one seed of
    five at 1,500 steps; with the Charbonnier loss, the default, the foreground owned it after
    10 minutes in both seeds measured; README)."""
    soft = test_metrics.get('soft_alpha')
    if soft is None or soft <= SOFT_ALPHA_WARNING:
        return None
    lo, hi = SOFT_ALPHA
    return (f'warning: the foreground matte is soft: {100 * soft:.1f} % of the held-out pixels have '
            f'{lo} < fg.A < {hi} (a clean matte has at most {100 * SOFT_ALPHA_WARNING:.0f} %, mostly '
            f'object edges). A surface is likely split between the volumes (e.g. the ground inside '
            f'the unit sphere painted by the background behind a half-transparent foreground), '
            f'which the random initialization of the background decides. This concerns the layers, '
            f'not the beauty pass: for compositing, train again with another --seed (it draws a new '
            f'background) and compare "soft_alpha" in metrics.json.')


def choose_coverage_fill(model, validation, train_cameras) -> dict | None:
    """Keep the model's coverage fill (:mod:`mi_nerfpp.core.coverage`) only where it paints the
    validation views' unseen pixels (directions fewer than ``SEEN_BY`` training views saw)
    better than the background volume: a capture whose volume extrapolates well there (a
    smooth sky) keeps the volume, one where it shows blocks of wrong colour (trees above a
    ring of cameras) takes the fill. Both are scored by their mean squared error over all
    those pixels, in the images' encoding, as the held-out PSNR is. Sets ``model.coverage``
    to None when the volume wins; returns ``{'kept', 'pixels', 'psnr_fill',
    'psnr_volume'}``, or None (and keeps the fill) when no validation pixel is unseen."""
    fill = model.coverage
    if fill is None or not len(validation):
        return None
    unseen = [(i, direction_coverage(cam, train_cameras) < SEEN_BY)
              for i, cam in enumerate(validation.cameras)]
    unseen = [(i, mask) for i, mask in unseen if mask.any()]
    if not unseen:
        return None
    mse = {}
    for keep in (True, False):
        model.coverage = fill if keep else None
        renderer = ViewRenderer(model)
        squared, count = 0.0, 0
        for i, mask in unseen:
            pred = np.clip(encoded_rgb(renderer.render(validation.cameras[i]),
                                       model.color_space), 0.0, 1.0)
            gt = np.asarray(validation.images[i], dtype=np.float64)[..., :3]
            squared += float(np.square(pred[mask] - gt[mask]).sum())
            count += int(mask.sum())
        mse[keep] = squared / (3 * count)
    kept = mse[True] <= mse[False]
    model.coverage = fill if kept else None
    return {'kept': bool(kept), 'pixels': count, 'psnr_fill': psnr_from_mse(mse[True]),
            'psnr_volume': psnr_from_mse(mse[False])}


def finish_run(out, model, held_out, cfg, checkpoint_path, metrics, progress=None):
    """Evaluate the held-out views; write metrics.json (with ``metrics``) and render.xml.

    ``cfg`` is the run's :class:`~mi_nerfpp.training.config.TrainConfig`; the views are rendered with
    the model's render settings, and render.xml leaves them to the checkpoint. ``progress``:
    as in :func:`evaluate_split`. Returns the metrics written.
    """
    metrics = dict(metrics, config=cfg.to_dict())
    if len(held_out):
        metrics['test'] = evaluate_split(model, held_out, os.path.join(out, 'test'),
                                         progress=progress,
                                         fit_appearance=cfg.model.per_photo_appearance,
                                         masks=cfg.losses.masks or 'none')
        norm = model.normalization
        write_render_xml(os.path.join(out, 'render.xml'), checkpoint_path,
                         norm.to_world_camera(held_out.cameras[0]),
                         near_clip=norm.to_world_distance(SCENE_NEAR_CLIP))
    write_json(os.path.join(out, 'metrics.json'), metrics, text=True)
    return metrics

