"""Whether a training view that fits far worse than the rest has a wrong pose.

A view can fit worse than the median view for three reasons: content that its neighbours see
differently or not at all (a passer-by, a glint), content that is simply harder (a close look
at a textured, glossy object), or a wrong pose. Only the last is helped by moving the camera, so
:func:`check_pose` registers the view against the trained fields as iNeRF registers a photo:
Adam over a rigid correction of that camera alone (a turn about its centre and a shift, as
:mod:`mi_nerfpp.core.poses`), on random batches of the view's pixels, everything else held fixed,
coarse to fine (the rays' footprints widened at first, as pose refinement does). The view's
error on a fixed set of its pixels before and after says whether the camera, not the scene, was
wrong: a wrong pose's error falls by much, a hard view's hardly moves.

Measured on the default capture after 3 minutes (``tests/training/test_pose_check.py`` checks the
same on a small capture): view 41, a close look at the glossy sphere that fits ~3.5x worse than
the median view with its true pose, keeps ~95 % of its error; a view whose camera is turned by
1 degree keeps well under half. :data:`WRONG` sits between.
"""
from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_nerfpp.core import appearance as app
from mi_nerfpp.core import poses
from mi_nerfpp.core.render import RenderOptions, render_rays
from mi_nerfpp.training import optim
from mi_nerfpp.training.raybank import RayBank
from mi_nerfpp.training.signs import NAMED

STEPS = 150             # Adam steps of one view's correction
RAYS = 1024             # of the view's pixels per step
SCORED_RAYS = 4096      # the fixed pixels the error is compared on, before and after
LR = 1e-3               # radians and model units per step, as pose refinement's
BLUR = 1.0              # degrees: the rays' least footprint at the start, falling to none by
SHARP = 0.5             # this fraction of the fit (poses.blur's schedule)
# A view whose error falls below this fraction of its error at its given pose when its camera
# alone is fitted has a wrong pose.
WRONG = 0.7


@dataclasses.dataclass
class PoseCheck:
    """What fitting one view's camera alone did: its error (mean squared, encoded) at its pose
    and after the fit, and the fitted correction ``(ω, τ)`` (:mod:`mi_nerfpp.core.poses`: an
    axis-angle turn about the camera's centre in radians, then a shift in model units), applied
    after any the run learned."""
    before: float
    after: float
    correction: tuple

    @property
    def turn_degrees(self) -> float:
        return math.degrees(float(np.linalg.norm(self.correction[:3])))

    @property
    def shift(self) -> float:
        return float(np.linalg.norm(self.correction[3:]))

    @property
    def kept(self) -> float:
        """The share of its error the view keeps when its camera is fitted."""
        return self.after / self.before if self.before > 0 else 1.0

    @property
    def wrong_pose(self) -> bool:
        return self.kept < WRONG

    def to_dict(self) -> dict:
        return {'error_kept': round(self.kept, 3), 'turn_degrees': round(self.turn_degrees, 3),
                'shift': round(self.shift, 5), 'wrong_pose': self.wrong_pose}


def check_pose(model, bank, view: int, steps: int = STEPS, rays: int = RAYS,
               seed: int = 0, training: bool = True) -> PoseCheck:
    """Fit view ``view``'s camera alone against ``model`` (see the module docstring).

    ``bank``: the :class:`~mi_nerfpp.training.raybank.RayBank` of the training split at full
    size (the trainer's, at the end of its run). The view is rendered as training renders it:
    with its colour transform, code and pose correction where the model learned them. With
    ``training`` False the bank holds other views (held out), rendered neutral from their given
    poses. The model is left as it was."""
    n, h, w = bank.layout[:3]
    if not 0 <= view < n:
        raise ValueError(f'view {view} is not one of the {n} training views')
    pixels = h * w
    rng = np.random.default_rng(seed)
    scored = view * pixels + rng.choice(pixels, size=min(SCORED_RAYS, pixels), replace=False)
    opt = optim.Adam(lr=LR)
    opt['turn'] = dr.zeros(mi.Float, 3)
    opt['shift'] = dr.zeros(mi.Float, 3)
    fg, bg = model.radiance_fields()
    try:
        with optim.colour_weights_attached(model):
            before = _error(model, bank, scored, opt, fg, bg, training)
            for step in range(steps):
                index = view * pixels + rng.choice(pixels, size=min(rays, pixels), replace=False)
                blur = poses.blur(step / steps, BLUR, SHARP)
                error = _squared_error(model, bank, index, opt, fg, bg, blur, rng, training)
                dr.backward(dr.mean(error))
                opt.step()
            after = _error(model, bank, scored, opt, fg, bg, training)
    finally:
        model.set_appearance(None)
    correction = np.concatenate([np.asarray(opt['turn'], np.float64),
                                 np.asarray(opt['shift'], np.float64)])
    return PoseCheck(before, after, tuple(float(v) for v in correction))


