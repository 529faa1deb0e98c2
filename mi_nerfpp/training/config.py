"""The options of a training run: one dataclass per concern, gathered in :class:`TrainConfig`.

:class:`TrainConfig` holds seven groups - :class:`DataOptions` (how the images are read),
:class:`ModelOptions` (the volumes, their fields and what else is learned),
:class:`SamplingOptions` (samples per ray, empty-space skipping), :class:`OptimizerOptions`
(Adam and its learning rates), :class:`LossOptions` (colour loss and priors),
:class:`ScheduleOptions` (budget, batches, seed) and :class:`OutputOptions` (checkpoints,
previews, evaluations) - and each group is the one home of its options' defaults and help
texts: the ``optimize`` command line is generated from them (:mod:`.options`), one section
of ``--help`` per group. On the command line (and in :meth:`TrainConfig.from_options`) the
options stay flat, each under its own name (``--batch-rays``, ``batch_rays=``).

To add an option, add a field ``name: type = option(default, 'help text')`` to its group and
check its value in the group's ``_validate``; give it ``shapes_model=True`` when a checkpoint
trained with another value cannot be resumed.

A checkpoint stores the config as :meth:`TrainConfig.to_dict` (the groups nested);
:meth:`TrainConfig.from_stored` also reads the flat dict of checkpoints written before the
groups, and fills options they do not know with today's defaults.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
from dataclasses import dataclass

from mi_nerfpp.core import appearance as app
from mi_nerfpp.core import budget
from mi_nerfpp.core import occupancy as occ
from mi_nerfpp.core import poses
from mi_nerfpp.core.encodings import sparse_s
from mi_nerfpp.core.fields import (BACKGROUND_COLOR, COLOR_MODES, MAX_APPEARANCE_DIMS,
                                   MAX_COLOR_LAYERS, MAX_DIR_OCTAVES, grid_default)
from mi_nerfpp.core.frame import NERF_CAMERA_RADIUS
from mi_nerfpp.core.model import FIELD_KINDS, default_field_config
from mi_nerfpp.core.render import SKIPPING, Sampling
from mi_nerfpp.data import masks
from mi_nerfpp.files.checkpoint import REMEDY as CHECKPOINT_REMEDY, CheckpointError
from mi_nerfpp.training import optim
from mi_nerfpp.training.options import (check_value, flag, group, groups, option,
                                        option_name, options_of)

MODEL_KINDS = ('nerfpp', 'nerf')
# The embedded default job (``optimize`` without a dataset, :func:`mi_nerfpp.jobs.run.default_job`):
# the default capture trained for these minutes, evaluated after these minutes too.
DEFAULT_JOB_MINUTES = 10.0
DEFAULT_JOB_EVAL_AT = (2.0, 5.0)
# The largest --seed: the background field is seeded with seed + 1, and Dr.Jit's generators
# take 64-bit seeds.
MAX_SEED = 2 ** 64 - 2
# The most --pyramid fractions: n of them start training at 1/2^n of the image size, where the
# step sums each ray's 2^n x 2^n block of stored pixels in its kernel (unrolled: 16 x 16 on a
# 32x24 capture took 97 s for 3 steps against 6 s, and a real capture's coarsest level many
# times more; issue 63). The level is also never coarser than leaves the images a pixel
# (RayBank.max_factor).
MAX_PYRAMID_LEVELS = 3
# Options measured and not kept (docs/experiments.md, each with the figure that decided it),
# removed after RETIRED_AFTER, with the value each took when off (None: any value, it only
# mattered with another option on). A stored config that used one otherwise is not resumed
# (:meth:`TrainConfig.retired_in`); its weights still evaluate and render. ``composite`` is
# read from the weights: sRGB models of before linear compositing ('srgb', the default of
# files that do not say) render as they were trained (:mod:`mi_nerfpp.core.model`).
RETIRED_OPTIONS = {'lazy_adam': False, 'coarse_to_fine': [], 'unseen_fill': False,
                   'far_smoothness': 0.0, 'tv': 0.0, 'tv_cells': None, 'opacity_entropy': 0.0,
                   'entropy_start': None, 'distortion_scope': 'ray', 'composite': 'linear'}
RETIRED_AFTER = 'b4d9de3'
# The budget of a run given neither iterations nor minutes (:func:`default_minutes`): the
# default capture's training pixels (48 views of 128x96) get DEFAULT_JOB_MINUTES, other
# captures minutes in proportion to the square root of their training pixels, within these
# bounds.
BUDGET_REFERENCE_PIXELS = 48 * 128 * 96
DEFAULT_MINUTES_RANGE = (2.0, 60.0)
# The entries of a volume's field config (:attr:`~mi_nerfpp.core.fields.GridField.config`)
# that options set: entry -> (option of the foreground, option of the background; None: that
# volume has no such entry). The one home of the option pairs: a background option left unset
# (None) takes the foreground's value (:meth:`ModelOptions.effective`); a volume's options are
# read through it (:meth:`ModelOptions.value_of`), :meth:`TrainConfig.field_config` writes a
# grid field's entries from them and :func:`weight_options` reads them back from a checkpoint.
GRID_FIELD_OPTIONS = {
    'kind': ('field', 'bg_field'), 'sparse': ('grid_sparse', 'bg_grid_sparse'),
    'channels': ('grid_channels', 'grid_channels'), 'hidden': ('color_width', 'color_width'),
    'dir_octaves': ('dir_octaves', 'dir_octaves'),
    'color_layers': ('color_layers', 'color_layers'), 'color': ('color', 'bg_color'),
    'antialias': ('antialias', 'antialias'), 'planes': ('grid_planes', 'bg_grid_planes'),
    'warp_radius': ('fg_warp', None), 's_ratio': (None, 'bg_s_ratio'),
    'density_bias': ('density_bias', 'density_bias'),
    'appearance_dims': ('appearance_embedding', 'appearance_embedding'),
    'resolutions': ('grid_levels', 'bg_grid_levels'), 'init': ('grid_init', 'grid_init')}
# The entries that hold one or more numbers: lists in a field config (one s ratio as a number,
# as before per-level ratios), tuples as options.
LIST_ENTRIES = ('resolutions', 'planes', 'sparse', 's_ratio')
# What a field config written without an entry had (files from before sparse levels and
# appearance codes have none); other entries it lacks are not read back.
ABSENT_ENTRIES = {'sparse': (), 'appearance_dims': 0}
# The options that, left unset (None), are chosen from the capture when a run is prepared
# (:mod:`mi_nerfpp.training.choices`): a model built before that has none, and the background's
# does not take the foreground's (:meth:`ModelOptions.source`).
CHOSEN_OPTIONS = ('grid_sparse', 'bg_grid_sparse')
# The entries a checkpoint's weights do not fix (:func:`weight_options`): its stored config has
# the resolutions, and the noise the grids started with shapes nothing.
UNFIXED_ENTRIES = ('resolutions', 'init')


def default_minutes(train_pixels: int) -> float:
    """The training minutes of a capture of ``train_pixels`` training pixels when no budget is
    given: ``DEFAULT_JOB_MINUTES * sqrt(train_pixels / BUDGET_REFERENCE_PIXELS)``, rounded to
    whole minutes within :data:`DEFAULT_MINUTES_RANGE`.

    A step takes a fixed batch of rays whatever the capture, so a minute is a fixed number of
    rays. Minutes in proportion to the pixels would give every capture the same number of
    passes over its pixels, hours for a photo set (118 photos of 1200x800 are 190 times the
    default capture); a field's detail grows with the images' side rather than their area,
    hence the square root (4 times the pixels, twice the minutes)."""
    low, high = DEFAULT_MINUTES_RANGE
    minutes = DEFAULT_JOB_MINUTES * math.sqrt(max(train_pixels, 0) / BUDGET_REFERENCE_PIXELS)
    return float(min(max(round(minutes), low), high))


def _grid_default(name):
    """A default of the grid field's config entry ``name``, read from its home
    (:func:`~mi_nerfpp.core.fields.grid_default`)."""
    return grid_default(name)


def _comma_floats(text):
    """``'1,1,1'`` -> ``(1.0, 1.0, 1.0)`` (the ``--background`` option)."""
    try:
        values = tuple(float(v) for v in text.split(','))
    except ValueError:
        values = ()
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expects three numbers like 1,1,1, got '{text}'")
    return values


def _as_tuple(value):
    """An option of one or more numbers as a tuple (from Python, one number may be given
    bare; from JSON, a list); the values are checked where the option is validated."""
    return (value,) if isinstance(value, (int, float)) else tuple(value)


def _finite(v):
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def per_volume(values):
    """An option of one value for both volumes or one per volume, as (foreground, background)."""
    return tuple(values) * (2 // len(values))


class _Options:
    """What every group does: each value is checked against its option's declared type
    (:func:`~.options.check_value`: lists from JSON become tuples), then the group checks
    their ranges."""

    def __post_init__(self):
        for f in dataclasses.fields(self):
            setattr(self, f.name, check_value(f, getattr(self, f.name)))
        self._validate()

    def _validate(self):
        pass

    def _bad(self, name, need):
        """Refuse the value of option ``name``: one message naming the flag and the value."""
        value = getattr(self, name)
        shown = ' '.join(map(str, value)) if isinstance(value, tuple) else value
        raise ValueError(f'{flag(type(self), name)} must be {need}, got {shown}')

    def _check(self, names, ok, need):
        for name in names:
            if not ok(getattr(self, name)):
                self._bad(name, need)


@dataclass
class DataOptions(_Options):
    downscale: int | None = option(
        None, 'integer image downscale factor', type=int,
        default_help="(default: the photos' own resolution, or the smallest factor that "
                     'makes the images and training fit in the available memory; announced)')
    background: tuple = option((1.0, 1.0, 1.0), 'colour that transparent (RGBA) images are '
                               'composited over', type=_comma_floats, metavar='R,G,B',
                               default_help='(default: 1,1,1)')

    def _validate(self):
        if self.downscale is not None and self.downscale < 1:        # None: automatic
            self._bad('downscale', 'at least 1')
        if len(self.background) != 3 or not all(_finite(c) for c in self.background):
            self._bad('background', 'three finite numbers R,G,B')


@dataclass
class ModelOptions(_Options):
    kind: str = option('nerfpp', "'nerfpp': a foreground volume in the unit sphere and an "
                       "inverted-sphere background; 'nerf': the paper's baseline, one bounded "
                       'volume', choices=MODEL_KINDS, flag='--model', shapes_model=True)
    field: str = option('grid', "field kind of both volumes: 'grid' (feature grids and a small "
                        "colour MLP), 'nerf' (NeRF's MLP) or 'vanilla' (an MLP taking position "
                        'and direction at its input)', choices=FIELD_KINDS, shapes_model=True)
    bg_field: str | None = option(None, 'field kind of the background volume', type=str,
                                  choices=FIELD_KINDS, default_help='(default: as --field)',
                                  shapes_model=True)
    grid_levels: tuple = option(tuple(_grid_default('resolutions')),
                                'grid field: resolution of each level (unless --grid-sparse is '
                                "given, the foreground's finest is stored in bricks: see "
                                '--grid-sparse)', metavar='RES', shapes_model=True)
    bg_grid_levels: tuple | None = option(None, 'grid field: resolution of each level of the '
                                          'background grid', type=int, nargs='+', metavar='RES',
                                          default_help='(default: as --grid-levels)',
                                          shapes_model=True)
    grid_planes: tuple = option(tuple(_grid_default('planes')), 'grid field: resolution of each '
                                'plane level of the foreground grid: three planes of RES x RES '
                                'cells over the coordinate pairs, summed (a factorized level: '
                                'fine cells for 3 RES² entries instead of RES³)', type=int,
                                nargs='*', metavar='RES', shapes_model=True)
    bg_grid_planes: tuple | None = option(None, 'grid field: resolution of each plane level of '
                                          'the background grid (longitude x colatitude 2RES x '
                                          'RES, longitude and colatitude x s with RES/2 along s)',
                                          type=int, nargs='*', metavar='RES',
                                          default_help='(default: as --grid-planes)',
                                          shapes_model=True)
    grid_sparse: tuple | None = option(None, 'grid field: resolution of each sparse level of '
                                       'the foreground grid: RES³ texels stored only in the '
                                       'bricks (one per occupancy cell) where the field is '
                                       'denser than the occupancy threshold at each --sparse-at '
                                       '(RES: a multiple of --occupancy-res); none: no sparse '
                                       'level', type=int, nargs='*', metavar='RES',
                                       default_help="(default: chosen from the capture and "
                                       "announced: the finest --grid-levels, taken out of the "
                                       "dense ones (the background's finest with it: see "
                                       "--bg-grid-sparse) where its "
                                       "cells span at least two training pixels at the scene's "
                                       "centre, and twice it where those cells do)",
                                       shapes_model=True)
    bg_grid_sparse: tuple | None = option(None, 'grid field: resolution of each sparse level '
                                          'of the background grid (longitude x colatitude '
                                          '2RES x RES, and along s as many texels as a dense '
                                          'level of RES and --bg-s-ratio has; RES: a multiple '
                                          'of half --occupancy-res), stored only in the bricks '
                                          "where the training rays take their colour from at "
                                          'each --sparse-at; none: no sparse level',
                                          type=int, nargs='*', metavar='RES',
                                          default_help="(default: the finest --bg-grid-levels, "
                                          "taken out of the dense ones, where the foreground's "
                                          'finest goes into bricks; none otherwise)',
                                          shapes_model=True)
    grid_channels: int = option(_grid_default('channels'), 'grid field: channels per level',
                                shapes_model=True)
    fg_warp: float = option(_grid_default('warp_radius'), 'grid field: radius of the inner ball '
                            "that the foreground grid magnifies (it fills half the grid's "
                            'radius; 0: a linear grid)', shapes_model=True)
    bg_s_ratio: tuple = option((_grid_default('s_ratio'),), 'grid field: cells along s (inverse '
                               'radius) per cell of colatitude in the background grid: one '
                               'ratio, or one per background level', type=float, nargs='+',
                               metavar='Q', shapes_model=True)
    color: str = option(_grid_default('color'), "grid field: colour of the foreground volume: "
                        "'deferred' composites the grid features along each ray and runs the "
                        "colour MLP once per ray; 'sample' runs it at every sample",
                        choices=COLOR_MODES, shapes_model=True)
    bg_color: str = option(BACKGROUND_COLOR, "grid field: colour of the background volume, "
                           "'deferred' or 'sample' as --color", choices=COLOR_MODES,
                           shapes_model=True)
    antialias: bool = option(True, "grid field: weigh each grid level by whether its cells "
                             "resolve the pixel's footprint at the sample (levels finer than "
                             'the footprint fade out), so renders at other resolutions than the '
                             "training images' neither alias nor blur", shapes_model=True)
    dir_octaves: int = option(_grid_default('dir_octaves'),
                              'grid field: frequencies of the view-direction encoding',
                              shapes_model=True)
    color_layers: int = option(_grid_default('color_layers'),
                               'grid field: hidden layers of the colour MLP', shapes_model=True)
    color_width: int = option(_grid_default('hidden'), 'grid field: width of the colour MLP',
                              shapes_model=True)
    density_bias: float = option(0.0, 'grid field: initial density logit; 0 gives σ = 1 '
                                 'everywhere, above the occupancy threshold, so that empty '
                                 'space is carved out rather than grown into (the grid '
                                 "field's own default, for random models, is more "
                                 'transparent)', shapes_model=True)
    grid_init: float = option(_grid_default('init'), 'grid field: standard deviation of the '
                              'noise the grid levels start with; 0 starts them neutral, so '
                              'that cells no training ray reaches hold no colour of their own')
    appearance: bool | None = option(
        None, 'learn a colour transform (exposure, white-balance gain and bias) per training '
        'image; training image 0 is the reference; held-out views are then scored NeRF-W style '
        '(transform fitted on the left half, right half scored)', type=bool, shapes_model=True,
        default_help="(default: on for photos, whose exposure and white balance vary; off for "
                     "a capture rendered by synth, of one exposure; announced)")
    appearance_embedding: int = option(0, 'learn a code of this many numbers per training '
                                       "image that both colour networks take (NeRF-W's "
                                       'appearance embedding): a sky or a haze that changes from '
                                       'photo to photo is explained per photo instead of '
                                       'fogging the volumes; renders use the neutral (zero) '
                                       'code; grid fields only (0: none)', metavar='DIMS',
                                       shapes_model=True)
    refine_poses: bool | None = option(
        None, 'learn an SE(3) correction of each training camera (rotation about its centre, '
        'translation) jointly with the fields, coarse to fine (--poses-blur); training image 0 '
        'is the reference; held-out views keep their given poses', type=bool, shapes_model=True,
        default_help="(default: on for photos, whose poses structure from motion estimated; off "
                     "for a capture rendered by synth, whose poses are exact; announced)")

    @property
    def per_photo_appearance(self) -> bool:
        """Whether each training photo has an appearance of its own (a colour transform or an
        embedding): held-out photos are then scored with theirs fitted (NeRF-W)."""
        return bool(self.appearance) or self.appearance_embedding > 0

    def _validate(self):
        self._check(('grid_channels', 'color_layers', 'color_width'),
                    lambda v: v >= 1, 'at least 1')
        self._check(('dir_octaves',), lambda v: 0 <= v <= MAX_DIR_OCTAVES,
                    f'0 or more and at most {MAX_DIR_OCTAVES} (frequencies 2^k beyond '
                    f'float32 precision are noise)')
        self._check(('color_layers',), lambda v: v <= MAX_COLOR_LAYERS,
                    f'at most {MAX_COLOR_LAYERS} (every layer is traced into the training '
                    f'kernels)')
        self._check(('density_bias',), _finite, 'a finite number')
        self._check(('grid_init',), lambda v: _finite(v) and v >= 0, 'a finite number >= 0')
        self._check(('appearance_embedding',), lambda v: isinstance(v, int) and 0 <= v
                    <= MAX_APPEARANCE_DIMS, f'a whole number from 0 to {MAX_APPEARANCE_DIMS}')
        if self.appearance_embedding and 'grid' not in (self.field, self.bg_field or self.field):
            self._bad('appearance_embedding', '0 for MLP fields (the codes condition the grid '
                      "fields' colour networks)")
        if not self.grid_levels or min(self.grid_levels) < 2:
            self._bad('grid_levels', 'one or more resolutions of at least 2')
        if self.bg_grid_levels is not None and (not self.bg_grid_levels
                                                or min(self.bg_grid_levels) < 2):
            self._bad('bg_grid_levels', 'one or more resolutions of at least 2')
        self.grid_planes = _as_tuple(self.grid_planes)
        if self.bg_grid_planes is not None:
            self.bg_grid_planes = _as_tuple(self.bg_grid_planes)
        if self.grid_sparse is not None:
            self.grid_sparse = _as_tuple(self.grid_sparse)
        if self.bg_grid_sparse is not None:
            self.bg_grid_sparse = _as_tuple(self.bg_grid_sparse)
        for name in ('grid_planes', 'bg_grid_planes'):
            if any(r < 2 for r in getattr(self, name) or ()):
                self._bad(name, 'resolutions of at least 2')
        if not (_finite(self.fg_warp) and 0 <= self.fg_warp < 1):
            self._bad('fg_warp', 'a radius in [0, 1)')
        self.bg_s_ratio = _as_tuple(self.bg_s_ratio)
        if (not self.bg_s_ratio or not all(_finite(q) and 0 < q <= 1 for q in self.bg_s_ratio)
                or len(self.bg_s_ratio) not in (1, len(self.levels('inverted_sphere')))):
            self._bad('bg_s_ratio', 'one number in (0, 1], or one per background grid level')
        if self.bg_field is None:
            self.bg_field = self.field

    def source(self, name):
        """The option whose value option ``name`` takes effect with: ``name``, or for a
        background option left unset (None) the foreground's of its pair
        (:data:`GRID_FIELD_OPTIONS`)."""
        if getattr(self, name) is None and name not in CHOSEN_OPTIONS:
            return next((fg for fg, bg in GRID_FIELD_OPTIONS.values() if bg == name and fg),
                        name)
        return name

    def effective(self, name):
        """The value option ``name`` takes effect with (:meth:`source`; the sparse levels
        unset: none, a model built now has none - jobs.run.prepare chooses them,
        :data:`CHOSEN_OPTIONS`), sequences as tuples."""
        value = getattr(self, self.source(name))
        if value is None and name in CHOSEN_OPTIONS:
            value = ()
        if value is None and name in ('appearance', 'refine_poses'):
            value = False       # unset: a model built now has none
        return tuple(value) if isinstance(value, (list, tuple)) else value

    def option_of(self, entry, domain):
        """The option that sets field-config ``entry`` in the volume over ``domain`` as it
        takes effect (:meth:`source`); None where that volume has no such entry."""
        name = GRID_FIELD_OPTIONS[entry][domain == 'inverted_sphere']
        return name and self.source(name)

    def value_of(self, entry, domain):
        """The value of field-config ``entry`` (:data:`GRID_FIELD_OPTIONS`) in the volume over
        ``domain``, as its option takes effect; None where that volume has no such entry."""
        name = GRID_FIELD_OPTIONS[entry][domain == 'inverted_sphere']
        return name and self.effective(name)

    def s_ratio_of_sparse(self) -> float:
        """The ``s`` ratio the background's sparse levels take: the finest dense level's
        (``--bg-s-ratio``)."""
        return (self.value_of('s_ratio', 'inverted_sphere') or (grid_default('s_ratio'),))[-1]

    def levels(self, domain):
        """The grid resolutions of one volume's grid field."""
        return self.value_of('resolutions', domain)

    def planes(self, domain):
        """The plane levels' resolutions of one volume's grid field."""
        return self.value_of('planes', domain)

    def field_of(self, domain):
        """The field kind of one volume."""
        return self.value_of('kind', domain)

    def sparse(self, domain):
        """The sparse levels' resolutions of one volume's grid field."""
        return self.value_of('sparse', domain)


