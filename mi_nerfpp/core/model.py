"""A NeRF++ scene representation: foreground and background fields plus the scene normalization.

The model lives in a *normalized* frame where all cameras are inside the unit
sphere; its :class:`~mi_nerfpp.core.frame.Normalization` maps world-space points, cameras and
rays into it and back.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import drjit as dr

from mi_nerfpp.core.appearance import identity, zero_embeddings
from mi_nerfpp.core.fields import make_field
from mi_nerfpp.core.frame import Normalization
from mi_nerfpp.core.occupancy import DEFAULT_DECAY, OccupancyGrid
from mi_nerfpp.core.poses import zeros
from mi_nerfpp.core.render import Sampling

FIELD_KINDS = ('grid', 'nerf', 'vanilla')


def default_field_config(kind, domain):
    if kind not in FIELD_KINDS:
        raise ValueError(f"unknown field kind '{kind}' (expected one of {', '.join(FIELD_KINDS)})")
    return {'kind': kind, 'domain': domain}


@dataclass(frozen=True)
class RenderSettings:
    """How a model is rendered unless a renderer is told otherwise: as it was trained.

    ``sampling``: samples per ray (coarse foreground, coarse background, fine per volume) and
    where camera rays start (``near``), those of training (a checkpoint stores them);
    ``background``: whether the background volume is rendered (the model has one);
    ``composite``: where samples are composited (see :class:`NeRFPPModel`). The ``nerfpp``
    integrator and :class:`~mi_nerfpp.output.views.ViewRenderer` render with these; the
    integrator's XML parameters override them one by one.
    """
    sampling: Sampling
    background: bool
    composite: str


class LinearRadiance:
    """A field whose sRGB-encoded colour output is decoded to linear light: per sample for a
    field with per-sample colour, per ray (after the colour network) for deferred colour."""

    def __init__(self, field):
        self.field = field
        self.deferred = getattr(field, 'deferred', False)
        if hasattr(field, 'sample_color'):     # (a grid field: see render._shade_visible)
            self.sample_color = lambda f, d, ray: dr.srgb_to_linear(field.sample_color(f, d, ray))

    def __call__(self, *args, **kwargs):
        sigma, rgb = self.field(*args, **kwargs)
        return sigma, dr.srgb_to_linear(rgb)

    def density(self, x, **kwargs):
        return self.field.density(x, **kwargs)

    def features(self, x, **kwargs):
        return self.field.features(x, **kwargs)

    def color(self, features, d):
        return dr.srgb_to_linear(self.field.color(features, d))


class NeRFPPModel:
    """Foreground field (unit ball), optional background field (inverted sphere), normalization.

    ``normalization`` (:class:`~mi_nerfpp.core.frame.Normalization`) maps the world to the model frame.

    ``bg=None`` is a bounded NeRF: one volume, nothing behind it.
    ``color_space`` is the encoding of the images the model was fitted to: 'srgb' for photos
    (PNG/JPG), 'linear' for EXR inputs. Rendering is scene-linear either way: the colour a
    field outputs at a sample is in that encoding and is decoded to linear light *per sample*
    (:meth:`radiance_fields`), so compositing - along the ray, between the volumes and by an
    artist merging the layers - happens in linear light and ``beauty = fg + (1 - α)·bg`` holds
    exactly. Training takes the loss on the sRGB-encoded composite of an sRGB model.

    ``composite`` says where the samples were composited when the model was trained:
    ``'linear'`` (every model trained since issue 11) or ``'srgb'`` (older sRGB checkpoints,
    which summed encoded colours). An ``'srgb'`` model keeps rendering as it was trained (its
    fields are not decoded, :meth:`radiance_fields`); the integrator then decodes its layers
    to linear light, where the compositing identity holds only approximately at soft edges.

    ``sampling`` (:class:`~mi_nerfpp.core.render.Sampling`): the samples per ray it is rendered
    with (training sets those it trains with; default: :class:`~mi_nerfpp.core.render.Sampling`'s,
    for models with no training behind them); with the background and the composite it makes
    the model's :attr:`render_settings`.
    """

    def __init__(self, fg, bg=None, normalization=Normalization(), color_space='srgb',
                 occupancy=None, composite='linear', appearance_images=0, pose_images=0,
                 sampling=None, coverage=None, embedding_images=0):
        self.fg, self.bg = fg, bg
        # The colour painted where no training view looked (:mod:`.coverage`); None: none.
        self.coverage = coverage
        self.sampling = Sampling() if sampling is None else sampling
        # Per-training-image colour transforms (:mod:`.appearance`); None: off.
        self.appearance = None
        if appearance_images:
            self.appearance = identity(appearance_images)
        # Per-training-image appearance codes of the colour networks (:mod:`.appearance`,
        # as many numbers each as the fields' ``appearance_dims``); None: off.
        self.embedding = None
        dims = self.appearance_dims
        if embedding_images and not dims:
            raise ValueError('appearance embeddings need fields with appearance_dims > 0')
        if dims and not embedding_images:
            raise ValueError(f'fields with appearance_dims {dims} need appearance embeddings')
        if embedding_images:
            self.embedding = zero_embeddings(embedding_images, dims)
        # The code renders use unless a training image's is asked for (``appearance_dims``
        # Python floats; None: the zero, neutral code): a held-out photo's fitted code
        # (:mod:`mi_nerfpp.training.appearance_fit`) while that photo is scored.
        self.render_code = None
        # Per-training-image camera pose corrections (:mod:`.poses`); None: off.
        self.poses = None
        if pose_images:
            self.poses = zeros(pose_images)
        self.normalization = normalization
        # Volume name ('fg'/'bg') -> OccupancyGrid: empty-space skipping (none: sample everywhere).
        self.occupancy = dict(occupancy or {})
        self.color_space = color_space
        if composite not in ('linear', 'srgb'):
            raise ValueError(f"composite must be 'linear' or 'srgb', not {composite!r}")
        self.composite = 'linear' if color_space == 'linear' else composite

    @classmethod
    def create(cls, field='grid', background=True, seed=0, fg_config=None, bg_config=None, **kwargs):
        """A freshly initialized (seeded random) model."""
        fg = make_field(fg_config or default_field_config(field, 'ball'), seed=seed)
        bg = None
        if background:
            bg = make_field(bg_config or default_field_config(field, 'inverted_sphere'), seed=seed + 1)
        return cls(fg, bg, **kwargs)

    def radiance_fields(self):
        """``(fg, bg)`` as :func:`~mi_nerfpp.core.render.render_rays` takes them: fields whose
        colour is linear radiance (an sRGB model's colour is decoded sample by sample)."""
        if self.color_space == 'linear' or self.composite == 'srgb':
            return self.fg, self.bg
        return LinearRadiance(self.fg), None if self.bg is None else LinearRadiance(self.bg)

    @property
    def antialias(self) -> bool:
        """Whether a field filters its lookups by the pixels' footprints (then renders and
        training pass them)."""
        return any(getattr(f, 'antialias', False) for f in (self.fg, self.bg))

    @property
    def render_settings(self) -> RenderSettings:
        """How this model is rendered unless a renderer is told otherwise."""
        return RenderSettings(self.sampling, background=self.bg is not None,
                              composite=self.composite)

    @property
    def loss_encoding(self):
        """The map from :func:`~mi_nerfpp.core.render.render_rays`' composite of
        :meth:`radiance_fields` to the encoding of the training images."""
        if self.color_space == 'srgb' and self.composite == 'linear':
            return dr.linear_to_srgb
        return lambda c: c

    @property
    def config(self):
        return {'fg': self.fg.config, 'bg': self.bg.config if self.bg else None,
                'normalization': self.normalization.to_config(), 'color_space': self.color_space,
                'composite': self.composite, 'appearance_images': self.appearance_images,
                'pose_images': self.pose_images,
                **({'embedding_images': self.embedding_images} if self.embedding is not None
                   else {}),
                'sampling': dataclasses.asdict(self.sampling),
                'occupancy': {k: g.config for k, g in self.occupancy.items()}}

    @property
    def appearance_images(self):
        """Number of training images with a colour transform (0: no appearance model)."""
        return 0 if self.appearance is None else self.appearance.shape[0]

    @property
    def appearance_dims(self) -> int:
        """Numbers per appearance code the grid fields' colour networks take (0: none)."""
        return max(int(getattr(f, 'appearance_dims', 0)) for f in (self.fg, self.bg)
                   if f is not None)

    @property
    def embedding_images(self):
        """Number of training images with an appearance embedding (0: none)."""
        return 0 if self.embedding is None else self.embedding.shape[0]

    def set_appearance(self, code=None):
        """The appearance code the colour networks render with: ``appearance_dims`` Floats
        (one value per ray, or one for all) or None, the neutral (zero) code."""
        for field in (self.fg, self.bg):
            if field is not None and getattr(field, 'appearance_dims', 0):
                field.appearance_code = None if code is None else list(code)

    @property
    def pose_images(self):
        """Number of training images with a learned pose correction (0: poses not refined)."""
        return 0 if self.poses is None else self.poses.shape[0]

    def enable_occupancy(self, resolution, threshold):
        """Give every volume a fresh (all occupied) occupancy grid."""
        self.occupancy = {'fg': OccupancyGrid('ball', resolution, threshold)}
        if self.bg is not None:
            self.occupancy['bg'] = OccupancyGrid('inverted_sphere', resolution, threshold)

    def update_occupancy(self, seed, decay=None):
        """Refresh the occupancy grids from the current fields."""
        for k, grid in self.occupancy.items():
            grid.update(self.fg if k == 'fg' else self.bg, seed, DEFAULT_DECAY if decay is None else decay)

    def parameters(self):
        """All learnable arrays, named ``fg.<name>`` / ``bg.<name>`` (live references), and
        ``appearance`` (:mod:`.appearance`) when the model has per-image transforms and
        ``poses`` (:mod:`.poses`) when it refines the training cameras."""
        out = {f'fg.{k}': v for k, v in self.fg.params.items()}
        if self.bg is not None:
            out.update({f'bg.{k}': v for k, v in self.bg.params.items()})
        if self.appearance is not None:
            out['appearance'] = self.appearance
        if self.embedding is not None:
            out['embedding'] = self.embedding
        if self.poses is not None:
            out['poses'] = self.poses
        return out

    def allocated_bricks(self):
        """The allocated bricks of the grid fields' sparse levels, named ``fg.sparse0``, ...
        (:meth:`~mi_nerfpp.core.fields.GridField.allocated_bricks`)."""
        out = {}
        for volume, field in (('fg', self.fg), ('bg', self.bg)):
            for k, v in (getattr(field, 'allocated_bricks', dict)()).items():
                out[f'{volume}.{k}'] = v
        return out

    def set_bricks(self, values):
        """Allocate sparse levels' bricks by their ``fg.``/``bg.`` names
        (:meth:`~mi_nerfpp.core.fields.GridField.set_bricks`)."""
        for volume, field in (('fg', self.fg), ('bg', self.bg)):
            sub = {k[len(volume) + 1:]: v for k, v in values.items() if k.startswith(volume + '.')}
            if sub:
                if field is None or not hasattr(field, 'set_bricks'):
                    raise KeyError(f'model has no sparse {volume} levels for {sorted(sub)}')
                field.set_bricks(sub)

    def n_parameters(self):
        """Number of learnable scalars."""
        return sum(dr.width(v.array) for v in self.parameters().values())

    def set_parameters(self, values):
        """Replace parameters by their ``fg.``/``bg.`` names."""
        for volume, field in (('fg', self.fg), ('bg', self.bg)):
            sub = {k[len(volume) + 1:]: v for k, v in values.items() if k.startswith(volume + '.')}
            if sub and field is None:
                raise KeyError(f'model has no {volume} field for parameters {sorted(sub)}')
            if sub:
                field.set_parameters(sub)
        for name, what in (('appearance', 'appearance transforms'), ('poses', 'pose corrections'),
                           ('embedding', 'appearance embeddings')):
            if name in values:
                if getattr(self, name) is None:
                    raise KeyError(f'model has no {what}')
                setattr(self, name, values[name])
        unknown = [k for k in values if not k.startswith(('fg.', 'bg.'))
                   and k not in ('appearance', 'poses', 'embedding')]
        if unknown:
            raise KeyError(f'unknown parameter names {unknown}')
