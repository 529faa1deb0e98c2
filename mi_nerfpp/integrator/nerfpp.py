"""The Mitsuba integrator ``nerfpp``: NeRF++ rendering with compositing layers as AOVs.

:class:`NeRFPPIntegrator` reads its XML parameters once (checked by :mod:`.parameters`), loads
its model (:mod:`.loading`) and renders each camera sample with one of two strategies: the
volumes alone (:class:`VolumesOnly`, :class:`~.volumes.VolumeRenderer`) or the volumes with the
scene's shapes (:class:`VolumesAndShapes`, :class:`~.shapes.ShapeRenderer`).
"""
from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np
from mitsuba.ad.integrators.common import ADIntegrator

from mi_nerfpp.core.budget import RENDER_CHUNK_RAYS, check_chunk_sizes
from mi_nerfpp.core.geometry import pixel_footprint
from mi_nerfpp.core.layers import AOVS, aov_list, rst_table
from mi_nerfpp.core.model import FIELD_KINDS, NeRFPPModel
from mi_nerfpp.core.objects import split_scene
from mi_nerfpp.core.rays import Rays
from mi_nerfpp.core.render import Sampling
from mi_nerfpp.integrator.loading import check_appearance, load_model
from mi_nerfpp.integrator.parameters import (MAX_FILM_SAMPLES, ParameterReader,
                                             check_film, check_sensor)
from mi_nerfpp.integrator.shapes import ShapeRenderer
from mi_nerfpp.integrator.volumes import VolumeRenderer, in_chunks