@dataclass
class SamplingOptions(_Options):
    fg_samples: int = option(SKIPPING.fg_samples, 'coarse foreground samples per ray',
                             joint='--samples', metavar='FG')
    bg_samples: int = option(SKIPPING.bg_samples, 'coarse background samples per ray',
                             joint='--samples', metavar='BG')
    fine_samples: int = option(SKIPPING.fine_samples, 'fine samples per ray and volume',
                               joint='--samples', metavar='FINE')
    occupancy: bool = option(True, 'skip empty space: an occupancy grid per volume places the '
                             'samples', shapes_model=True)
    occupancy_res: int = option(occ.DEFAULT_RESOLUTION, 'resolution of the occupancy grids',
                                shapes_model=True)
    occupancy_threshold: float = option(
        occ.DEFAULT_THRESHOLD, 'density below which an occupancy cell is empty (per unit '
        'length in the foreground, per unit of s in the background)')
    occupancy_every: int = option(occ.DEFAULT_EVERY,
                                  'steps between refreshes of the occupancy grids')

    def _validate(self):
        self._check(('fg_samples', 'bg_samples', 'occupancy_res', 'occupancy_every'),
                    lambda v: v >= 1, 'at least 1')
        self._check(('fine_samples',), lambda v: v >= 0, '0 or more')
        self._check(('occupancy_threshold',), lambda v: _finite(v) and v >= 0,
                    'a finite number >= 0')


