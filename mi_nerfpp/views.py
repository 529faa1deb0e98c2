"""Rendering through the ``nerfpp`` integrator: scene files to layered EXR/PNG, cameras to layers.

Views of a model are rendered by Mitsuba with the same integrator a user renders with.
:class:`ViewRenderer` builds one scene holding the model and passes a sensor per view
(rays through pixel centres), so rendering many views builds no further models.
"""
from __future__ import annotations

import mitsuba as mi
import numpy as np

from .data import Camera, mitsuba_sensor_dict
from .exr import BEAUTY, LAYERS, split_channels, write_exr
from .frame import VIEW_NEAR_CLIP
from .integrator import NeRFPPIntegrator
from .preview import write_png
from .render import Sampling


def film_channel_names(film, integrator):
    """Channel names of ``mi.render``'s output for this film and integrator."""
    base = list(BEAUTY if mi.has_flag(film.flags(), mi.FilmFlags.Alpha) else BEAUTY[:3])
    return base + list(integrator.aov_names())


def render_to_files(scene, out, spp=0, preview=None, seed=0, progress=True):
    """Render ``scene``'s first sensor and write a multi-layer EXR (and a PNG preview).

    Returns the image as a dict of channel name -> HxW float32 array.
    """
    integrator = scene.integrator()
    if isinstance(integrator, NeRFPPIntegrator):
        integrator.show_progress = progress
    film = scene.sensors()[0].film()
    image = np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float32)
    channels = split_channels(image, film_channel_names(film, integrator))
    write_exr(out, channels)
    if preview:
        color_space = (integrator.model.color_space if isinstance(integrator, NeRFPPIntegrator)
                       else 'linear')
        write_png(preview, rgb(channels), color_space)
    return channels


def rgb(layers):
    """The beauty of a layer dict as an (H, W, 3) array."""
    return np.stack([layers[c] for c in BEAUTY[:3]], axis=-1)


class ViewRenderer:
    """One scene with the ``nerfpp`` integrator holding ``model``; renders model-frame cameras."""

    def __init__(self, model, sampling: Sampling, background=True):
        self.model = model
        self.scene = mi.load_dict({
            'type': 'scene',
            'integrator': {'type': 'nerfpp', 'fg_samples': sampling.fg_samples,
                           'bg_samples': sampling.bg_samples,
                           'fine_samples': sampling.fine_samples, 'near': sampling.near,
                           'background': background}})
        self.scene.integrator().set_model(model)

    def sensor(self, camera: Camera):
        """A perspective sensor reproducing ``camera`` (model frame) in the world frame."""
        norm = self.model.normalization
        desc = mitsuba_sensor_dict(norm.to_world_camera(camera))
        desc['sampler'] = {'type': 'stratified', 'sample_count': 1, 'jitter': False}
        # Mitsuba starts rays on the near plane: keep it at a negligible model-frame distance.
        desc['near_clip'] = norm.to_world_distance(VIEW_NEAR_CLIP)
        return mi.load_dict(desc)

    def render(self, camera: Camera):
        """All layers of one view: channel name -> (H, W) float32."""
        img = mi.render(self.scene, sensor=self.sensor(camera))
        return split_channels(np.array(img, dtype=np.float32), LAYERS)


def render_view(model, camera: Camera, sampling: Sampling, background=True):
    """All layers of one view of ``model`` (a one-off :class:`ViewRenderer`)."""
    return ViewRenderer(model, sampling, background).render(camera)
