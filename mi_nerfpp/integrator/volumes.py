"""The volumes of the ``nerfpp`` integrator: NeRF++ rendering of world-space rays into the beauty
and the sample channels of :mod:`mi_nerfpp.core.layers`, and rendering in chunks."""
from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
from tqdm import tqdm

from mi_nerfpp.core.color import srgb_to_linear
from mi_nerfpp.core.layers import BACKGROUND_WEIGHT_FLOOR, layer_channels
from mi_nerfpp.core.rays import Rays
from mi_nerfpp.core.render import RenderOptions, render_rays, surface_distance
from mi_nerfpp.core.appearance import image_code
from mi_nerfpp.integrator.loading import appearance_transform


class VolumeRenderer:
    """Renders the model's two volumes along world-space rays, with the settings of one
    :class:`~mi_nerfpp.integrator.NeRFPPIntegrator` (its ``model``, ``sampling``,
    ``background``, ``camera`` and parameters, read at each render)."""

    def __init__(self, integrator):
        self.integrator = integrator

    def layers(self, rays: Rays, primal=False, transform=True, camera=True, record=None):
        """Beauty, volume AOVs and composite opacity of world-space ``rays``
        (:class:`~mi_nerfpp.core.rays.Rays`): ``(L: Color3f, aovs: {channel: Float}, opacity:
        Float)``.

        The paper's steps: both volumes are sampled and integrated by quadrature, and
        composited by Eq. 4 (:func:`~mi_nerfpp.core.render.render_rays`); the composite is
        developed into the layers (``fg``, ``bg``, ``depth``, ``distance``, ``A``).

        The rays' ``far``: where the volumes end (world units per ray, ``inf``: no end; None:
        all); their ``footprint``: pixel widths per unit distance
        (:func:`~mi_nerfpp.core.geometry.pixel_footprint`), or None; ``transform=False``
        leaves out the appearance transform; ``camera=False`` (rays that leave a surface)
        starts the samples at the ray origin, not at ``near``; ``record`` (a dict, camera
        rays only) receives the per-sample render ``res`` and the ``aovs``
        (:meth:`~mi_nerfpp.integrator.NeRFPPIntegrator.render_rays`)."""
        ig = self.integrator
        model = ig.model
        norm = model.normalization
        fg_field, bg_field = model.radiance_fields()
        sampling = ig.sampling
        if not camera:      # path segments that leave a surface: from their origin on
            sampling = dataclasses.replace(sampling, near=0.0)
        keep_samples = record is not None and camera and transform
        # The colour networks' appearance code: a training image's when asked, else the
        # model's render code (neutral unless a held-out photo's fitted code is set).
        chosen = ig.appearance_image >= 0 and transform and model.embedding is not None
        model.set_appearance(image_code(model.embedding, ig.appearance_image) if chosen
                             else model.render_code if transform else None)
        # 1-3. Sample both volumes, quadrature, Eq. 4 (a recorded render keeps its samples).
        o, d = rays.o, rays.d
        model_o, model_d = norm.to_model_rays(o, d)
        res = render_rays(
            rays.replace(o=model_o, d=model_d,
                         far=None if rays.far is None else norm.to_model_distance(rays.far),
                         footprint=rays.footprint if model.antialias else None),
            fg_field, bg_field if ig.background else None, sampling,
            RenderOptions(occupancy=model.occupancy if ig.skip_empty else None,
                          skip_occluded=primal and not ig.occluded_background,
                          fused=primal and not keep_samples,
                          coverage=model.coverage if ig.fill_unseen else None))
        model.set_appearance(None)
        # 4. The layers.
        fg = res.fg.shading
        L, fg_rgb, alpha = res.composite.rgb, fg.rgb, dr.clip(fg.opacity, 0.0, 1.0)
        bg = res.bg.shading.rgb if res.bg is not None else mi.Color3f(0.0)
        if model.composite == 'srgb' and model.color_space == 'srgb':
            # A checkpoint from before linear compositing: decode its layers to linear light
            # (the foreground unpremultiplied first); fg over bg is then exact only where
            # alpha is 0 or 1.
            L, bg = srgb_to_linear(L), srgb_to_linear(bg)
            fg_rgb = alpha * srgb_to_linear(fg_rgb / dr.maximum(alpha, 1e-6))
        if ig.appearance_image >= 0 and transform and model.appearance is not None:
            # c' = g·c + b on the beauty; fg' = g·fg + α·b and bg' = g·bg + b keep
            # beauty = fg' + (1 - α)·bg'.
            gain, bias = appearance_transform(model, ig.appearance_image)
            L, fg_rgb, bg = gain * L + bias, gain * fg_rgb + alpha * bias, gain * bg + bias
        surface = norm.to_world_distance(surface_distance(res))
        depth = ig.camera_depth(o, d, surface)
        # The background as seen through the foreground (weighted by λ + ε: see
        # mi_nerfpp.core.layers), so that the layers add up after the film averages the samples.
        seen = (1.0 - alpha) + BACKGROUND_WEIGHT_FLOOR
        aovs = layer_channels(fg=(fg_rgb.x, fg_rgb.y, fg_rgb.z, alpha),
                              bg=(seen * bg.x, seen * bg.y, seen * bg.z),
                              depth=(depth,),
                              distance=(norm.to_world_distance(res.composite.depth),),
                              A=(dr.full(mi.Float, 1.0, dr.width(alpha)) if ig.background
                                 else alpha,))
        if keep_samples:
            record.update(res=res, aovs=aovs)
        return L, aovs, res.composite.opacity

    def segments(self, rays: Rays, primal):
        """Radiance and transmittance of the volumes along ``rays`` that end at their ``far``
        (the segments that leave surfaces; neutral colour, in chunks when primal)."""
        def segment(rays):
            L, _, opacity = self.layers(rays, primal, transform=False, camera=False)
            return L, {'T': 1.0 - opacity}
        if primal:
            L, values = in_chunks(segment, rays, self.integrator.chunk_rays)
        else:
            L, values = segment(rays)
        return L, values['T']


def in_chunks(render, rays: Rays, chunk, progress=False):
    """Primal rendering of ``rays``, ``chunk`` at a time (bounded memory): ``render(rays)``
    of each chunk returns ``(L, values)``, ``values`` a dict of per-ray Floats (AOV
    channels); returns the same for all the rays. ``progress``: show a bar."""
    n = rays.width
    if n <= chunk:
        return render(rays)
    dr.eval(rays)
    L_out, out = [dr.zeros(mi.Float, n) for _ in range(3)], None
    starts = range(0, n, chunk)
    if progress:
        starts = tqdm(starts, desc='render', unit='chunk', leave=False)
    for start in starts:
        # Same-size chunks with an opaque offset: every chunk reuses one compiled kernel.
        i = dr.arange(mi.UInt32, chunk) + dr.opaque(mi.UInt32, start)
        valid = i < n
        j = dr.minimum(i, n - 1)
        L, values = render(rays.gather(j))
        if out is None:
            out = {name: dr.zeros(mi.Float, n) for name in values}
        for buf, value in zip(L_out + list(out.values()),
                              [L.x, L.y, L.z] + [values[name] for name in out]):
            dr.scatter(buf, value, i, valid)
        dr.eval(L_out, out)
    return mi.Color3f(*L_out), out