@dataclass
class OptimizerOptions(_Options):
    lr_grid: float = option(optim.LR_GRID, 'learning rate of the feature grids')
    lr_mlp: float = option(optim.LR_MLP, 'learning rate of the MLPs')
    lr_final: float = option(optim.LR_FINAL, 'learning rates decay exponentially to this '
                             'fraction of their start over the run')
    adam_beta2: float = option(optim.ADAM_BETA2, "decay of Adam's second-moment estimate")
    lr_appearance: float = option(app.LR_APPEARANCE, 'learning rate of the appearance transforms')
    lr_poses: float = option(poses.LR_POSES, 'learning rate of the pose corrections (radians and '
                             'model-frame units: the cameras lie in the unit sphere)')
    poses_start: float = option(poses.START, 'fraction of the run after which the pose '
                                'corrections are learned (before it the fields are too rough '
                                'to steer them)')
    poses_blur: float = option(poses.BLUR, 'with --refine-poses, coarse to fine: the training '
                               'rays see the scene blurred to this many degrees at the start '
                               '(the size of the pose errors it recovers), sharpening to their '
                               f'pixels by {poses.SHARP:g} of the run (0: off)')

    def _validate(self):
        self._check(('lr_grid', 'lr_mlp', 'lr_final', 'lr_appearance', 'lr_poses'),
                    lambda v: _finite(v) and v > 0, 'a positive finite number')
        if not (_finite(self.adam_beta2) and 0 < self.adam_beta2 < 1):
            self._bad('adam_beta2', 'a number in (0, 1)')
        self._check(('poses_start',), lambda v: _finite(v) and v >= 0, 'a finite number >= 0')
        self._check(('poses_blur',), lambda v: _finite(v) and 0 <= v <= 90,
                    'degrees from 0 (off) to 90')
        self._check(('lr_poses',), lambda v: v <= poses.MAX_LR_POSES,
                    f'at most {poses.MAX_LR_POSES:g} (an Adam step moves each camera correction '
                    f'by about the learning rate: radians, and the unit sphere\'s radius)')


