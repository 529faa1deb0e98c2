"""The Mitsuba integrator ``nerfpp``: NeRF++ rendering with compositing layers as AOVs."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
from mitsuba.ad.integrators.common import ADIntegrator

from .checkpoint import load_checkpoint
from .exr import AOVS
from .model import NeRFPPModel
from .render import Sampling, render_rays


class NeRFPPIntegrator(ADIntegrator):
    r"""
    .. _integrator-nerfpp:

    NeRF++ (``nerfpp``)
    -------------------

    Renders a NeRF++ scene representation: a foreground volume inside the unit
    sphere and an inverted-sphere background volume, composited as in the
    paper's Eq. 4, ``C = C_fg + λ·C_bg``. Scene geometry and emitters are
    ignored; only the sensor matters. The model lives in a normalized frame; a
    checkpoint carries the normalization, so sensors are placed in the
    original world frame.

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
       - Coarse samples per ray in the foreground volume. (Default: 64)
     * - bg_samples
       - |int|
       - Coarse samples per ray in the background volume. (Default: 64)
     * - fine_samples
       - |int|
       - Fine samples per ray and volume, drawn from the coarse weights by
         inverse CDF; 0 disables hierarchical sampling. (Default: 128)
     * - near
       - |float|
       - Foreground samples start at this ray distance (normalized units). (Default: 0)
     * - background
       - |bool|
       - Render the background volume (``false``: foreground over black). (Default: true)
     * - stratified
       - |bool|
       - Jitter sample positions within their strata (using the sampler); off
         gives deterministic midpoints, as NeRF does at test time. (Default: false)
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

    AOVs (after ``R, G, B, A``): ``fg.R fg.G fg.B`` premultiplied foreground
    radiance, ``fg.A`` and ``alpha.Y`` foreground opacity ``1 - λ``,
    ``bg.R bg.G bg.B`` background radiance as seen unoccluded (0 behind opaque foreground unless
    ``occluded_background``), ``depth.Z``
    expected distance along the ray in world units (background at infinity is
    capped at 1000 unit-sphere radii, see :mod:`mi_nerfpp.render`).
    ``beauty = fg + (1 - alpha)·bg``.
    """

    def __init__(self, props):
        super().__init__(props)
        self.checkpoint = props.get('checkpoint', '')
        default = Sampling()      # the XML defaults live in render.Sampling
        self.sampling = Sampling(
            fg_samples=props.get('fg_samples', default.fg_samples),
            bg_samples=props.get('bg_samples', default.bg_samples),
            fine_samples=props.get('fine_samples', default.fine_samples),
            near=props.get('near', default.near))
        for name in ('fg_samples', 'bg_samples'):
            if getattr(self.sampling, name) < 1:
                raise ValueError(f'nerfpp: {name} must be >= 1')
        if self.sampling.fine_samples < 0:
            raise ValueError('nerfpp: fine_samples must be >= 0')
        self.background = props.get('background', True)
        self.stratified = props.get('stratified', False)
        self.occluded_background = props.get('occluded_background', False)
        self.chunk_rays = props.get('chunk_rays', 1 << 15)
        self.show_progress = False
        self.random_field = props.get('field', 'grid')
        self.random_seed = props.get('seed', 0)
        self._model, self.meta = None, {}
        if self.checkpoint:
            # Relative paths are found next to the scene file (Mitsuba's file resolver).
            path = str(mi.file_resolver().resolve(self.checkpoint))
            self._model, self.meta, _ = load_checkpoint(path)

    @property
    def model(self):
        """The :class:`~mi_nerfpp.model.NeRFPPModel` rendered: the checkpoint's, the one
        given to :meth:`set_model`, or (built on first use) seeded random fields."""
        if self._model is None:
            self._model = NeRFPPModel.create(field=self.random_field, seed=self.random_seed)
        return self._model

    def set_model(self, model, meta=None):
        """Render ``model`` (a :class:`~mi_nerfpp.model.NeRFPPModel`) from now on."""
        self._model, self.meta = model, meta or {}

    def aov_names(self):
        return list(AOVS)

    def to_string(self):
        return (f'NeRFPPIntegrator[checkpoint="{self.checkpoint}", {self.sampling}, '
                f'background={self.background}]')

    def traverse(self, cb):
        for k, v in self.model.parameters().items():
            cb.put(k, v, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        # Fields read their parameter dict on every evaluation: nothing to rebuild.
        pass

    def render_layers(self, o, d, seed, primal=False):
        """Beauty and AOVs of world-space rays: ``(L: Color3f, aovs: list[Float])``."""
        model = self.model
        o, d = model.normalization.to_model_rays(o, d)
        res = render_rays(o, d, model.fg, model.bg if self.background else None,
                          self.sampling, seed, occupancy=model.occupancy,
                          skip_occluded=primal and not self.occluded_background)
        fg = res.fg.fine
        bg = res.bg.fine.rgb if res.bg is not None else mi.Color3f(0.0)
        aovs = [fg.rgb.x, fg.rgb.y, fg.rgb.z, fg.opacity, bg.x, bg.y, bg.z, fg.opacity,
                model.normalization.to_world_distance(res.fine.depth)]
        return res.fine.rgb, aovs

    def sample(self, mode, scene, sampler, ray, active=True, **kwargs):
        o, d = mi.Point3f(dr.detach(ray.o)), mi.Vector3f(dr.detach(ray.d))
        seed = None
        if self.stratified:
            seed = mi.UInt32(sampler.next_1d() * 4294967040.0)
        n = dr.width(o)
        if mode != dr.ADMode.Primal:
            L, aovs = self.render_layers(o, d, seed)
        elif n <= self.chunk_rays:
            L, aovs = self.render_layers(o, d, seed, primal=True)
        else:
            L, aovs = self._render_chunked(o, d, seed, n)
        return L, mi.Bool(True), aovs, None

    def _render_chunked(self, o, d, seed, n):
        """Primal rendering of many rays, ``chunk_rays`` at a time (bounded memory)."""
        dr.eval(o, d, seed)
        chunk = self.chunk_rays
        out = [dr.zeros(mi.Float, n) for _ in range(3 + len(AOVS))]
        chunks = range(0, n, chunk)
        if self.show_progress:
            from tqdm import tqdm
            chunks = tqdm(chunks, desc='render', unit='chunk', leave=False)
        for start in chunks:
            # Same-size chunks with an opaque offset: every chunk reuses one compiled kernel.
            i = dr.arange(mi.UInt32, chunk) + dr.opaque(mi.UInt32, start)
            valid = i < n
            j = dr.minimum(i, n - 1)
            L, aovs = self.render_layers(dr.gather(mi.Point3f, o, j), dr.gather(mi.Vector3f, d, j),
                                         None if seed is None else dr.gather(mi.UInt32, seed, j),
                                         primal=True)
            for buf, value in zip(out, [L.x, L.y, L.z] + aovs):
                dr.scatter(buf, value, i, valid)
            dr.eval(out)
        return mi.Color3f(*out[:3]), out[3:]


def register():
    mi.register_integrator('nerfpp', lambda props: NeRFPPIntegrator(props))
