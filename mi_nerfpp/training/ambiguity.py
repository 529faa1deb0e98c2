"""The shape-radiance ambiguity (paper §3, Figure 2): radiance fitted to a wrong, fixed shape.

The paper fixes NeRF's opacity to an opaque sphere around the object and fits only the
radiance ``c(x, d)``: for every training pixel, the radiance where its ray meets the sphere,
along the ray's direction, becomes the pixel's colour. That solution explains the training
images but must reproduce every view-dependent detail with ``c`` and so generalizes badly.

With ``σ = ∞`` on the sphere and 0 outside it, the volume rendering integral of a ray has a
single weight of 1 at the ray's first hit ``x_hit``, so

    C(r) = c(x_hit, d)        (rays that miss the sphere see the background colour)

and this module evaluates exactly that — one field evaluation per ray, no quadrature. The
field sees the hit in the sphere's own unit coordinates, ``(x_hit - center) / radius``, a point
on the unit sphere, as in the paper; any :mod:`mi_nerfpp.core.fields` field ('nerf', 'vanilla',
'grid') supplies ``c``. Its density output is ignored, so density parameters get no gradient.

Data flow as in training: rays of the training split (:class:`mi_nerfpp.training.raybank.RayBank`) ->
sphere hit -> field colour -> squared error -> Adam, with training's optimizer set-up,
learning-rate schedule and loss (:mod:`mi_nerfpp.training.optim`).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_nerfpp.core.geometry import unit_sphere_chord
from mi_nerfpp.data import pixel_rays
from mi_nerfpp.training import optim


def sphere_hit(o, d, center, radius):
    """First intersection of the rays ``o + t·d`` (``|d| = 1``) with a sphere.

    Returns ``(x, t, hit)``: the hit in the sphere's unit coordinates
    ``(o + t·d - center) / radius`` (on the unit sphere), its ray distance ``t > 0`` and
    whether there is one. From outside the sphere the hit is the entry point; from inside,
    the exit point (the sphere is an opaque shell).
    """
    c = mi.Point3f(*[float(v) for v in center])
    local = (mi.Point3f(o) - c) / radius
    t_in, t_out, hit = unit_sphere_chord(local, d)
    t = dr.select(t_in > 0, t_in, t_out)
    hit &= t_out > 0
    return dr.fma(d, t, local), t * radius, hit


class OpaqueSphere:
    """A radiance field on an opaque sphere: the paper's degenerate reconstruction.

    ``field`` provides ``c(x, d)`` for ``x`` on the unit sphere; ``center`` and
    ``radius`` place the sphere in the frame of the rays; ``background`` is the colour
    of rays that miss it.
    """

    def __init__(self, field, center, radius, background=(0.0, 0.0, 0.0)):
        if not radius > 0:
            raise ValueError(f'sphere radius must be positive, got {radius}')
        self.field = field
        self.center = np.asarray(center, dtype=np.float64).reshape(3)
        self.radius = float(radius)
        self.background = mi.Color3f(*[float(v) for v in background])

    def radiance(self, o, d):
        """Colour of each ray (Color3f)."""
        x, _, hit = sphere_hit(o, d, self.center, self.radius)
        ray = dr.arange(mi.UInt32, dr.width(hit))
        _, rgb = self.field([x.x, x.y, x.z], d, ray)
        return dr.select(hit, rgb, self.background)

    def render_view(self, camera, chunk=1 << 16):
        """The (H, W, 3) image of a camera in the rays' frame, float32."""
        py, px = np.mgrid[0:camera.height, 0:camera.width] + 0.5
        o, d = pixel_rays(camera, px, py)
        o, d = o.astype(np.float32), d.astype(np.float32)
        out = []
        for s in range(0, len(o), chunk):
            oc = mi.Point3f(*[mi.Float(o[s:s + chunk, i]) for i in range(3)])
            dc = mi.Vector3f(*[mi.Float(d[s:s + chunk, i]) for i in range(3)])
            out.append(np.array(self.radiance(oc, dc), dtype=np.float32).T)   # (3, n) -> (n, 3)
        return np.concatenate(out).reshape(camera.height, camera.width, 3)


def fit_radiance(sphere, rays, iterations, batch_rays=4096, lr_mlp=optim.LR_MLP,
                 lr_grid=optim.LR_GRID, lr_final=optim.LR_FINAL, seed=0, progress=None):
    """Fit the sphere's radiance field to a :class:`~mi_nerfpp.training.raybank.RayBank` by Adam on the
    squared error (learning rates decay exponentially to ``lr_final`` of their start).

    ``progress``: optional ``tqdm``-like wrapper of the iteration range.
    Returns the training history ``[(iteration, mse), ...]`` every 50 iterations.
    """
    field = sphere.field
    opt = optim.adam(field.params, lr_mlp)
    rng = np.random.default_rng(seed)
    history = []
    steps = range(iterations)
    if progress is not None:
        steps = progress(steps, desc='fit radiance', unit='it')
    for it in steps:
        optim.set_learning_rates(opt, it / max(iterations, 1), lr_grid, lr_mlp, lr_final)
        batch, gt = rays.batch(rng.integers(0, rays.size, batch_rays))
        for k in opt.keys():
            field.params[k] = opt[k]
        rgb = sphere.radiance(batch.o, batch.d)
        loss = optim.mse(rgb, gt)
        dr.backward(loss)
        opt.step()
        if it % 50 == 0 or it == iterations - 1:
            history.append((it + 1, float(loss.array[0])))
    for k in opt.keys():
        field.params[k] = dr.detach(opt[k])
    return history