@dataclass
class LossOptions(_Options):
    color_loss: str = option('charbonnier', "colour loss of the rendered pixels: "
                             "'charbonnier' (mip-NeRF 360's robust loss) or 'mse' (the "
                             "paper's squared error)", choices=tuple(optim.COLOR_LOSSES))
    distortion: float = option(0.01, 'weight of the mip-NeRF 360 distortion loss, which '
                               'gathers the weights along a ray against floaters and haze '
                               '(0: off)')
    sparsity: tuple = option((0.01,), 'weight of the sparsity prior: Cauchy loss log(1 + 2σ²) '
                             'of the density at random points of each volume (Plenoxels), which '
                             'removes haze and floaters: one for both volumes, or one for the '
                             'foreground and one for the background',
                             type=float, nargs='+', metavar='W', default_help='(default: 0.01)')
    sparsity_start: tuple = option((0.15, 0.5), 'fraction of the run after which the sparsity '
                                   'prior applies: one for both volumes, or one for the '
                                   'foreground and one for the background. Starting late lets '
                                   'the young, dense foreground keep the ground inside its '
                                   'sphere (cleaner mattes) and the background form its '
                                   'geometry before its prior starts',
                                   type=float, nargs='+', metavar='F',
                                   default_help='(default: 0.15 0.5)')
    near_gradient: float = option(0.5, 'scale the gradients of samples within this distance of '
                                  'their camera (in the units of the unit sphere of NeRF++) by '
                                  '(distance / this)² (Floaters No More: fewer '
                                  'floaters near the cameras; 0: off)')
    appearance_prior: float = option(app.PRIOR, 'weight of the L2 prior that keeps the '
                                     'appearance transforms near the identity')
    masks: str | None = option(None, "what the photos' masks mean (docs/data.md, \"Masks\"): "
                               "'ignore' leaves their black pixels out of the colour loss "
                               "(people, cars); 'object' takes their white pixels as the "
                               "object's silhouette and fits the foreground's opacity to it "
                               "(a clean matte); 'none' leaves them unused",
                               type=str, choices=masks.MEANINGS,
                               default_help=f"(default: '{masks.DEFAULT_MEANING}' when the "
                                            f"dataset has masks; announced)")
    transients: float = option(0.0, 'transients without masks (docs/training.md, "Transients"): '
                               'a pixel whose tile errs more than this many times as much as '
                               'the same point in the other photos that see it weighs less in '
                               'the colour loss, and nothing from twice that (a passer-by, a '
                               'car in one photo). 0: off')
    mask_weight: float = option(optim.SILHOUETTE_WEIGHT, 'weight of the silhouette loss of '
                                '--masks object (the foreground opacity against the mask)')

    def _validate(self):
        self._check(('distortion', 'appearance_prior', 'mask_weight', 'near_gradient'),
                    lambda v: _finite(v) and v >= 0, 'a finite number >= 0')
        self._check(('transients',), lambda v: _finite(v) and (v == 0 or v > 1),
                    '0 (off) or a ratio above 1')
        for name, ok, one in (('sparsity', lambda w: w >= 0, 'one finite number >= 0'),
                              ('sparsity_start', lambda f: 0 <= f <= 1, 'one fraction in [0, 1]')):
            v = _as_tuple(getattr(self, name))          # per volume: see per_volume()
            setattr(self, name, v)
            if len(v) not in (1, 2) or not all(_finite(x) and ok(x) for x in v):
                self._bad(name, f'{one}, or two (foreground, background)')


