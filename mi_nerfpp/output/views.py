"""Rendering through the ``nerfpp`` integrator: scene files to layered EXR/PNG, cameras to layers.

Views of a model are rendered by Mitsuba with the same integrator a user renders with.
:class:`ViewRenderer` builds one scene holding the model and passes a sensor per view
(rays through pixel centres), so rendering many views builds no further models.
"""
from __future__ import annotations

import mitsuba as mi
import numpy as np

from mi_nerfpp.core.color import encode
from mi_nerfpp.core.frame import VIEW_NEAR_CLIP
from mi_nerfpp.core.layers import AOVS, BEAUTY, develop
from mi_nerfpp.core.render import Sampling
from mi_nerfpp.data import Camera, mitsuba_sensor_dict
from mi_nerfpp.files.exr import compositing_attributes, write_exr
from mi_nerfpp.files.preview import write_linear_png
from mi_nerfpp.integrator import NeRFPPIntegrator


def render_layers(image, integrator=None):
    """``mi.render``'s output (H, W, C) as the layer dict of :data:`~mi_nerfpp.core.layers.LAYERS`
    (channel name -> H x W), whatever the film's pixel format: the film's ``R G B [A]``, then
    the sample channels that ``integrator.aov_names()`` names (None: a ``nerfpp`` integrator's,
    :data:`~mi_nerfpp.core.layers.AOVS`), developed into layers by
    :func:`mi_nerfpp.core.layers.develop` (so that they add up at any samples per pixel)."""
    image = np.asarray(image, dtype=np.float32)
    aovs = list(AOVS if integrator is None else integrator.aov_names())
    base = image.shape[2] - len(aovs)
    if base not in (3, 4):
        raise ValueError(f"the film gives {base} colour channel(s): set its pixel_format to "
                         f"'rgb' or 'rgba'")
    rgb = {name: image[..., i] for i, name in enumerate(BEAUTY[:3])}
    return develop(rgb, {name: image[..., base + i] for i, name in enumerate(aovs)})


def camera_attributes(sensor) -> dict:
    """Standard EXR camera attributes of a Mitsuba perspective sensor, in the world frame, as
    OpenEXR's ``ImfStandardAttributes.h`` defines them.

    ``worldToCamera``: world to the camera space of the standard (RenderMan's): left-handed,
    origin at the camera, +x right and +y up in the image, **+z the viewing direction**
    (points in front of the camera have positive z). ``worldToNDC``: world to normalized
    device coordinates after the division by w: (0, 0) the upper-left and (1, 1) the
    lower-right corner of the display window (the image edges), x right, y down; z (which
    the standard discards) is 0 at the near and 1 at the far plane. Both are stored as Imath
    writes them, for row vectors (``p' = p·M``), i.e. transposed. So a world point ``p``
    lands on the continuous pixel position ``(ndc.x·width, ndc.y·height)`` (pixel centres at
    ``+0.5``). Also ``fovX``/``fovY`` (degrees, through the image edges) and
    ``clipNear``/``clipFar`` (world units).
    """
    to_world = np.array(sensor.world_transform().matrix, dtype=np.float64).reshape(4, 4)
    world_to_mitsuba = np.linalg.inv(to_world)   # Mitsuba camera: x left, y up, z forward
    world_to_camera = np.diag([-1.0, 1.0, 1.0, 1.0]) @ world_to_mitsuba

    def slope(u, v):
        """(x/z, y/z) in Mitsuba camera space of the ray through film position (u, v)."""
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(u, v), mi.Point2f(0.5))
        d = world_to_mitsuba[:3, :3] @ np.array(ray.d, dtype=np.float64).reshape(3)
        return d[0] / d[2], d[1] / d[2]

    s0, s1 = slope(0.0, 0.5)[0], slope(1.0, 0.5)[0]
    t0, t1 = slope(0.5, 0.0)[1], slope(0.5, 1.0)[1]
    near, far = float(sensor.near_clip()), float(sensor.far_clip())
    # u = (x/z - s0) / (s1 - s0), v = (y/z - t0) / (t1 - t0) in Mitsuba camera space.
    projection = np.array([
        [1 / (s1 - s0), 0, -s0 / (s1 - s0), 0],
        [0, 1 / (t1 - t0), -t0 / (t1 - t0), 0],
        [0, 0, far / (far - near), -far * near / (far - near)],
        [0, 0, 1, 0]])
    world_to_ndc = projection @ world_to_mitsuba

    def fov(a, b):
        return float(np.degrees(abs(np.arctan(a) - np.arctan(b))))

    return {'worldToCamera': np.ascontiguousarray(world_to_camera.T, dtype=np.float32),
            'worldToNDC': np.ascontiguousarray(world_to_ndc.T, dtype=np.float32),
            'fovX': fov(s0, s1), 'fovY': fov(t0, t1), 'clipNear': near, 'clipFar': far}


