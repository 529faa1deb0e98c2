"""A held-out photo's appearance code, fitted on its left half as NeRF-W evaluates.

A model trained with ``--appearance-embedding`` explains each training photo's weather and sky
with that photo's code (:mod:`mi_nerfpp.core.appearance`). A held-out photo has its own, which
no training photo's code need match, so NeRF-W scores such a model by *fitting* the held-out
photo's code on the left half of the photo (the fields and everything else held fixed) and
scoring the right half. :func:`fit_code` does the fit: Adam over the code's ``DIMS`` numbers -
and, for a model that also learned per-photo colour transforms (``--appearance``), over a
per-channel log-gain and bias beside it, so that the code is not spent on exposure - on random
batches of the left half's pixels, the training loss's colour term (in the images' encoding).
:func:`~mi_nerfpp.training.evaluate.evaluate_split` then renders the view with the code and
fits the affine transform on the left half as before.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_nerfpp.core.appearance import LR_APPEARANCE, PARAMS
from mi_nerfpp.core.render import RenderOptions, render_rays
from mi_nerfpp.data.dataset import Split
from mi_nerfpp.training import optim
from mi_nerfpp.training.raybank import RayBank

FIT_STEPS = 100          # Adam steps of a held-out photo's code
FIT_RAYS = 1024          # left-half pixels per step
FIT_LR = 5 * LR_APPEARANCE   # a few hundred steps, not a run: a larger rate than training's


def fit_code(model, camera, image: np.ndarray, steps: int = FIT_STEPS,
             rays: int = FIT_RAYS, seed: int = 0) -> list[float]:
    """The appearance code (``model``'s ``appearance_dims`` Python floats) that best renders
    the left half of the held-out ``image`` (float32 (H, W, 3) in the encoding of the training
    images) from ``camera`` (in the model's frame), as NeRF-W fits it. The model is left as it
    was (its neutral code)."""
    dims = model.embedding.shape[1]
    h, w = image.shape[:2]
    half = w // 2
    if half < 1:
        raise ValueError(f'a {w}-pixel-wide view has no left half to fit its appearance on')
    bank = RayBank(Split([camera], [''], [np.asarray(image, dtype=np.float32)]))
    left = (np.arange(h)[:, None] * w + np.arange(half)[None, :]).ravel().astype(np.uint32)
    rng = np.random.default_rng(seed)
    opt = optim.Adam(lr=FIT_LR)
    opt['code'] = dr.zeros(mi.Float, dims)
    if model.appearance is not None:
        opt['transform'] = dr.zeros(mi.Float, PARAMS)
    encode = model.loss_encoding
    fg, bg = model.radiance_fields()
    try:
        with optim.colour_weights_attached(model):
            for _ in range(steps):
                index = rng.choice(left, size=min(rays, left.size), replace=False)
                batch, target = bank.batch(mi.UInt32(index), footprint=model.antialias)
                batch.seed = mi.UInt32(rng.integers(0, 2 ** 32, size=index.size, dtype=np.uint32))
                per_ray = dr.zeros(mi.UInt32, index.size)
                model.set_appearance([dr.gather(mi.Float, opt['code'], per_ray + j)
                                      for j in range(dims)])
                res = render_rays(batch, fg, bg, model.sampling,
                                  RenderOptions(occupancy=model.occupancy))
                rgb = res.composite.rgb
                if 'transform' in opt:
                    p = [dr.gather(mi.Float, opt['transform'], j) for j in range(PARAMS)]
                    rgb = dr.exp(mi.Color3f(p[0], p[1], p[2])) * rgb + mi.Color3f(p[3], p[4], p[5])
                dr.backward(optim.mse(encode(rgb), target))
                opt.step()
    finally:
        model.set_appearance(None)
    return [float(v) for v in np.asarray(opt['code'], dtype=np.float64)]