@dataclass
class ScheduleOptions(_Options):
    iterations: int | None = option(
        None, 'training steps', type=int, exclusive='budget',
        default_help=f'(default: a time budget chosen from the training pixels, '
                     f'{DEFAULT_MINUTES_RANGE[0]:g} to {DEFAULT_MINUTES_RANGE[1]:g} minutes, '
                     f'announced; the embedded default run: --minutes '
                     f'{DEFAULT_JOB_MINUTES:g})')
    minutes: float | None = option(
        None, 'wall-time budget in minutes of training steps', type=float, exclusive='budget')
    batch_rays: int = option(1024, 'rays per step')
    error_rays: float | None = option(
        None, "share of each step's rays drawn where the training error is high (an error map "
        "over tiles of the training images, as instant-ngp's); the rest uniform over the "
        'pixels. 0: all uniform', type=float,
        default_help='(default: 0, uniform: on photos the error is largely what no consistent '
                     'scene explains; 0.8 suits clean synthetic captures of photo size; a '
                     'resumed run draws as it did)')
    error_tile: int = option(16, "side in pixels of the error map's tiles (of the full-size "
                             'training images)')
    seed: int = option(0, 'seed of the initialization, the ray batches and the samples')
    freeze: bool = option(True, 'record the kernels of a training step once and replay them '
                          '(drjit.freeze) instead of tracing every step in Python; re-recorded '
                          'when a prior starts or the grids change resolution')
    sparse_at: tuple = option((0, 0.1, 0.2, 0.3, 0.5, 0.7),
                              'grid field: fractions of the run at which sparse '
                              "levels allocate their bricks: the foreground's where the field's "
                              "density is above the occupancy threshold, the background's where "
                              'the training rays take their colour from '
                              '(again at each: bricks kept keep their texels and Adam '
                              'moments; 0: at the first step, every brick of each level that '
                              '--sparse-entries holds whole, since the occupancy knows nothing '
                              'yet; a larger level waits for the next fraction)', type=float,
                              nargs='+', metavar='F')
    sparse_entries: int = option(9_000_000, 'grid field: most entries of one sparse level (the '
                                 'densest bricks are kept, behind those that take most of a '
                                 "ray's colour)")
    pyramid: tuple = option((0.1, 0.3), 'image pyramid: fractions of the run at which training '
                            'moves to the next finer level of box-filtered images (it starts at '
                            '1/2^n of their size, the last fraction reaches full size; none: '
                            'full size throughout)', type=float, nargs='*', metavar='F')

    def _validate(self):        # neither iterations nor minutes: chosen from the capture
        if self.minutes is not None and not (_finite(self.minutes) and self.minutes > 0):
            self._bad('minutes', 'a positive number of minutes')
        if self.iterations is not None and self.iterations < 1:
            self._bad('iterations', 'at least 1')
        self._check(('batch_rays', 'error_tile'), lambda v: v >= 1, 'at least 1')
        self._check(('error_rays',), lambda v: v is None or (_finite(v) and 0 <= v <= 1),
                    'a fraction in [0, 1]')
        self._check(('seed',), lambda v: 0 <= v <= MAX_SEED,
                    f'a whole number from 0 to {MAX_SEED} (2^64 - 2)')
        self._check(('sparse_entries',), lambda v: v >= 1, 'at least 1')
        if not all(_finite(f) and 0 < f < 1 for f in self.pyramid):
            self._bad('pyramid', 'fractions between 0 and 1')
        if not all(_finite(f) and 0 <= f < 1 for f in self.sparse_at):
            self._bad('sparse_at', 'fractions from 0 (the first step) to below 1')
        if len(self.pyramid) > MAX_PYRAMID_LEVELS:
            self._bad('pyramid', f'at most {MAX_PYRAMID_LEVELS} fractions (the first level '
                                 f'averages 2^n x 2^n stored pixels per ray inside the training '
                                 f'step, whose compilation takes minutes beyond '
                                 f'{1 << MAX_PYRAMID_LEVELS} x {1 << MAX_PYRAMID_LEVELS})')


