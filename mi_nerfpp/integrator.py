"""The Mitsuba integrator ``nerfpp``: NeRF++ rendering with compositing layers as AOVs."""
from __future__ import annotations

import dataclasses
import os

import drjit as dr
import mitsuba as mi
from mitsuba.ad.integrators.common import ADIntegrator

from .checkpoint import load_checkpoint
from .color import srgb_to_linear
from .layers import AOVS, BACKGROUND_WEIGHT_FLOOR, aov_list, layer_channels, rst_table
from .model import FIELD_KINDS, NeRFPPModel
from .objects import combine, path_rng, split_scene, trace_paths
from .render import Sampling, render_rays, surface_distance

# Largest number of camera rays (film pixels x samples per pixel) one render may trace: memory
# grows by roughly 100 bytes per ray, so this bounds a render to about 2 GB. Raise it with the
# ``max_samples`` parameter on a machine with more memory.
MAX_FILM_SAMPLES = 1 << 24

_XML_TAGS = {int: 'integer', float: 'float', bool: 'boolean', str: 'string'}


class _ParameterReader:
    """Reads the integrator's XML parameters once, each with its type and range checked."""

    def __init__(self, props):
        self.props, self.known = props, set()

    def __call__(self, name, kind, default, minimum=None, choices=None):
        self.known.add(name)
        if name not in self.props:
            return default
        value = self.props.get(name)
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or (kind is not bool and isinstance(value, bool)):
            raise ValueError(
                f"nerfpp: parameter '{name}' must be given as <{_XML_TAGS[kind]} "
                f"name=\"{name}\" value=\"...\"/>, got {type(value).__name__} {value!r}")
        if kind in (int, float) and not value == value:
            raise ValueError(f"nerfpp: parameter '{name}' is NaN")
        if minimum is not None and value < minimum:
            raise ValueError(f"nerfpp: parameter '{name}' must be >= {minimum}, got {value}")
        if choices is not None and value not in choices:
            raise ValueError(f"nerfpp: parameter '{name}' must be one of "
                             f"{', '.join(choices)}, got {value!r}")
        return value

    def reject_unknown(self):
        unknown = sorted(set(self.props.unqueried()) - self.known)
        if unknown:
            raise ValueError(f"nerfpp: unknown parameter(s) {', '.join(unknown)}; the nerfpp "
                             f"integrator takes {', '.join(sorted(self.known))}")


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
    (:mod:`mi_nerfpp.objects`): a camera ray integrates the volumes up to the
    first surface and sees the surface through the remaining transmittance; the
    surface is path traced with its BSDF (``max_depth``, ``rr_depth`` as in
    Mitsuba's ``path``), and every path segment that leaves a surface takes the
    volumes' radiance along it, from its vertex to the next surface or to
    infinity, so the reconstruction lights and is reflected by the objects with
    parallax. Area, point, spot and directional emitters add next-event
    estimation, their shadow rays attenuated by the volumes (``volume_shadows``;
    the opaque end of the background at infinity excepted); environment maps
    are refused (the background volume is the environment). Shapes listed in
    ``shadow_catchers`` are not rendered: they stand for a reconstructed surface
    (the ground), and the volumes seen through them are scaled by the ratio of
    their irradiance with and without the objects (differential rendering), so
    objects cast shadows on the reconstruction. A scene without shapes renders
    exactly as the volumes alone, with no intersection work.

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
         model's, :class:`~mi_nerfpp.model.RenderSettings`: a checkpoint renders
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
     * - chunk_rays
       - |int|
       - Primal renders are evaluated in chunks of this many rays to bound
         memory. (Default: 32768)
     * - appearance_image
       - |int|
       - Render with the colour transform (exposure, white balance) learned for
         this training image of a model trained with ``--appearance``; -1 renders
         neutral (the model's own colour, that of training image 0). An index
         the model has no transform for is refused. (Default: -1)
     * - max_samples
       - |int|
       - Largest film (pixels times samples per pixel) a render accepts; larger
         ones are refused before any memory is taken. (Default: 16777216,
         :data:`MAX_FILM_SAMPLES`)
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
     * - catcher_samples
       - |int|
       - Directions per camera sample over a catcher's hemisphere for its
         irradiance ratio. (Default: 16)
     * - volume_shadows
       - |bool|
       - Attenuate the light of the scene's emitters by the volumes'
         transmittance along each shadow ray (the reconstruction shadows the
         objects); off: shadow rays see shapes only, and are cheaper. (Default: true)

    Unknown parameters, values of the wrong type and out-of-range values are
    refused with a message naming the parameter. The model carries how it is
    rendered (:attr:`~mi_nerfpp.model.NeRFPPModel.render_settings`: its sample
    counts, ``near``, whether it has a background, where it composites); the
    parameters above that say "the model's" override those settings one by one,
    also for a model handed over with :meth:`set_model`.

    Radiance is scene-linear (Rec.709 primaries), also for models fitted to
    sRGB photos (:meth:`~mi_nerfpp.model.NeRFPPModel.radiance_fields`).
    The AOVs follow the film's ``R G B [A]`` in this order (the layers of
    :mod:`mi_nerfpp.layers`; :func:`mi_nerfpp.views.render_layers` reads a
    render by name, and sets the beauty ``A``):

    {layer_table}
    """

    def __init__(self, props):
        super().__init__(props)
        read = _ParameterReader(props)
        self.checkpoint = read('checkpoint', str, '')
        # Overrides of the model's render settings (None: the model's, see ``sampling``).
        self._sampling = {
            'fg_samples': read('fg_samples', int, None, minimum=1),
            'bg_samples': read('bg_samples', int, None, minimum=1),
            'fine_samples': read('fine_samples', int, None, minimum=0),
            'near': read('near', float, None, minimum=0.0)}
        self._background = read('background', bool, None)
        self.stratified = read('stratified', bool, False)
        self.occluded_background = read('occluded_background', bool, False)
        self.chunk_rays = read('chunk_rays', int, 1 << 15, minimum=1)
        self.max_samples = read('max_samples', int, MAX_FILM_SAMPLES, minimum=1)
        self.random_field = read('field', str, 'grid', choices=FIELD_KINDS)
        self.random_seed = read('seed', int, 0, minimum=0)
        self.appearance_image = read('appearance_image', int, -1, minimum=-1)
        self.max_depth = read('max_depth', int, 6, minimum=1)
        self.rr_depth = read('rr_depth', int, 5, minimum=1)
        catchers = read('shadow_catchers', str, '')
        self.shadow_catchers = tuple(c.strip() for c in catchers.split(',') if c.strip())
        self.catcher_samples = read('catcher_samples', int, 16, minimum=1)
        self.volume_shadows = read('volume_shadows', bool, True)
        read.reject_unknown()
        self.show_progress = False
        self._model, self.meta = None, {}
        self._view = None
        if self.checkpoint:
            # Relative paths are found next to the scene file (Mitsuba's file resolver).
            resolver = mi.file_resolver()
            path = str(resolver.resolve(self.checkpoint))
            if not os.path.isfile(path):
                places = [os.path.abspath(os.path.join(str(resolver[i]), self.checkpoint))
                          for i in range(len(resolver))] or [os.path.abspath(path)]
                raise ValueError(
                    f"nerfpp: checkpoint '{self.checkpoint}' not found (looked for "
                    f"{', '.join(dict.fromkeys(places))}; relative paths are resolved against "
                    f"the scene file's folder)")
            self._model, self.meta, _ = load_checkpoint(path)
            self._check_appearance(self._model)

    @property
    def model(self):
        """The :class:`~mi_nerfpp.model.NeRFPPModel` rendered: the checkpoint's, the one
        given to :meth:`set_model`, or (built on first use) seeded random fields."""
        if self._model is None:
            self._model = NeRFPPModel.create(field=self.random_field, seed=self.random_seed)
        return self._model

    @property
    def sampling(self) -> Sampling:
        """Samples per ray: the model's (:attr:`~mi_nerfpp.model.NeRFPPModel.render_settings`)
        with the ones the XML gives in their place."""
        given = {k: v for k, v in self._sampling.items() if v is not None}
        return dataclasses.replace(self.model.render_settings.sampling, **given)

    @property
    def background(self) -> bool:
        """Whether the background volume is rendered: the XML's ``background``, else whether
        the model has one."""
        if self._background is not None:
            return self._background
        return self.model.render_settings.background

    def set_model(self, model, meta=None):
        """Render ``model`` (a :class:`~mi_nerfpp.model.NeRFPPModel`) from now on."""
        self._check_appearance(model)
        self._model, self.meta = model, meta or {}

    def _check_appearance(self, model):
        n = model.appearance_images
        if self.appearance_image >= n:
            have = (f'transforms for training images 0..{n - 1}' if n else
                    'no appearance transforms (train with --appearance)')
            raise ValueError(f"nerfpp: parameter 'appearance_image' is {self.appearance_image} "
                             f"but the model has {have}; -1 renders neutral")

    def _transform(self):
        """``(gain, bias)`` (Color3f) of the chosen training image's colour transform."""
        from .appearance import single
        gain, bias = single(self.model.appearance.numpy(), self.appearance_image)
        return mi.Color3f(*map(float, gain)), mi.Color3f(*map(float, bias))

    def aov_names(self):
        """The AOV channels, in :data:`mi_nerfpp.layers.AOVS` order."""
        return list(AOVS)

    def to_string(self):
        given = {k: v for k, v in dict(self._sampling, background=self._background).items()
                 if v is not None}
        settings = ', '.join(f'{k}={v}' for k, v in given.items()) or "the model's settings"
        return f'NeRFPPIntegrator[checkpoint="{self.checkpoint}", {settings}]'

    def traverse(self, cb):
        for k, v in self.model.parameters().items():
            cb.put(k, v, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        # Fields read their parameter dict on every evaluation: nothing to rebuild.
        pass

    def prepare(self, sensor, seed=0, spp=0, aovs=()):
        """Refuses films beyond ``max_samples`` and a sample count of 0 before Mitsuba
        allocates anything, and notes the camera frame for the depth layer."""
        size = sensor.film().crop_size()
        count = spp or sensor.sampler().sample_count()
        if count < 1:
            raise ValueError('nerfpp: the sampler has sample_count 0: give it at least 1 '
                             '(<integer name="sample_count" value="1"/>) or pass spp >= 1')
        rays = int(size[0]) * int(size[1]) * int(count)
        if rays > self.max_samples:
            raise ValueError(
                f'nerfpp: a {size[0]}x{size[1]} film at {count} samples per pixel traces '
                f'{rays} rays, more than max_samples={self.max_samples} (about 100 bytes each): '
                f'render a smaller film or crop, or raise the integrator\'s max_samples')
        self._view = camera_axis(sensor)
        return super().prepare(sensor, seed, spp, list(aovs))

    def render_layers(self, o, d, seed, primal=False, far=None):
        """Beauty and volume AOVs of world-space rays: ``(L: Color3f, aovs: {channel: Float})``
        (the ``fg``, ``bg``, ``depth`` and ``distance`` channels), the volumes ending at
        ``far`` (world units per ray, ``inf``: no end; None: all)."""
        L, aovs, _ = self._volume(o, d, seed, primal, far)
        return L, aovs

    def _volume(self, o, d, seed, primal=False, far=None, transform=True, camera=True):
        """:meth:`render_layers` plus the composite opacity (``1 -`` the transmittance to
        ``far``); ``transform=False`` leaves out the appearance transform; ``camera=False``
        (rays that leave a surface) starts the samples at the ray origin, not at ``near``."""
        model = self.model
        norm = model.normalization
        fg_field, bg_field = model.radiance_fields()
        sampling = self.sampling
        if not camera:      # path segments that leave a surface: from their origin on
            sampling = dataclasses.replace(sampling, near=0.0)
        res = render_rays(*norm.to_model_rays(o, d), fg_field,
                          bg_field if self.background else None, sampling, seed,
                          occupancy=model.occupancy,
                          skip_occluded=primal and not self.occluded_background,
                          far=None if far is None else norm.to_model_distance(far))
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
            gain, bias = self._transform()
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
        return L, aovs, res.fine.opacity

    def sample(self, mode, scene, sampler, ray, active=True, **kwargs):
        o, d = mi.Point3f(dr.detach(ray.o)), mi.Vector3f(dr.detach(ray.d))
        seed = None
        if self.stratified:
            seed = mi.UInt32(sampler.next_1d() * 4294967040.0)
        n = dr.width(o)
        # (Split on every render, not cached: a cache would keep the scene alive.)
        parts = split_scene(scene, self.shadow_catchers)
        if parts.objects is None and parts.catchers is None:
            # No shapes: the volumes alone, without any intersection.
            if mode != dr.ADMode.Primal:
                L, aovs = self.render_layers(o, d, seed)
            elif n <= self.chunk_rays:
                L, aovs = self.render_layers(o, d, seed, primal=True)
            else:
                L, aovs = self._chunked(lambda o, d, seed: self.render_layers(
                    o, d, seed, primal=True), [o, d, seed], n)
            # The objects' layers are 0.
            return L, mi.Bool(True), aov_list(aovs, lambda: dr.zeros(mi.Float, n)), None
        # One seed per camera sample: its index hashed with the sampler (which carries the
        # render's seed), so no two samples share a path even where the sampler repeats.
        path_seed, _ = mi.sample_tea_32(dr.arange(mi.UInt32, n),
                                        mi.UInt32(sampler.next_1d() * 4294967040.0))
        if mode != dr.ADMode.Primal:
            L, aovs = self._render_scene(parts, o, d, seed, path_seed, primal=False)
        else:
            L, aovs = self._chunked(lambda o, d, seed, path_seed: self._render_scene(
                parts, o, d, seed, path_seed, primal=True), [o, d, seed, path_seed], n)
        return L, mi.Bool(True), aov_list(aovs, lambda: dr.zeros(mi.Float, n)), None

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

    def _render_scene(self, parts, o, d, seed, path_seed, primal, catchers=True,
                      transform=True, camera=True):
        """Beauty and AOVs of camera rays through a scene with shapes (see
        :mod:`mi_nerfpp.objects`): the volumes up to the first surface, the surfaces path
        traced with the volumes as their light, the shadow catchers' differential shading
        (``catchers``); ``transform=False`` leaves out the appearance transform;
        ``camera=False``: the rays start on a surface (see :meth:`_volume`)."""
        n = dr.width(o)
        hit = dr.zeros(mi.Bool, n)
        far0 = None
        if parts.objects is not None:
            paths = trace_paths(parts.objects, mi.Ray3f(o, d), path_seed, self.max_depth,
                                self.rr_depth)
            far0 = dr.gather(mi.Float, paths.far, paths.segment(0))
            hit = ~dr.isinf(far0)
        L0, volumes, opacity0 = self._volume(o, d, seed, primal, far0, transform, camera)
        surfaces = dr.zeros(mi.Color3f, n)
        if parts.objects is not None:
            # Every segment's volumes: the camera segment's from above, the others here.
            L_seg = dr.zeros(mi.Color3f, paths.n * paths.depth)
            T_seg = dr.ones(mi.Float, paths.n * paths.depth)
            if paths.depth > 1:
                later = dr.compress(paths.valid & (dr.arange(mi.UInt32, dr.width(paths.valid))
                                                   >= n))
                if dr.width(later):
                    L_k, T_k = self._volume_batch(dr.gather(mi.Point3f, paths.o, later),
                                                  dr.gather(mi.Vector3f, paths.d, later),
                                                  dr.gather(mi.Float, paths.far, later), primal)
                    dr.scatter(L_seg, L_k, later)
                    dr.scatter(T_seg, T_k, later)
            dr.scatter(T_seg, 1.0 - opacity0, paths.segment(0))
            if self.volume_shadows:
                paths.vertex = self._shadowed_by_volumes(paths, primal)
            _, surfaces = combine(paths, L_seg, T_seg)
            if self.appearance_image >= 0 and transform:
                surfaces = self._transform()[0] * surfaces
        shadow = dr.zeros(mi.Color3f, n)
        if catchers and parts.catchers is not None and parts.objects is not None:
            shadow = self._shadow(parts, o, d, far0, L0, path_seed, primal)
        t_hit = dr.select(hit, far0, 0.0) if far0 is not None else dr.zeros(mi.Float, n)
        z_hit = t_hit
        if self._view is not None:
            center, axis = self._view
            z_hit = dr.dot(o - center, axis) + t_hit * dr.dot(dr.normalize(d), axis)
        # The surface is the depth where the volumes in front of it stay below half opacity.
        depth = dr.select(hit & (opacity0 < 0.5), z_hit, volumes['depth.Z'])
        distance = volumes['distance.Y'] + dr.select(hit, (1.0 - opacity0) * t_hit, 0.0)
        mask = dr.select(hit, 1.0, 0.0)
        fg_alpha = volumes['fg.A']
        aovs = dict(volumes, **layer_channels(
            depth=(depth,), distance=(distance,),
            obj=(surfaces.x, surfaces.y, surfaces.z, mask),
            obj_depth=(dr.select(hit, z_hit, 0.0),),
            shadow=(shadow.x, shadow.y, shadow.z),
            # Without the background: the foreground over the shapes, sample by sample.
            A=(dr.full(mi.Float, 1.0, n) if self.background
               else fg_alpha + (1.0 - fg_alpha) * mask,)))
        return L0 + surfaces + shadow, aovs

    def _shadowed_by_volumes(self, paths, primal):
        """The paths' vertex light with next-event estimation attenuated by the volumes'
        transmittance along each shadow ray: ``V - (1 - T)·V_nee``."""
        rays = dr.compress(paths.shadow_far > 0.0)
        if dr.width(rays) == 0:
            return paths.vertex
        _, T = self._volume_batch(dr.gather(mi.Point3f, paths.shadow_o, rays),
                                  dr.gather(mi.Vector3f, paths.shadow_d, rays),
                                  dr.gather(mi.Float, paths.shadow_far, rays), primal)
        vertex = mi.Color3f(paths.vertex)
        dr.scatter(vertex, dr.gather(mi.Color3f, vertex, rays)
                   - (1.0 - T) * dr.gather(mi.Color3f, paths.nee, rays), rays)
        return vertex

    def _shadow(self, parts, o, d, far0, L0, path_seed, primal):
        """Differential rendering on the shadow catchers (Debevec 1998): where a camera ray
        meets a catcher before any object, the radiance ``L0`` of the volumes along it is
        scaled by ``E_with / E_without``, the catcher's irradiance with and without the
        objects, both estimated from the same ``catcher_samples`` cosine-distributed
        directions (a direction that meets no object contributes the same volume radiance
        to both). Returns the change, ``(ratio - 1)·L0`` (0 where no catcher is seen, and
        where no direction meets an object)."""
        n, K = dr.width(o), self.catcher_samples
        ray = mi.Ray3f(o, d)
        if far0 is not None:
            ray.maxt = dr.select(dr.isinf(far0), dr.largest(mi.Float), far0)
        si = parts.catchers.ray_intersect(ray)
        caught = dr.compress(si.is_valid())
        shadow = dr.zeros(mi.Color3f, n)
        m = dr.width(caught)
        if m == 0:
            return shadow
        j = dr.arange(mi.UInt32, m * K)
        ray_of = dr.gather(mi.UInt32, caught, j // K)
        si_k = dr.gather(mi.SurfaceInteraction3f, si, ray_of)
        rng = path_rng(dr.gather(mi.UInt32, path_seed, ray_of), j % K + 1)
        # The hemisphere of the catcher that faces the camera.
        normal = si_k.sh_frame.n
        normal = dr.mulsign(normal, -dr.dot(normal, dr.gather(mi.Vector3f, d, ray_of)))
        u = mi.Point2f(rng.next_float32(), rng.next_float32())
        local = mi.warp.square_to_cosine_hemisphere(u)
        ray_k = si_k.spawn_ray(mi.Frame3f(normal).to_world(local))
        seed_k = rng.next_uint32()
        # Where no direction meets an object the ratio is 1: only catcher points next to
        # objects are shaded, each from all of its directions.
        blocked = parts.objects.ray_test(ray_k)
        near = dr.compress(dr.block_sum(dr.select(blocked, 1, 0), K) > 0)
        if dr.width(near) == 0:
            return shadow
        j = dr.arange(mi.UInt32, dr.width(near) * K)
        r = dr.gather(mi.UInt32, near, j // K) * K + j % K
        o_r, d_r = dr.gather(mi.Point3f, ray_k.o, r), dr.gather(mi.Vector3f, ray_k.d, r)
        without, _ = self._volume_batch(o_r, d_r, dr.full(mi.Float, dr.inf, dr.width(r)), primal)
        with_objects = mi.Color3f(without)
        hits = dr.compress(dr.gather(mi.Bool, blocked, r))
        def render_hits(o, d, seed):
            return self._render_scene(parts, o, d, None, seed, primal, catchers=False,
                                      transform=False, camera=False)
        hit_args = [dr.gather(mi.Point3f, o_r, hits), dr.gather(mi.Vector3f, d_r, hits),
                    dr.gather(mi.UInt32, seed_k, dr.gather(mi.UInt32, r, hits))]
        if primal:      # up to chunk_rays x catcher_samples rays: in chunks too
            L_hit, _ = self._chunked(render_hits, hit_args, dr.width(hits), progress=False)
        else:
            L_hit, _ = render_hits(*hit_args)
        dr.scatter(with_objects, L_hit, hits)
        e_with, e_without = dr.block_sum(with_objects, K), dr.block_sum(without, K)
        ratio = dr.select(e_without > 0.0, e_with / dr.maximum(e_without, 1e-30), 1.0)
        rays = dr.gather(mi.UInt32, caught, near)
        dr.scatter(shadow, (ratio - 1.0) * dr.gather(mi.Color3f, L0, rays), rays)
        return shadow


if NeRFPPIntegrator.__doc__:     # (None under python -OO)
    NeRFPPIntegrator.__doc__ = NeRFPPIntegrator.__doc__.replace(
        '{layer_table}', rst_table('    ').lstrip())


def camera_axis(sensor):
    """``(centre, view axis)`` of a sensor in the world frame (Mitsuba cameras look along +z)."""
    import numpy as np
    m = np.array(sensor.world_transform().matrix, dtype=np.float64).reshape(4, 4)
    axis = m[:3, 2] / np.linalg.norm(m[:3, 2])
    return mi.ScalarPoint3f(*m[:3, 3]), mi.ScalarVector3f(*axis)


def register():
    mi.register_integrator('nerfpp', lambda props: NeRFPPIntegrator(props))