class NeRFPPIntegrator(ADIntegrator):
    r"""
    .. _integrator-nerfpp:

    NeRF++ (``nerfpp``)
    -------------------

    Renders a NeRF++ scene representation: a foreground volume inside the unit
    sphere and an inverted-sphere background volume, composited as in the
    paper's Eq. 4, ``C = C_fg + λ·C_bg``. The model lives in a normalized frame; a
    checkpoint carries the normalization, so sensors and shapes are placed in the
    original world frame.

    The scene's shapes are rendered inside the reconstruction
    (:mod:`mi_nerfpp.core.objects`): a camera ray integrates the volumes up to the
    first surface and sees the surface through the remaining transmittance; the
    surface is path traced with its BSDF (``max_depth``, ``rr_depth`` as in
    Mitsuba's ``path``), and every path segment that leaves a surface takes the
    volumes' radiance along it, from its vertex to the next surface or to
    infinity, so the reconstruction lights and is reflected by the objects with
    parallax. Area, point, spot and directional emitters add next-event
    estimation, their shadow rays attenuated by the volumes (``volume_shadows``;
    the opaque end of the background at infinity excepted); environment maps
    are refused (the background volume is the environment). Shapes listed in
    ``shadow_catchers`` or ``proxies`` are not rendered: they stand for a
    reconstructed surface (the ground). On a shadow catcher the volumes seen
    through it are scaled by the ratio of its irradiance with and without the
    objects (the occlusion part of differential rendering, against a map of the
    reconstruction rendered once per frame), so objects cast shadows on the
    reconstruction. A scene without shapes renders exactly as the volumes alone,
    with no intersection work.

    The model comes from ``checkpoint``, or from Python: :meth:`set_model` hands
    the integrator a model already in memory (evaluation does this with the
    model it trains). Only when neither is given and the integrator is asked
    to render (or traversed) does it build seeded random fields.

    .. pluginparameters::

     * - checkpoint
       - |string|
       - Model file written by ``optimize.py`` (.npz), relative paths resolved
         against the scene file's folder. Without it, seeded random fields are
         rendered, unless a model is handed over with :meth:`set_model`.
         (Default: none)
     * - field
       - |string|
       - Field kind of a model without checkpoint: ``grid`` (grid + MLP),
         ``nerf`` (NeRF-MLP) or ``vanilla`` (vanilla MLP). (Default: ``grid``)
     * - seed
       - |int|
       - Seed of the random fields when there is no checkpoint. (Default: 0)
     * - fg_samples
       - |int|
       - Coarse samples per ray in the foreground volume. (Default: the
         model's, :class:`~mi_nerfpp.core.model.RenderSettings`: a checkpoint renders
         with the counts it was trained with, older checkpoints with those of
         their training config; random fields with 64)
     * - bg_samples
       - |int|
       - Coarse samples per ray in the background volume. (Default: the
         model's, as ``fg_samples``; random fields: 64)
     * - fine_samples
       - |int|
       - Fine samples per ray and volume, drawn from the coarse weights by
         inverse CDF; 0 disables hierarchical sampling. (Default: the model's,
         as ``fg_samples``; random fields: 128)
     * - near
       - |float|
       - Foreground samples of camera rays start at this ray distance (normalized
         units); rays that leave a surface start at it. (Default: the model's, 0)
     * - background
       - |bool|
       - Render the background volume (``false``: foreground over black).
         (Default: whether the model has one, i.e. ``false`` for models trained
         with ``--model nerf``)
     * - skip_empty
       - |bool|
       - Skip the space that the model's occupancy grids mark empty, as training
         did. Off: every interval of both volumes is sampled, with 64 + 64 + 128
         samples unless the counts are given: slower, and directions that few
         training rays constrained (camera paths that leave the captured ring)
         render without the rectangular cells that the grids' edges cut into the
         haze there (on the default capture 0.14 dB lower on the test views).
         (Default: true)
     * - stratified
       - |bool|
       - Jitter sample positions within their strata (using the sampler); off
         gives deterministic midpoints, as NeRF does at test time; a ray's jitter
         does not depend on ``chunk_rays``. (Default: false)
     * - occluded_background
       - |bool|
       - Also render the background behind opaque foreground (transmittance
         ``λ < 1e-4``), for a complete ``bg`` layer. Off: those pixels' ``bg``
         layer is 0 and the render is faster; the beauty changes by at most
         ``1e-4``. Differentiable renders always render it. (Default: false)
     * - fill_unseen
       - |bool|
       - Paint the background where no two training views looked (the sky
         above a ring of cameras) with the broad colour of the nearest
         directions they saw, blended in by how many saw it
         (:mod:`~mi_nerfpp.core.coverage`), instead of the background
         volume's cells there, which few rays or none trained. A checkpoint
         holds the fill only when its run found that it paints the validation
         views' unseen pixels better than the volume; without one (or off),
         the volume everywhere. (Default: true)
     * - chunk_rays
       - |int|
       - Primal renders are evaluated in chunks of this many rays to bound
         memory. (Default: 32768)
     * - appearance_image
       - |int|
       - Render with the appearance learned for this training image: its colour
         transform (exposure, white balance) of a model trained with
         ``--appearance``, its appearance code of one trained with
         ``--appearance-embedding``; -1 renders neutral (the model's own colour,
         of the capture's average exposure, and the zero code). An index the model
         has no appearance for is refused. (Default: -1)
     * - max_samples
       - |int|
       - Largest film (pixels times samples per pixel) a render accepts; larger
         ones are refused before any memory is taken. (Default: 16777216,
         :data:`~mi_nerfpp.integrator.parameters.MAX_FILM_SAMPLES`)
     * - max_depth
       - |int|
       - Longest light path through the scene's shapes, in segments (1: the
         surfaces show their emission only; 2: direct light from the volumes
         and the emitters; ...). -1 (unbounded) is refused. (Default: 6)
     * - rr_depth
       - |int|
       - Depth from which Russian roulette may end a path. (Default: 5)
     * - shadow_catchers
       - |string|
       - Comma-separated ids of shapes that are shadow catchers (Mitsuba
         refuses unknown properties on shapes, so they are named here). (Default: none)
     * - proxies
       - |string|
       - Comma-separated ids of shapes that stand for the reconstruction and
         are never rendered, like the catchers, but receive no shadows (a
         catcher whose shadows are turned off). (Default: none)
     * - catcher_samples
       - |int|
       - Directions per camera sample over a catcher's hemisphere for its
         irradiance ratio (ray tests against the objects; the reconstruction's
         radiance along each comes from a map rendered once per frame). (Default: 16)
     * - volume_shadows
       - |bool|
       - Attenuate the light of the scene's emitters by the volumes'
         transmittance along each shadow ray (the reconstruction shadows the
         objects); off: shadow rays see shapes only, and are cheaper. (Default: true)

    Unknown parameters, values of the wrong type and out-of-range values are
    refused with a message naming the parameter; so are sizes beyond what a
    render holds (sample counts, ``max_depth`` and ``catcher_samples`` times
    ``chunk_rays``, the film, a sensor with a non-finite ``to_world`` or farther
    than 1e4 unit-sphere radii from the model), with the largest value that
    fits, before Dr.Jit sees them (:mod:`~mi_nerfpp.integrator.parameters`). The model carries how it is
    rendered (:attr:`~mi_nerfpp.core.model.NeRFPPModel.render_settings`: its sample
    counts, ``near``, whether it has a background, where it composites); the
    parameters above that say "the model's" override those settings one by one,
    also for a model handed over with :meth:`set_model`.

    Renderers other than Mitsuba's (deep output, :mod:`mi_nerfpp.output.deep`)
    use the same code through :meth:`look_through` (the camera of the depth
    layer), :meth:`frame` (the scene's shapes, split once per frame) and
    :meth:`render_rays`, whose ``record`` receives the per-sample render.

    Radiance is scene-linear (Rec.709 primaries), also for models fitted to
    sRGB photos (:meth:`~mi_nerfpp.core.model.NeRFPPModel.radiance_fields`).
    The AOVs are the *sample channels* of :data:`mi_nerfpp.core.layers.AOVS`, after
    the film's ``R G B [A]``: per-sample values that the film averages, from
    which :func:`mi_nerfpp.output.views.render_layers` develops the layers below
    (ratios of averages, so that they add up at any samples per pixel:
    :mod:`mi_nerfpp.core.layers`):

    {layer_table}
    """

    def __init__(self, props):
        read = ParameterReader(props)
        # Mitsuba's base class reads these two with messages of its own ('"rr_depth" must be set
        # to a value greater than zero!'): checked first, so that a bad value is named here.
        self.max_depth = read('max_depth', int, 6, minimum=1)
        self.rr_depth = read('rr_depth', int, 5, minimum=1)
        super().__init__(props)
        self.checkpoint = read('checkpoint', str, '')
        self.random_field = read('field', str, 'grid', choices=FIELD_KINDS)
        self.random_seed = read('seed', int, 0, minimum=0)
        # Overrides of the model's render settings (None: the model's).
        self.sampling_overrides = {
            'fg_samples': read('fg_samples', int, None, minimum=1),
            'bg_samples': read('bg_samples', int, None, minimum=1),
            'fine_samples': read('fine_samples', int, None, minimum=0),
            'near': read('near', float, None, minimum=0.0)}
        self.background_override = read('background', bool, None)
        self.skip_empty = read('skip_empty', bool, True)
        self.stratified = read('stratified', bool, False)
        self.occluded_background = read('occluded_background', bool, False)
        self.fill_unseen = read('fill_unseen', bool, True)
        self.chunk_rays = read('chunk_rays', int, RENDER_CHUNK_RAYS, minimum=1)
        self.appearance_image = read('appearance_image', int, -1, minimum=-1)
        self.max_samples = read('max_samples', int, MAX_FILM_SAMPLES, minimum=1)
        # Ours over what the base class set (the same values, read and checked above).
        self.max_depth, self.rr_depth = read('max_depth', int, 6), read('rr_depth', int, 5)
        self.shadow_catchers = _ids(read('shadow_catchers', str, ''))
        self.proxies = _ids(read('proxies', str, ''))
        self.catcher_samples = read('catcher_samples', int, 16, minimum=1)
        self.volume_shadows = read('volume_shadows', bool, True)
        read.reject_unknown()
        if self.random_seed >= 2 ** 32:
            raise ValueError(f"nerfpp: parameter 'seed' is {self.random_seed}; the largest "
                             f"seed is {2 ** 32 - 1}")
        check_chunk_sizes(self.chunk_rays, self.sampling_overrides, self.max_depth,
                          self.catcher_samples)
        self.show_progress = False
        self.camera = None           # (centre, view axis) of the sensor: the depth layer's
        self._model, self.meta = None, {}
        if self.checkpoint:
            self._model, self.meta = load_model(self.checkpoint)
            check_appearance(self._model, self.appearance_image)
        self.volumes = VolumeRenderer(self)
        self.shapes = ShapeRenderer(self, self.volumes)

    @property
    def model(self):
        """The :class:`~mi_nerfpp.core.model.NeRFPPModel` rendered: the checkpoint's, the one
        given to :meth:`set_model`, or (built on first use) seeded random fields."""
        if self._model is None:
            self._model = NeRFPPModel.create(field=self.random_field, seed=self.random_seed)
        return self._model

    @property
    def sampling(self) -> Sampling:
        """Samples per ray: the model's (:attr:`~mi_nerfpp.core.model.NeRFPPModel.render_settings`),
        or whole rays' (:class:`~mi_nerfpp.core.render.Sampling`'s defaults) without
        ``skip_empty``, with the ones the XML gives in their place."""
        given = {k: v for k, v in self.sampling_overrides.items() if v is not None}
        settings = self.model.render_settings.sampling
        if not self.skip_empty:
            settings = Sampling(near=settings.near)
        return dataclasses.replace(settings, **given)

    @property
    def background(self) -> bool:
        """Whether the background volume is rendered: the XML's ``background``, else whether
        the model has one."""
        if self.background_override is not None:
            return self.background_override
        return self.model.render_settings.background

    def set_model(self, model, meta=None):
        """Render ``model`` (a :class:`~mi_nerfpp.core.model.NeRFPPModel`) from now on."""
        check_appearance(model, self.appearance_image)
        self._model, self.meta = model, meta or {}

    def aov_names(self):
        """The AOV channels, in :data:`mi_nerfpp.core.layers.AOVS` order."""
        return list(AOVS)

    def to_string(self):
        given = {k: v for k, v in dict(self.sampling_overrides,
                                       background=self.background_override).items()
                 if v is not None}
        settings = ', '.join(f'{k}={v}' for k, v in given.items()) or "the model's settings"
        return f'NeRFPPIntegrator[checkpoint="{self.checkpoint}", {settings}]'

    def traverse(self, cb):
        for k, v in self.model.parameters().items():
            cb.put(k, v, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        # Fields read their parameter dict on every evaluation: nothing to rebuild.
        pass

    # ------------------------------------------------------------------ rendering

    def prepare(self, sensor, seed=0, spp=0, aovs=()):
        """Refuses films beyond ``max_samples``, an empty film, a sample count of 0, sample
        counts beyond what a chunk holds and a sensor with a non-finite or far-away
        ``to_world`` before Mitsuba or Dr.Jit allocates anything
        (:mod:`~mi_nerfpp.integrator.parameters`), and looks through ``sensor``."""
        check_film(sensor.film().crop_size(), spp or sensor.sampler().sample_count(),
                   self.max_samples)
        self.look_through(sensor)
        return super().prepare(sensor, seed, spp, list(aovs))

    def look_through(self, sensor):
        """Render for ``sensor`` from now on: the depth layer is measured along its view axis.
        Refuses sample counts beyond what a chunk holds and a sensor with a non-finite or
        far-away ``to_world``."""
        check_chunk_sizes(self.chunk_rays, self.sampling, self.max_depth, self.catcher_samples)
        check_sensor(sensor.world_transform().matrix, self.model.normalization)
        self.camera = camera_axis(sensor)

    def camera_depth(self, o, d, t):
        """The depth layer of points at distance ``t`` along rays ``o + t·d``: along the
        camera's view axis (:meth:`look_through`), or the distance itself before any."""
        if self.camera is None:
            return t
        center, axis = self.camera
        return dr.dot(o - center, axis) + t * dr.dot(dr.normalize(d), axis)

    def frame(self, scene):
        """How ``scene`` is rendered, decided once per frame: :class:`VolumesOnly` for a scene
        without shapes (no intersection work), else :class:`VolumesAndShapes` (the shapes
        split into objects, shadow catchers and proxies; the catchers' environment map
        rendered once). A new split each time: a cached one would keep the scene alive."""
        parts = split_scene(scene, self.shadow_catchers, self.proxies)
        if parts.objects is None and parts.catchers is None:
            return VolumesOnly(self)
        return VolumesAndShapes(self, parts)

    def render_rays(self, frame, rays: Rays, primal=True, record=None):
        """Beauty and AOVs (``{channel: Float}``) of camera ``rays``
        (:class:`~mi_nerfpp.core.rays.Rays` in world space: their ``seed`` jitters the samples,
        None: strata midpoints; their ``path_seed`` picks the paths through the shapes, None:
        the rays' indices; their ``footprint``, the pixels') through ``frame`` (:meth:`frame`),
        in chunks of ``chunk_rays`` when ``primal``. ``record`` (a dict; one chunk of rays,
        ``primal`` only) receives the render's per-sample arrays (deep output)."""
        if frame.traces_paths and rays.path_seed is None:
            rays = rays.replace(path_seed=dr.arange(mi.UInt32, rays.width))
        if not primal or record is not None:
            return frame.layers(rays, primal, record)
        return in_chunks(lambda chunk: frame.layers(chunk, True), rays, self.chunk_rays,
                         progress=self.show_progress)

    def sample(self, mode, scene, sampler, ray, active=True, **kwargs):
        """One camera sample per ray (Mitsuba's entry point): both volumes sampled and
        integrated by quadrature, composited by Eq. 4, developed into the layers
        (:meth:`~.volumes.VolumeRenderer.layers`), through the scene's shapes where it has
        some (:meth:`~.shapes.ShapeRenderer.layers`)."""
        # --------------------------- Variables declared up front --------------------------
        primal = mode == dr.ADMode.Primal      # a render, not a gradient pass
        frame = self.frame(scene)              # volumes alone, or volumes and shapes
        n = dr.width(ray.o)                    # camera samples in this wavefront

        # ------------------------------- The camera rays ----------------------------------
        # Origins and unit directions in world space, each ray's pixel footprint (for grids
        # that filter by it), the jitter of its samples along the ray (None: strata midpoints)
        # and, where the scene has shapes, the seed of its paths: the sample's index hashed
        # with the sampler (which carries the render's seed), so that no two samples share a
        # path even where the sampler repeats.
        rays = Rays(mi.Point3f(dr.detach(ray.o)), mi.Vector3f(dr.detach(ray.d)),
                    footprint=pixel_footprint(ray))
        if self.stratified:
            rays.seed = mi.UInt32(sampler.next_1d() * 4294967040.0)
        if frame.traces_paths:
            rays.path_seed, _ = mi.sample_tea_32(dr.arange(mi.UInt32, n), mi.UInt32(
                sampler.next_1d() * 4294967040.0))

        # ---------- Samples, quadrature and Eq. 4, developed into the layers --------------
        # (Section 4 of the paper: both volumes sampled and integrated, then composited;
        # through the scene's shapes where it has some.)
        L, aovs = self.render_rays(frame, rays, primal)
        return L, mi.Bool(True), aov_list(aovs, lambda: dr.zeros(mi.Float, n)), None


class VolumesOnly:
    """The strategy for a scene without shapes: the volumes alone, without any intersection;
    the objects' layers are 0."""
    traces_paths = False

    def __init__(self, integrator):
        self.volumes = integrator.volumes

    def layers(self, rays, primal, record=None):
        L, aovs, _ = self.volumes.layers(rays, primal, record=record)
        return L, aovs


class VolumesAndShapes:
    """The strategy for a scene with shapes: the volumes up to the first surface, the surfaces
    path traced with the volumes as their light, the shadow catchers' differential shading
    (:class:`~.shapes.ShapeRenderer`)."""
    traces_paths = True

    def __init__(self, integrator, parts):
        self.shapes, self.parts = integrator.shapes, parts
        self.environment = None
        if parts.catchers is not None and parts.objects is not None:
            with dr.suspend_grad():
                self.environment = integrator.shapes.catcher_environment(parts)

    def layers(self, rays, primal, record=None):
        return self.shapes.layers(self.parts, rays, primal, self.environment, record)


def _ids(text):
    """The shape ids of a comma-separated list."""
    return tuple(c.strip() for c in text.split(',') if c.strip())


if NeRFPPIntegrator.__doc__:     # (None under python -OO)
    NeRFPPIntegrator.__doc__ = NeRFPPIntegrator.__doc__.replace(
        '{layer_table}', rst_table('    ').lstrip())


def camera_axis(sensor):
    """``(centre, view axis)`` of a sensor in the world frame (Mitsuba cameras look along +z)."""
    m = np.array(sensor.world_transform().matrix, dtype=np.float64).reshape(4, 4)
    axis = m[:3, 2] / np.linalg.norm(m[:3, 2])
    return mi.ScalarPoint3f(*m[:3, 3]), mi.ScalarVector3f(*axis)


def register():
    mi.register_integrator('nerfpp', lambda props: NeRFPPIntegrator(props))