@dataclass
class OutputOptions(_Options):
    checkpoint_every: int = option(500, 'iterations between checkpoints (0: only at the end)')
    preview_every: int = option(500, 'iterations between held-out previews (0: never)')
    eval_at: tuple | None = option(None, 'also evaluate the held-out views after these minutes '
                                   'of training; recorded in metrics.json as "progress"',
                                   type=float, nargs='*', metavar='MIN',
                                   default_help='(default: none; the embedded default run: '
                                                + ' '.join(f'{m:g}' for m in DEFAULT_JOB_EVAL_AT)
                                                + ')')

    def _validate(self):
        self._check(('checkpoint_every', 'preview_every'), lambda v: v >= 0, '0 or more')
        self.eval_at = tuple(sorted(self.eval_at or ()))
        if not all(_finite(m) and m > 0 for m in self.eval_at):
            self._bad('eval_at', 'positive numbers of minutes')


@dataclass
class TrainConfig:
    """Everything a training run is told; the ``optimize`` command line is generated from it."""
    data: DataOptions = group(DataOptions, 'data', 'how the images are read')
    model: ModelOptions = group(ModelOptions, 'model',
                                'the volumes, their fields and what else is learned (fixed '
                                'for a run: --resume refuses other values)')
    sampling: SamplingOptions = group(SamplingOptions, 'sampling',
                                      'samples per ray and empty-space skipping; the sample '
                                      'counts are stored with the model and renders use them')
    optimizer: OptimizerOptions = group(OptimizerOptions, 'optimizer',
                                        'Adam and its learning rates')
    losses: LossOptions = group(LossOptions, 'losses and priors')
    schedule: ScheduleOptions = group(ScheduleOptions, 'schedule',
                                      'how long, in what batches, from which seed')
    output: OutputOptions = group(OutputOptions, 'output',
                                  'what the run writes along the way')

    def __post_init__(self):
        """Checks across groups: a sparse level's bricks are the occupancy grid's cells."""
        m, s = self.model, self.sampling
        for domain, name in (('ball', 'grid_sparse'), ('inverted_sphere', 'bg_grid_sparse')):
            levels = m.sparse(domain)
            if not levels or m.field_of(domain) != 'grid':
                continue
            option = name
            shown = ' '.join(map(str, levels))
            if not s.occupancy:
                raise ValueError(f'{self.flag(option)} {shown} needs empty-space skipping (its '
                                 f'bricks are the occupancy cells): drop --no-occupancy')
            _, cells_y, cells_x = occ.grid_shape(domain, s.occupancy_res)
            if any(r % cells_y or (r if domain == 'ball' else 2 * r) % cells_x
                   for r in levels):
                raise ValueError(f'{self.flag(option)} must be multiples of {cells_y} (the '
                                 f'occupancy cells, --occupancy-res {s.occupancy_res}), got '
                                 f'{shown}')
        if not any(self.schedule.sparse_at):
            self._check_first_allocation()

    def _check_first_allocation(self):
        """``--sparse-at 0`` alone allocates only at the first step, where the occupancy knows
        nothing yet: a level larger than ``--sparse-entries`` waits for a later fraction there,
        so with none it would never be allocated, and is refused by name."""
        sizing = self.sizing()
        at, entries = self.flag('sparse_at'), self.flag('sparse_entries')
        for v in sizing.volumes:
            for r, full in zip(v.sparse, budget.sparse_level_sizes(sizing, v.domain)):
                if full > sizing.sparse_entries:
                    raise ValueError(
                        f'{at} 0 allocates every brick of {self.flag(v.sparse_by)} {r} at the '
                        f'first step, {full:,} entries, but {entries} is '
                        f'{sizing.sparse_entries:,}, so the level would never be allocated: '
                        f'give {entries} {full} or more, or a later fraction too ({at} 0 0.1 '
                        f'...), where the occupancy grid chooses its densest bricks')

    # ------------------------------------------------------------------ flat options
    @classmethod
    def from_options(cls, **options):
        """A config from options by their command-line names (``batch_rays=512``,
        ``model='nerf'``); options not given take their defaults. Raises ValueError naming the
        flag of a bad value, TypeError for an unknown name."""
        kwargs = {}
        for name, sub, _ in groups(cls):
            own = {f.name: options.pop(option_name(f)) for _, f in options_of(sub)
                   if option_name(f) in options}
            kwargs[name] = sub(**own)
        if options:
            raise TypeError(f'unknown training options: {", ".join(sorted(options))}')
        return cls(**kwargs)

    def options(self) -> dict:
        """Every option by its command-line name (what :meth:`from_options` takes)."""
        return {option_name(f): getattr(getattr(self, name), f.name)
                for name, f in options_of(type(self))}

    def replace(self, **options):
        """A copy with some options (by their command-line names) changed, checked anew."""
        return type(self).from_options(**dict(self.options(), **options))

    def to_dict(self) -> dict:
        """The config as JSON-ready nested dicts (as checkpoints and metrics.json store it)."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def _stored_names(cls, stored: dict):
        """``(options, unknown)`` of a stored config: its values by option name, and the
        ``group.key`` (or ``key``) of the entries this version does not know. A grouped entry
        is found by its key whatever group it is stored in (options that moved between groups
        keep their values); a flat dict is read by option name."""
        known = {option_name(f): (name, f.name) for name, f in options_of(cls)}
        by_key = {key: name for name, (_, key) in known.items()}
        by_key.update({name: name for name in known})
        if any(isinstance(stored.get(name), dict) for name, _, _ in groups(cls)):
            options, unknown = {}, []
            for part, values in stored.items():
                if not isinstance(values, dict):
                    unknown.append(part)
                    continue
                for key, value in values.items():
                    if key in by_key:
                        options[by_key[key]] = value
                    else:
                        unknown.append(f'{part}.{key}')
            return options, unknown
        return ({k: v for k, v in stored.items() if k in known},
                [k for k in stored if k not in known])

    @classmethod
    def stored_options(cls, stored: dict) -> dict:
        """The options (by command-line name) of a stored config: :meth:`to_dict`'s nested
        groups, or the flat dict of checkpoints written before the groups; names this version
        does not know are left out (:meth:`unknown_stored` lists them). A value that is not of
        its option's type is a ValueError naming the option (:func:`~.options.check_value`)."""
        options = cls._stored_names(stored)[0]
        if 'bg_s_ratio' in options and isinstance(options['bg_s_ratio'], (int, float)):
            options['bg_s_ratio'] = [options['bg_s_ratio']]     # before per-level ratios
        if (options.get('bg_grid_sparse', ()) is None
                and options.get('grid_sparse') is not None):
            # Runs of 15f237e stored None for "as --grid-sparse", which they always gave
            # (today None is chosen from the capture, CHOSEN_OPTIONS, and a run stores the
            # choice).
            options['bg_grid_sparse'] = options.get('grid_sparse') or ()
        if stored and 'error_rays' not in options:
            options['error_rays'] = 0.0     # runs from before the error map drew uniformly
        if stored and options.get('refine_poses') and 'poses_blur' not in options:
            options['poses_blur'] = 0.0     # refined before coarse to fine: without it
        fields = {option_name(f): f for _, f in options_of(cls)}
        return {name: check_value(fields[name], value) for name, value in options.items()}

    @classmethod
    def unknown_stored(cls, stored: dict) -> list[str]:
        """The entries of a stored config that name no option of this version (written by
        another version), as ``group.key``; retired options (:data:`RETIRED_OPTIONS`) are
        not among them."""
        return [k for k in cls._stored_names(stored)[1]
                if k.rsplit('.', 1)[-1] not in RETIRED_OPTIONS]

    @classmethod
    def retired_in(cls, stored: dict, weights: dict | None = None) -> list[str]:
        """The retired options (:data:`RETIRED_OPTIONS`) that a stored config, or the
        checkpoint's model config ``weights``, used with a value other than off, as command-line
        words (``--tv 0.01``): a run that used one cannot go on with this version."""
        values = {}
        for part, entry in stored.items():
            for key, value in (entry.items() if isinstance(entry, dict) else [(part, entry)]):
                if key in RETIRED_OPTIONS:
                    values[key] = value
        if weights is not None and weights.get('color_space', 'srgb') == 'srgb':
            values['composite'] = weights.get('composite', 'srgb')
        out = []
        for key, value in values.items():
            off = RETIRED_OPTIONS[key]
            if off is None or value == off or (isinstance(off, list) and not value):
                continue
            shown = ' '.join(map(str, value)) if isinstance(value, (list, tuple)) else value
            spelled = '--' + key.replace('_', '-')
            out.append(spelled if value is True else f'{spelled} {shown}')
        return out

    @classmethod
    def from_stored(cls, stored: dict, weights: dict | None = None):
        """The config a checkpoint's ``meta['config']`` stores (see :meth:`stored_options`);
        options it does not store take today's defaults. With ``weights`` (the checkpoint's
        model config, :attr:`~mi_nerfpp.core.model.NeRFPPModel.config`), the options that
        shape the model take the values of the weights wherever the stored config says
        otherwise or nothing, so that the config describes the model."""
        options = cls.stored_options(stored)
        config = cls.from_options(**options)
        if weights is None:
            return config
        fixed = weight_options(weights)
        wrong = {name: value for name, value in fixed.items()
                 if config.effective(name) != value}
        for name in CHOSEN_OPTIONS:         # chosen: the weights'
            if getattr(config.model, name) is None and name in fixed:
                wrong[name] = fixed[name]
        return config.replace(**wrong) if wrong else config

    def effective(self, name: str):
        """The value option ``name`` takes effect with (a model option:
        :meth:`ModelOptions.effective`), sequences as tuples."""
        part, key = {option_name(f): (part, f.name)
                     for part, f in options_of(type(self))}[name]
        if part == 'model':
            return self.model.effective(key)
        value = getattr(getattr(self, part), key)
        return tuple(value) if isinstance(value, (list, tuple)) else value

    # ------------------------------------------------------------------ derived
    def field_config(self, kind, domain):
        """The field config of one volume whose field is of ``kind``: a grid field's entries
        from their options (:data:`GRID_FIELD_OPTIONS`), the other kinds' their defaults."""
        if kind != 'grid':
            return default_field_config(kind, domain)
        config = {'kind': 'grid', 'domain': domain}
        for entry in GRID_FIELD_OPTIONS:
            value = self.model.value_of(entry, domain)
            if entry == 'kind' or value is None:
                continue
            if entry in LIST_ENTRIES:
                value = value[0] if entry == 's_ratio' and len(value) == 1 else list(value)
            config[entry] = value
        if config['sparse']:        # (files without sparse levels stay as they were)
            blocks = occ.grid_shape(domain, self.sampling.occupancy_res)
            config['sparse_blocks'] = list(blocks)
            if domain == 'inverted_sphere':
                config['sparse_s'] = sparse_s(config['sparse'], self.model.s_ratio_of_sparse(),
                                              blocks)
        else:
            del config['sparse']
        return config

    def sizing(self) -> budget.Sizing:
        """What sizes this run's arrays (:class:`~mi_nerfpp.core.budget.Sizing`, what
        :func:`~mi_nerfpp.core.budget.plan` takes): each volume's grid as
        :meth:`field_config` builds it, the other sizes as the options give them, and the
        command-line words that set each size, which the budget's refusals name."""
        m, s, schedule = self.model, self.sampling, self.schedule
        volumes = []
        for domain in ('ball', 'inverted_sphere')[:2 if m.kind == 'nerfpp' else 1]:
            grid = m.field_of(domain) == 'grid'
            volumes.append(budget.VolumeSizes(
                domain, m.field_of(domain),
                levels=m.levels(domain) if grid else (), planes=m.planes(domain) if grid else (),
                sparse=m.sparse(domain) if grid else (),
                s_ratios=(m.value_of('s_ratio', domain) or ()) if grid else (),
                levels_by=m.option_of('resolutions', domain),
                planes_by=m.option_of('planes', domain),
                sparse_by=m.option_of('sparse', domain) if grid else ''))
        sizes = dict(grid_channels=m.grid_channels, color_width=m.color_width,
                     batch_rays=schedule.batch_rays, occupancy_res=s.occupancy_res,
                     sparse_entries=schedule.sparse_entries)
        flags = {name: _as_flag(name, self.effective(name))
                 for name in [*sizes] + [v.levels_by for v in volumes]
                 + [v.planes_by for v in volumes]
                 + [v.sparse_by for v in volumes if v.sparse_by]}
        flags['samples_per_ray'] = (f'{self.flag("fg_samples")} {s.fg_samples} {s.bg_samples} '
                                    f'{s.fine_samples}')
        default = type(self)()
        return budget.Sizing(
            tuple(volumes), color_layers=m.color_layers, dir_octaves=m.dir_octaves,
            appearance_dims=m.appearance_embedding, samples_per_ray=self.samples_per_ray,
            render_sampling=self.render_sampling, occupancy=s.occupancy, **sizes, flags=flags,
            defaults={'grid_channels': default.model.grid_channels,
                      'batch_rays': default.schedule.batch_rays})

    @property
    def render_sampling(self) -> Sampling:
        """Samples per ray of the model (it stores them and renders with them,
        :meth:`~mi_nerfpp.core.render.Sampling.of_model`)."""
        s = self.sampling
        return Sampling.of_model(self.model.kind, s.fg_samples, s.bg_samples, s.fine_samples)

    @property
    def samples_per_ray(self):
        """Field evaluations per training ray (coarse + fine, every volume)."""
        s = self.render_sampling
        n = s.fg_samples + s.fine_samples
        return n if self.model.kind == 'nerf' else n + s.bg_samples + s.fine_samples

    def flag(self, option: str) -> str:
        """The command-line spelling of ``option`` (for messages)."""
        return flag(type(self), option)

    @classmethod
    def step_sizes(cls) -> list[str]:
        """The options whose values, raised far enough, blow the parameters up - every learning
        rate (``lr_*``, the final decay included) and every loss weight (help text "weight of
        ..."): the suspects named when a run diverges."""
        return [option_name(f) for _, f in options_of(cls)
                if f.name.startswith('lr_') or f.metadata['help'].startswith('weight of')]

    def divergence_hint(self) -> str:
        """What to change when the run's state stops being finite: the prior weights and
        learning rates raised furthest above their defaults (the likely cause), else the
        learning rates."""
        defaults, now = type(self)().options(), self.options()
        raised = []
        for name in self.step_sizes():
            value, default = max(_as_tuple(now[name])), max(_as_tuple(defaults[name]))
            if value > default:
                raised.append((value / default if default > 0 else math.inf, name, now[name]))
        if not raised:
            return 'Lower the learning rates (--lr-grid, --lr-mlp)'
        shown = [f'{flag(TrainConfig, name)} '
                 f'{" ".join(f"{v:g}" for v in _as_tuple(value))}'
                 for _, name, value in sorted(raised, key=lambda r: -r[0])[:3]]
        return (f'Most likely {" or ".join(shown)} (above the default'
                f'{"s" if len(shown) > 1 else ""}): lower {"them" if len(shown) > 1 else "it"}')

    def model_normalization(self, dataset_normalization):
        """The model frame: the dataset's, or for the NeRF baseline one shrunk into
        :data:`~mi_nerfpp.core.frame.NERF_CAMERA_RADIUS`."""
        if self.model.kind == 'nerf':
            return dataset_normalization.with_camera_radius(NERF_CAMERA_RADIUS)
        return dataset_normalization

    def resume_conflicts(self, stored: dict, weights: dict | None = None) -> list[str]:
        """The model-shaping options in which a checkpoint differs from this config, as
        readable lines: those the ``weights`` fix (the checkpoint's model config, see
        :func:`weight_options`) and the others of the stored config (:meth:`to_dict`, or a
        flat one of an older checkpoint)."""
        out = []
        fixed = weight_options(weights) if weights is not None else {}
        for name, value in fixed.items():
            if self.effective(name) != value:
                out.append(f"{flag(TrainConfig, name)}: the checkpoint's weights have "
                           f'{_shown(value)}, this run asks for '
                           f'{_shown(self.effective(name))} (resume with '
                           f'{_as_flag(name, value)})')
        now = json.loads(json.dumps(self.options()))
        stored = json.loads(json.dumps(self.stored_options(stored)))    # as ``now``: lists
        if 'field' in stored:
            stored.setdefault('bg_field', stored['field'])
        if 'color' in stored:
            stored.setdefault('bg_color', stored['color'])
        for _, f in options_of(type(self)):
            name = option_name(f)
            if name in CHOSEN_OPTIONS and now[name] is None:
                continue        # chosen on resume: the checkpoint's own (training.choices)
            if (f.metadata.get('shapes_model') and name not in fixed and name in stored
                    and stored[name] != now[name]):
                out.append(f'{flag(TrainConfig, name)}: the checkpoint has {stored[name]!r}, '
                           f'this run asks for {now[name]!r}')
        return out