def exr_attributes(sensor) -> dict:
    """All header attributes of a render of ``sensor``."""
    return dict(compositing_attributes(), **camera_attributes(sensor))


def render_to_files(scene, out, spp=0, preview=None, seed=0, progress=True, sensor=None):
    """Render ``scene``'s first sensor (or ``sensor``) and write a multi-layer EXR (and a PNG
    preview).

    Returns the image as a dict of channel name -> HxW float32 array.
    """
    integrator = scene.integrator()
    if not isinstance(integrator, NeRFPPIntegrator):
        raise ValueError("the scene's integrator is not 'nerfpp': use "
                         "<integrator type=\"nerfpp\"> for layered output")
    integrator.show_progress = progress
    sensor = sensor or scene.sensors()[0]
    channels = render_layers(mi.render(scene, sensor=sensor, spp=spp, seed=seed), integrator)
    write_exr(out, channels, attributes=exr_attributes(sensor))
    if preview:
        write_linear_png(preview, rgb(channels))
    return channels


def rgb(layers):
    """The beauty of a layer dict as an (H, W, 3) array (scene-linear)."""
    return np.stack([layers[c] for c in BEAUTY[:3]], axis=-1)


def encoded_rgb(layers, color_space):
    """The beauty in the encoding of a model's training images (``'srgb'``: clipped to [0, 1]
    and sRGB-encoded, as the photos are; ``'linear'``: as rendered), to compare with them
    (:func:`mi_nerfpp.core.color.encode`)."""
    return encode(rgb(layers), color_space)


class ViewRenderer:
    """One scene with the ``nerfpp`` integrator holding ``model``; renders model-frame cameras.

    The model is rendered with its own settings
    (:attr:`~mi_nerfpp.core.model.NeRFPPModel.render_settings`: the sample counts it was trained
    with, its background); ``sampling`` and ``background`` override them. ``skip_empty=False``
    samples whole rays (the integrator's ``skip_empty``); ``chunk_rays``: the integrator's
    (its default when None); ``appearance_image``: render with that training image's appearance
    (the integrator's; -1: neutral)."""

    def __init__(self, model, sampling: Sampling | None = None, background: bool | None = None,
                 skip_empty: bool = True, chunk_rays: int | None = None,
                 appearance_image: int = -1):
        self.model = model
        integrator = {'type': 'nerfpp', 'skip_empty': bool(skip_empty),
                      'appearance_image': int(appearance_image)}
        if chunk_rays is not None:
            integrator['chunk_rays'] = int(chunk_rays)
        if sampling is not None:
            integrator.update(fg_samples=sampling.fg_samples, bg_samples=sampling.bg_samples,
                              fine_samples=sampling.fine_samples, near=sampling.near)
        if background is not None:
            integrator['background'] = background
        self.scene = mi.load_dict({'type': 'scene', 'integrator': integrator})
        self.scene.integrator().set_model(model)

    def sensor(self, camera: Camera):
        """A perspective sensor reproducing ``camera`` (model frame) in the world frame."""
        norm = self.model.normalization
        desc = mitsuba_sensor_dict(norm.to_world_camera(camera))
        desc['sampler'] = {'type': 'stratified', 'sample_count': 1, 'jitter': False}
        # Mitsuba starts rays on the near plane: keep it at a negligible model-frame distance.
        desc['near_clip'] = norm.to_world_distance(VIEW_NEAR_CLIP)
        return mi.load_dict(desc)

    def render(self, camera: Camera, with_attributes=False):
        """All layers of one view: channel name -> (H, W) float32 (and the EXR header
        attributes of the view with ``with_attributes``)."""
        sensor = self.sensor(camera)
        layers = render_layers(mi.render(self.scene, sensor=sensor), self.scene.integrator())
        return (layers, exr_attributes(sensor)) if with_attributes else layers


def render_view(model, camera: Camera, sampling: Sampling | None = None,
                background: bool | None = None):
    """All layers of one view of ``model`` (a one-off :class:`ViewRenderer`)."""
    return ViewRenderer(model, sampling, background).render(camera)
