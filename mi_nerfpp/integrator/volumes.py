"""The volumes' layers of the ``nerfpp`` integrator: NeRF++ rendering of world-space rays into
the beauty and the sample channels of :mod:`mi_nerfpp.layers`, chunked to bound memory."""
from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi

from ..color import srgb_to_linear
from ..layers import BACKGROUND_WEIGHT_FLOOR, layer_channels
from ..render import render_rays, surface_distance
from .loading import appearance_transform


class VolumeLayers:
    """The volumes' methods of :class:`~mi_nerfpp.integrator.NeRFPPIntegrator` (which takes
    them as its own; they read its ``model``, ``sampling``, ``background`` and parameters)."""

    def render_layers(self, o, d, seed, primal=False, far=None, footprint=None):
        """Beauty and volume AOVs of world-space rays: ``(L: Color3f, aovs: {channel: Float})``
        (the ``fg``, ``bg``, ``depth`` and ``distance`` channels), the volumes ending at
        ``far`` (world units per ray, ``inf``: no end; None: all); ``footprint``: the rays'
        pixel widths per unit distance (:func:`~mi_nerfpp.geometry.pixel_footprint`), or
        None."""
        L, aovs, _ = self._volume(o, d, seed, primal, far, footprint=footprint)
        return L, aovs

    def _volume(self, o, d, seed, primal=False, far=None, transform=True, camera=True,
                footprint=None):
        """:meth:`render_layers` plus the composite opacity (``1 -`` the transmittance to
        ``far``); ``transform=False`` leaves out the appearance transform; ``camera=False``
        (rays that leave a surface) starts the samples at the ray origin, not at ``near``."""
        model = self.model
        norm = model.normalization
        fg_field, bg_field = model.radiance_fields()
        sampling = self.sampling
        if not camera:      # path segments that leave a surface: from their origin on
            sampling = dataclasses.replace(sampling, near=0.0)
        # A deep render reads the samples of the camera rays: no fused quadrature for those.
        deep = camera and transform and getattr(self, '_deep', None) is not None
        res = render_rays(*norm.to_model_rays(o, d), fg_field,
                          bg_field if self.background else None, sampling, seed,
                          occupancy=model.occupancy if self.skip_empty else None,
                          skip_occluded=primal and not self.occluded_background,
                          far=None if far is None else norm.to_model_distance(far),
                          footprint=footprint if model.antialias else None,
                          fused=primal and not deep)
        fg = res.fg.fine
        L, fg_rgb, alpha = res.fine.rgb, fg.rgb, dr.clip(fg.opacity, 0.0, 1.0)
        bg = res.bg.fine.rgb if res.bg is not None else mi.Color3f(0.0)
        if model.composite == 'srgb' and model.color_space == 'srgb':
            # A checkpoint from before linear compositing: decode its layers to linear light
            # (the foreground unpremultiplied first); fg over bg is then exact only where
            # alpha is 0 or 1.
            L, bg = srgb_to_linear(L), srgb_to_linear(bg)
            fg_rgb = alpha * srgb_to_linear(fg_rgb / dr.maximum(alpha, 1e-6))
        if self.appearance_image >= 0 and transform:
            # c' = g·c + b on the beauty; fg' = g·fg + α·b and bg' = g·bg + b keep
            # beauty = fg' + (1 - α)·bg'.
            gain, bias = appearance_transform(model, self.appearance_image)
            L, fg_rgb, bg = gain * L + bias, gain * fg_rgb + alpha * bias, gain * bg + bias
        surface = norm.to_world_distance(surface_distance(res))
        if self._view is None:        # no sensor known: the distance along the ray
            depth = surface
        else:
            center, axis = self._view
            depth = dr.dot(o - center, axis) + surface * dr.dot(dr.normalize(d), axis)
        # The background as seen through the foreground (weighted by λ + ε: see
        # mi_nerfpp.layers), so that the layers add up after the film averages the samples.
        seen = (1.0 - alpha) + BACKGROUND_WEIGHT_FLOOR
        aovs = layer_channels(fg=(fg_rgb.x, fg_rgb.y, fg_rgb.z, alpha),
                              bg=(seen * bg.x, seen * bg.y, seen * bg.z),
                              depth=(depth,),
                              distance=(norm.to_world_distance(res.fine.depth),),
                              A=(dr.full(mi.Float, 1.0, dr.width(alpha)) if self.background
                                 else alpha,))
        if deep:
            self._deep.update(res=res, aovs=aovs)
        return L, aovs, res.fine.opacity

    def _chunked(self, render, args, n, progress=True):
        """Primal rendering of ``n`` rays, ``chunk_rays`` at a time (bounded memory):
        ``render(*args)`` on each chunk of the per-ray ``args`` (None stays None) returns
        ``(L, values)``, ``values`` a dict of per-ray Floats (AOV channels); returns the same
        for all ``n`` rays. ``progress``: show a bar (with ``show_progress``) - not for the
        chunks of path segments inside a chunk."""
        if n <= self.chunk_rays:
            return render(*args)
        dr.eval(*[a for a in args if a is not None])
        chunk = self.chunk_rays
        L_out, out = [dr.zeros(mi.Float, n) for _ in range(3)], None
        chunks = range(0, n, chunk)
        if self.show_progress and progress:
            from tqdm import tqdm
            chunks = tqdm(chunks, desc='render', unit='chunk', leave=False)
        for start in chunks:
            # Same-size chunks with an opaque offset: every chunk reuses one compiled kernel.
            i = dr.arange(mi.UInt32, chunk) + dr.opaque(mi.UInt32, start)
            valid = i < n
            j = dr.minimum(i, n - 1)
            L, values = render(*[None if a is None else dr.gather(type(a), a, j)
                                 for a in args])
            if out is None:
                out = {name: dr.zeros(mi.Float, n) for name in values}
            for buf, value in zip(L_out + list(out.values()), [L.x, L.y, L.z]
                                  + [values[name] for name in out]):
                dr.scatter(buf, value, i, valid)
            dr.eval(L_out, out)
        return mi.Color3f(*L_out), out

    def _volume_batch(self, o, d, far, primal):
        """Radiance and transmittance of the volumes along rays that end at ``far`` (the
        segments that leave surfaces; neutral colour, chunked when primal)."""
        def render(o, d, far):
            L, _, opacity = self._volume(o, d, None, primal, far, transform=False,
                                         camera=False)
            return L, {'T': 1.0 - opacity}
        if primal:
            L, values = self._chunked(render, [o, d, far], dr.width(o), progress=False)
        else:
            L, values = render(o, d, far)
        return L, values['T']