def stored_config(meta: dict, path, weights: dict | None = None) -> dict:
    """The training config that the (checked, :func:`~mi_nerfpp.files.checkpoint.check_meta`)
    ``meta`` of checkpoint ``path`` stores, as stored, when it describes a valid config
    (:meth:`TrainConfig.from_stored`, with the checkpoint's model config ``weights`` when
    given); else :class:`~mi_nerfpp.files.checkpoint.CheckpointError` naming the file and the
    option. Every reader of a run folder's training config takes it from here (issue 63: a
    retyped entry ended in TypeError deep inside)."""
    stored = meta.get('config') or {}
    try:
        TrainConfig.from_stored(stored, weights)
    except (ValueError, TypeError) as e:
        raise CheckpointError(f'{path}: its stored training config is damaged: {e}: '
                              f'{CHECKPOINT_REMEDY}') from None
    return stored


def weight_options(weights: dict) -> dict:
    """The model-shaping options that a checkpoint's model config fixes (its weights were
    made with them), by option name, as :meth:`TrainConfig.effective` gives them: the model
    kind, the appearance and pose models, each volume's field kind and its grid options read
    back through :data:`GRID_FIELD_OPTIONS` (not :data:`UNFIXED_ENTRIES`: the stored config has
    the grid resolutions)."""
    out = {'model': 'nerf' if weights.get('bg') is None else 'nerfpp',
           'appearance': int(weights.get('appearance_images', 0)) > 0,
           'refine_poses': int(weights.get('pose_images', 0)) > 0}
    occupancy = weights.get('occupancy') or {}
    if 'fg' in occupancy and 'resolution' in occupancy['fg']:    # the bricks' cells
        out['occupancy_res'] = occupancy['fg']['resolution']
    for side, key in enumerate(('fg', 'bg')):
        field = weights.get(key)
        if not field:
            continue
        for entry, names in GRID_FIELD_OPTIONS.items():
            name = names[side]
            if name is None or (side and name in out):
                continue            # options both volumes share: the first grid field's value
            if entry != 'kind' and (field['kind'] != 'grid' or entry in UNFIXED_ENTRIES):
                continue
            if entry not in field and entry not in ABSENT_ENTRIES:
                continue
            value = field.get(entry, ABSENT_ENTRIES.get(entry))
            out[name] = _as_tuple(value) if entry in LIST_ENTRIES else value
    return out


def _shown(value):
    """An option's value in a message: sequences as the command line takes them."""
    if isinstance(value, tuple):
        return ' '.join(f'{v:g}' if isinstance(v, float) else str(v) for v in value) or 'none'
    return repr(value)


def _as_flag(name, value):
    """The command-line words that give option ``name`` the value ``value``."""
    spelled = flag(TrainConfig, name)
    if isinstance(value, bool):
        return spelled if value else '--no-' + spelled[2:]
    if isinstance(value, tuple):
        return ' '.join([spelled] + [f'{v:g}' if isinstance(v, float) else str(v)
                                     for v in value])
    return f'{spelled} {value:g}' if isinstance(value, float) else f'{spelled} {value}'