def _error(model, bank, index, opt, fg, bg, training) -> float:
    """The mean squared error of the rays ``index`` (a fixed seed: the same samples each time)."""
    with dr.suspend_grad():
        error = _squared_error(model, bank, index, opt, fg, bg, 0.0, None, training)
        return float(dr.mean(error)[0])


def _squared_error(model, bank, index, opt, fg, bg, blur, seed, training):
    """Per ray the squared error (summed over channels, in the images' encoding) of the rays
    ``index`` of ``bank`` rendered from the camera corrected by ``opt``'s turn and shift."""
    batch, target = bank.batch(mi.UInt32(index), footprint=model.antialias)
    batch.seed = (mi.UInt32(seed.integers(0, 2 ** 32, size=len(index), dtype=np.uint32))
                  if seed is not None else mi.UInt32(np.arange(len(index), dtype=np.uint32)))
    if batch.footprint is not None and blur > 0:
        batch.footprint = dr.maximum(batch.footprint, blur)
    o, d = batch.o, batch.d
    if training and model.poses is not None:    # the run's correction, then the fitted one
        o, d = poses.correct_rays(model.poses, batch.image, o, d)
    turn = mi.Vector3f(*[dr.gather(mi.Float, opt['turn'], j) for j in range(3)])
    shift = mi.Vector3f(*[dr.gather(mi.Float, opt['shift'], j) for j in range(3)])
    batch.o, batch.d = o + shift, poses.rotate(turn, d)
    if training and model.embedding is not None:
        model.set_appearance(app.codes(model.embedding, batch.image))
    res = render_rays(batch, fg, bg, model.sampling,
                      RenderOptions(occupancy=model.occupancy, ray_gradients=True))
    rgb = res.composite.rgb
    if training and model.appearance is not None:
        rgb = app.transform_rays(model.appearance, batch.image, rgb)
    return optim.squared_error(model.loss_encoding(rgb), target)


def check_outliers(trainer, signs: dict, progress=None) -> dict:
    """``{name: PoseCheck.to_dict()}`` for each view that ``signs`` (the
    :meth:`~mi_nerfpp.training.signs.CaptureSigns.summary` of ``trainer``'s run) names as an
    outlier, at most :data:`~mi_nerfpp.training.signs.NAMED` of them. ``progress``: a
    ``tqdm``-like wrapper of the views."""
    names = [v['name'] for v in signs.get('views', [])]
    views = [names.index(name) for name in signs.get('outliers', [])[:NAMED]]
    if not views:
        return {}
    bank = trainer.rays.level(1)
    if progress is not None:
        views = progress(views, desc='check outlier poses', unit='view', leave=False)
    return {names[v]: check_pose(trainer.model, bank, v, seed=v).to_dict() for v in views}


def registered(model, split, steps: int = 2 * STEPS):
    """``split`` (held-out views, model frame) with each camera fitted alone against ``model``
    (:func:`check_pose`): BARF's test-time pose optimisation, which scores what a model with
    refined poses renders apart from where its refinement left the frame of the capture."""
    bank = RayBank(split)
    cameras = [dataclasses.replace(cam, c2w=poses.corrected_c2w(
        cam.c2w, check_pose(model, bank, v, steps=steps, seed=v, training=False).correction))
        for v, cam in enumerate(split.cameras)]
    return dataclasses.replace(split, cameras=cameras)
