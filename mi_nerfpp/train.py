"""Fitting the foreground and background volumes to posed images (Dr.Jit AD on the CPU).

One training step: draw a batch of random rays across all training images, render
them with :func:`mi_nerfpp.render.render_rays` (the same code the integrator uses),
take the colour loss (Charbonnier by default, or the squared error) of the coarse and the
fine composite against the pixels (radiance is
composited in linear light; for sRGB photos the composite is sRGB-encoded before the loss,
see :meth:`~mi_nerfpp.model.NeRFPPModel.radiance_fields`),
back-propagate with Dr.Jit and take an Adam step (``drjit.opt``). Learning rates
decay exponentially to ``lr_final`` times their start over the run (:mod:`.optim`, shared
with :mod:`.ambiguity`). With ``freeze`` (the default) the kernels of a step are recorded once
by :func:`drjit.freeze` and replayed: a step is a function of :meth:`Trainer._step_inputs`
alone (optimizer, occupancy grids, ray bank, random draws as Dr.Jit arrays, and the phase of
the run as Python values, whose change records the step anew).

The run directory holds ``model.npz`` (the latest checkpoint, written atomically with
the optimizer and RNG state and the loss history, so ``resume=True`` continues exactly);
the ``optimize`` command adds ``preview/`` and, at the end, the evaluation outputs.

:class:`TrainConfig` is the one home of the training options and their defaults: the
``optimize`` command line is generated from its fields (:mod:`.options`). To add an option,
add a field ``name: type = option(default, 'help text')``; give it ``shapes_model=True`` when
a checkpoint trained with another value cannot be resumed.
"""
from __future__ import annotations

import contextlib
import copy
import dataclasses
import gc
import inspect
import json
import math
import os
import signal
import time
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from . import appearance as app, occupancy as occ, optim, poses, priors
from .arrays import owned
from .checkpoint import load_checkpoint, save_checkpoint
from .data import pixel_rays
from .fields import GridField
from .files import remove_stale_temporaries
from .frame import NERF_CAMERA_RADIUS, reframe_cameras
from .model import FIELD_KINDS, NeRFPPModel, default_field_config
from .options import flag, option
from .profiling import stage
from .render import Sampling, distortion, ray_distortion, render_rays

MODEL_KINDS = ('nerfpp', 'nerf')
DEFAULT_ITERATIONS = 2000     # the budget when neither iterations nor minutes is given
# The colour loss's weight against the priors, whose weights were tuned when the loss had two
# terms of about equal size (the coarse and the fine composite; the coarse pass now only places
# samples).
PHOTOMETRIC_WEIGHT = float(os.environ.get('MI_NERFPP_PW', 2.0))
# Gradients scattered into arrays of up to this many entries are summed in one copy per thread
# and added up after the kernel (Dr.Jit's "expand" reduction) instead of by atomic adds: the
# 8.4 M-entry grid levels are above Dr.Jit's default threshold (1 M), and their atomics cost
# twice as much per sample at thousands of rays per step.
GRADIENT_EXPAND_THRESHOLD = 1 << 25


class TrainingError(RuntimeError):
    """Training cannot go on (diverged, or a resume that does not match)."""


def _grid_default(name):
    """A default of the grid field, read from :class:`~mi_nerfpp.fields.GridField` (its home)."""
    return inspect.signature(GridField.__init__).parameters[name].default


def _comma_floats(text):
    """``'1,1,1'`` -> ``(1.0, 1.0, 1.0)`` (the ``--background`` option)."""
    import argparse
    try:
        values = tuple(float(v) for v in text.split(','))
    except ValueError:
        values = ()
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expects three numbers like 1,1,1, got '{text}'")
    return values


def _as_tuple(value):
    """An option of one or more numbers as a tuple (from Python, one number may be given
    bare); the values are checked where the option is validated."""
    return (value,) if isinstance(value, (int, float)) else tuple(value)


def per_volume(values):
    """An option of one value for both volumes or one per volume, as (foreground, background)."""
    return tuple(values) * (2 // len(values))


@dataclass
class TrainConfig:
    """Options of a training run; the ``optimize`` command line is generated from these fields."""
    iterations: int | None = option(
        None, 'training steps', type=int, exclusive='budget',
        default_help=f'(default without --minutes: {DEFAULT_ITERATIONS}, or the embedded '
                     f"default's time budget)")
    minutes: float | None = option(
        None, 'wall-time budget in minutes of training steps', type=float, exclusive='budget')
    model: str = option('nerfpp', "'nerf': the paper's baseline, one bounded volume",
                        choices=MODEL_KINDS, shapes_model=True)
    field: str = option('grid', 'field kind of both volumes', choices=FIELD_KINDS,
                        shapes_model=True)
    bg_field: str | None = option(None, 'field kind of the background volume', type=str,
                                  choices=FIELD_KINDS, default_help='(default: as --field)',
                                  shapes_model=True)
    batch_rays: int = option(1024, 'rays per step')
    fg_samples: int = option(16, 'coarse foreground samples per ray', joint='--samples',
                             metavar='FG')
    bg_samples: int = option(16, 'coarse background samples per ray', joint='--samples',
                             metavar='BG')
    fine_samples: int = option(8, 'fine samples per ray and volume', joint='--samples',
                               metavar='FINE')
    lr_grid: float = option(optim.LR_GRID, 'learning rate of the feature grids')
    lr_mlp: float = option(optim.LR_MLP, 'learning rate of the MLPs')
    lazy_adam: bool = option(False, 'leave parameters whose gradient is zero untouched in an Adam '
                             'step (moments included)')
    adam_beta2: float = option(optim.ADAM_BETA2, "decay of Adam's second-moment estimate")
    lr_final: float = option(optim.LR_FINAL, 'learning rates decay exponentially to this '
                             'fraction of their start over the run')
    color_loss: str = option('charbonnier', "colour loss of the coarse and fine composites: "
                             "'charbonnier' (mip-NeRF 360's robust loss) or 'mse' (the "
                             "paper's squared error)", choices=tuple(optim.COLOR_LOSSES))
    distortion: float = option(0.01, 'weight of the mip-NeRF 360 distortion loss against '
                               'floaters and haze (0: off; with occupancy sampling it measured '
                               '+0.4 dB after 2 minutes on the default capture)')
    distortion_scope: str = option('ray', "'ray': the distortion loss of whole rays, both "
                                   "volumes on one axis (a surface split between the volumes "
                                   "counts as spread out: crisp foreground mattes, measured soft "
                                   "alpha 49 -> 13 %% at equal PSNR); 'volume': of each volume "
                                   "on its own (before)", choices=('volume', 'ray'))
    opacity_entropy: float = option(0.0, 'weight of the binary-entropy prior on the foreground '
                                    'opacity of each ray (pushes it to 0 or 1)')
    entropy_start: float = option(0.0, 'fraction of the run after which the entropy prior applies')
    sparsity: tuple = option((0.01,), 'weight of the sparsity prior: Cauchy loss log(1 + 2σ²) '
                             'of the density at random points of each volume (Plenoxels), which '
                             'removes haze and floaters: one for both volumes, or one for the '
                             'foreground and one for the background',
                             type=float, nargs='+', metavar='W', default_help='(default: 0.01)')
    sparsity_start: tuple = option((0.15, 0.5), 'fraction of the run after which the sparsity '
                                   'prior applies: one for both volumes, or one for the '
                                   'foreground and one for the background. The default lets the '
                                   'young, dense foreground keep the ground inside its sphere '
                                   '(the mattes) and the background form its geometry before its '
                                   'prior starts (novel views): on the default capture after 10 '
                                   'minutes |alpha - alpha_gt| 0.06 against 0.25 and +0.4 dB '
                                   "held-out PSNR over '0' (the prior from the start)",
                                   type=float, nargs='+', metavar='F',
                                   default_help='(default: 0.15 0.5)')
    near_gradient: float = option(0.5, 'scale the gradients of samples within this distance of '
                                  'their camera (in the units of the unit sphere of NeRF++) by '
                                  '(distance / this)² (Floaters No More: fewer '
                                  'floaters near the cameras; 0: off)')
    tv: float = option(0.0, 'weight of the total-variation prior on the feature grids')
    tv_cells: int = option(16384, 'grid cells per level sampled for the TV prior each step')
    density_bias: float = option(0.0, "grid field: initial density logit: σ = 1 everywhere, above "
                                 "the occupancy threshold, so that empty space is carved out "
                                 "rather than grown into (the grid field's own default, for random "
                                 "models, is more transparent)", shapes_model=True)
    occupancy: bool = option(True, 'skip empty space: an occupancy grid per volume places the '
                             'samples', shapes_model=True)
    occupancy_res: int = option(occ.DEFAULT_RESOLUTION, 'resolution of the occupancy grids',
                                shapes_model=True)
    occupancy_threshold: float = option(
        occ.DEFAULT_THRESHOLD, 'density below which an occupancy cell is empty (per unit length in the foreground, '
        'per unit of s in the background)')
    occupancy_every: int = option(occ.DEFAULT_EVERY,
                                  'steps between refreshes of the occupancy grids')
    grid_levels: tuple = option(tuple(_grid_default('resolutions')),
                                'grid field: resolution of each level',
                                metavar='RES', shapes_model=True)
    fg_warp: float = option(_grid_default('warp_radius'), 'grid field: radius of the inner ball '
                            'that the foreground grid magnifies (it fills half the grid\'s '
                            'radius; 0: a linear grid)', shapes_model=True)
    bg_grid_levels: tuple | None = option(None, 'grid field: resolution of each level of the '
                                          'background grid', type=int, nargs='+', metavar='RES',
                                          default_help='(default: as --grid-levels)',
                                          shapes_model=True)
    bg_s_ratio: tuple = option((_grid_default('s_ratio'),), 'grid field: cells along s (inverse '
                               'radius) per cell of colatitude in the background grid: one '
                               'ratio, or one per background level', type=float, nargs='+',
                               metavar='Q',
                               shapes_model=True)
    coarse_to_fine: tuple = option((), 'grid field: fractions of the run at which the grids '
                                   'double in resolution (they start at RES / 2^n)', type=float,
                                   nargs='*', metavar='F', shapes_model=True)
    grid_channels: int = option(_grid_default('channels'), 'grid field: channels per level',
                                shapes_model=True)
    color: str = option(_grid_default('color'), "grid field: 'deferred' composites the grid "
                        "features along each ray and runs the colour MLP once per ray; 'sample' "
                        "runs it at every sample", choices=('deferred', 'sample'),
                        shapes_model=True)
    dir_octaves: int = option(_grid_default('dir_octaves'),
                              'grid field: frequencies of the view-direction encoding',
                              shapes_model=True)
    color_layers: int = option(_grid_default('color_layers'),
                               'grid field: hidden layers of the colour MLP', shapes_model=True)
    color_width: int = option(_grid_default('hidden'), 'grid field: width of the colour MLP',
                              shapes_model=True)
    seed: int = option(0, 'seed of the initialization, the ray batches and the samples')
    freeze: bool = option(True, 'record the kernels of a training step once and replay them '
                          '(drjit.freeze) instead of tracing every step in Python; re-recorded '
                          'when a prior starts or the grids change resolution')
    checkpoint_every: int = option(500, 'iterations between checkpoints (0: only at the end)')
    preview_every: int = option(500, 'iterations between held-out previews (0: never)')
    downscale: int = option(None, 'integer image downscale factor (default: the smallest that '
                            'keeps the training images under 4.2 M pixels in all, announced)',
                            type=int)
    background: tuple = option((1.0, 1.0, 1.0), 'colour that transparent (RGBA) images are '
                               'composited over', type=_comma_floats, metavar='R,G,B',
                               default_help='(default: 1,1,1)')
    composite: str = option('linear', "sRGB photos: 'linear' decodes each sample's colour and "
                            "composites in linear light (EXR layers recombine exactly); 'srgb' "
                            'sums encoded colour as before issue 11 (measured 1-2 dB better '
                            'held-out PSNR on a small capture; layers recombine only '
                            'approximately)', choices=('linear', 'srgb'), shapes_model=True)
    appearance: bool = option(False, 'learn a colour transform (exposure, white-balance gain and '
                              'bias) per training image; training image 0 is the reference; '
                              'held-out views are then scored NeRF-W style (transform fitted on '
                              'the left half, right half scored)', shapes_model=True)
    lr_appearance: float = option(app.LR_APPEARANCE, 'learning rate of the appearance transforms')
    appearance_prior: float = option(app.PRIOR, 'weight of the L2 prior that keeps the '
                                     'appearance transforms near the identity')
    refine_poses: bool = option(False, 'learn an SE(3) correction of each training camera '
                                '(rotation about its centre, translation) jointly with the '
                                'fields; training image 0 is the reference; held-out views keep '
                                'their given poses', shapes_model=True)
    lr_poses: float = option(poses.LR_POSES, 'learning rate of the pose corrections (radians and '
                             'model-frame units: the cameras lie in the unit sphere)')
    poses_start: float = option(poses.START, 'fraction of the run after which the pose '
                                'corrections are learned (before it the fields are too rough '
                                'to steer them)')

    def __post_init__(self):
        if self.model not in MODEL_KINDS:
            raise ValueError(f"model must be 'nerfpp' or 'nerf', not '{self.model}'")
        if self.iterations is None and self.minutes is None:
            self.iterations = DEFAULT_ITERATIONS
        self.grid_levels, self.background = tuple(self.grid_levels), tuple(self.background)
        if self.bg_grid_levels is not None:
            self.bg_grid_levels = tuple(self.bg_grid_levels)
        self._validate()
        if self.bg_field is None:
            self.bg_field = self.field

    def _validate(self):
        """Every option checked where it is read: one message naming the flag and the value."""
        def bad(name, need):
            value = getattr(self, name)
            shown = ' '.join(map(str, value)) if isinstance(value, tuple) else value
            raise ValueError(f'{flag(TrainConfig, name)} must be {need}, got {shown}')

        def finite(v):
            return isinstance(v, (int, float)) and math.isfinite(v)

        at_least_one = ('batch_rays', 'fg_samples', 'bg_samples', 'color_layers', 'color_width',
                        'downscale', 'grid_channels', 'occupancy_res', 'occupancy_every',
                        'tv_cells')
        for name in at_least_one:
            if getattr(self, name) is not None and getattr(self, name) < 1:   # downscale: auto
                bad(name, 'at least 1')
        for name in ('fine_samples', 'checkpoint_every', 'preview_every', 'dir_octaves', 'seed'):
            if getattr(self, name) < 0:
                bad(name, '0 or more')
        for name in ('lr_grid', 'lr_mlp', 'lr_final', 'lr_appearance', 'lr_poses'):
            if not (finite(getattr(self, name)) and getattr(self, name) > 0):
                bad(name, 'a positive finite number')
        for name in ('distortion', 'opacity_entropy', 'tv', 'entropy_start', 'density_bias',
                     'occupancy_threshold', 'appearance_prior', 'poses_start', 'near_gradient'):
            v = getattr(self, name)
            if not finite(v) or (name != 'density_bias' and v < 0):
                bad(name, 'a finite number' if name == 'density_bias' else
                    'a finite number >= 0')
        if self.minutes is not None and not (finite(self.minutes) and self.minutes > 0):
            bad('minutes', 'a positive number of minutes')
        if self.iterations is not None and self.iterations < 1:
            bad('iterations', 'at least 1')
        if not self.grid_levels or min(self.grid_levels) < 2:
            bad('grid_levels', 'one or more resolutions of at least 2')
        if self.bg_grid_levels is not None and (not self.bg_grid_levels
                                                or min(self.bg_grid_levels) < 2):
            bad('bg_grid_levels', 'one or more resolutions of at least 2')
        if self.color_loss not in optim.COLOR_LOSSES:
            bad('color_loss', ' or '.join(f"'{k}'" for k in optim.COLOR_LOSSES))
        if not (finite(self.adam_beta2) and 0 < self.adam_beta2 < 1):
            bad('adam_beta2', 'a number in (0, 1)')
        if not (finite(self.fg_warp) and 0 <= self.fg_warp < 1):
            bad('fg_warp', 'a radius in [0, 1)')
        for name, ok, one in (('sparsity', lambda w: w >= 0, 'one finite number >= 0'),
                              ('sparsity_start', lambda f: 0 <= f <= 1, 'one fraction in [0, 1]')):
            v = _as_tuple(getattr(self, name))          # per volume: see per_volume()
            setattr(self, name, v)
            if len(v) not in (1, 2) or not all(finite(x) and ok(x) for x in v):
                bad(name, f'{one}, or two (foreground, background)')
        self.bg_s_ratio = _as_tuple(self.bg_s_ratio)
        if (not self.bg_s_ratio or not all(finite(q) and 0 < q <= 1 for q in self.bg_s_ratio)
                or len(self.bg_s_ratio) not in (1, len(self.levels('inverted_sphere')))):
            bad('bg_s_ratio', 'one number in (0, 1], or one per background grid level')
        if not all(finite(f) and 0 < f < 1 for f in self.coarse_to_fine):
            bad('coarse_to_fine', 'fractions between 0 and 1')
        if len(self.background) != 3 or not all(finite(c) for c in self.background):
            bad('background', 'three finite numbers R,G,B')

    def field_config(self, kind, domain):
        """The field config of one volume: the grid options apply to grid fields only."""
        if kind != 'grid':
            return default_field_config(kind, domain)
        start = [max(r >> len(self.coarse_to_fine), 4) for r in self.levels(domain)]
        ratio = self.bg_s_ratio[0] if len(self.bg_s_ratio) == 1 else list(self.bg_s_ratio)
        extra = ({'s_ratio': ratio} if domain == 'inverted_sphere' else
                 {'warp_radius': self.fg_warp})
        return dict(kind='grid', domain=domain, resolutions=start,
                    channels=self.grid_channels, dir_octaves=self.dir_octaves,
                    color_layers=self.color_layers, hidden=self.color_width, color=self.color,
                    density_bias=self.density_bias, **extra)

    def levels(self, domain):
        """The final grid resolutions of one volume's grid field."""
        if domain == 'inverted_sphere' and self.bg_grid_levels is not None:
            return self.bg_grid_levels
        return self.grid_levels

    @property
    def sampling(self):
        """Samples per ray; the NeRF baseline gets both volumes' budget in its one volume."""
        if self.model == 'nerf':
            return Sampling(fg_samples=self.fg_samples + self.bg_samples,
                            bg_samples=self.bg_samples, fine_samples=2 * self.fine_samples)
        return Sampling(self.fg_samples, self.bg_samples, self.fine_samples)

    @property
    def samples_per_ray(self):
        s = self.sampling
        n = s.fg_samples + s.fine_samples
        return n if self.model == 'nerf' else n + s.bg_samples + s.fine_samples

    def model_normalization(self, dataset_normalization):
        """The model frame: the dataset's, or for the NeRF baseline one shrunk into
        :data:`~mi_nerfpp.frame.NERF_CAMERA_RADIUS`."""
        if self.model == 'nerf':
            return dataset_normalization.with_camera_radius(NERF_CAMERA_RADIUS)
        return dataset_normalization

    def resume_conflicts(self, stored: dict) -> list[str]:
        """The model-shaping options in which a stored config (``dataclasses.asdict`` of a
        TrainConfig, as in a checkpoint) differs from this one, as readable lines."""
        now = json.loads(json.dumps(dataclasses.asdict(self)))
        stored = dict(stored)
        stored.setdefault('bg_field', stored.get('field'))
        if isinstance(stored.get('bg_s_ratio'), (int, float)):    # before per-level ratios
            stored['bg_s_ratio'] = [stored['bg_s_ratio']]
        out = []
        for f in dataclasses.fields(self):
            if f.metadata.get('shapes_model') and f.name in stored \
                    and stored[f.name] != now[f.name]:
                out.append(f'{flag(TrainConfig, f.name)}: the checkpoint has {stored[f.name]!r}, '
                           f'this run asks for {now[f.name]!r}')
        return out


class RayBank:
    """Every pixel ray of a split (model frame), its colour and its image index, as Dr.Jit
    arrays."""

    def __init__(self, split):
        if len(split) == 0:
            raise TrainingError('the training split is empty')
        o, d, c, image = [], [], [], []
        for k, (cam, img) in enumerate(zip(split.cameras, split.images)):
            h, w = img.shape[:2]
            py, px = np.mgrid[0:h, 0:w] + 0.5
            oi, di = pixel_rays(cam, px, py)
            o.append(oi)
            d.append(di)
            c.append(img.reshape(-1, 3))
            image.append(np.full(h * w, k, np.uint32))
        o, d, c = (np.concatenate(a).astype(np.float32) for a in (o, d, c))
        self.size = len(c)
        # Owned copies (:mod:`.arrays`): a frozen step of another Trainer may outlive this one.
        self.o = mi.Point3f(*[owned(o[:, i], mi.Float) for i in range(3)])
        self.d = mi.Vector3f(*[owned(d[:, i], mi.Float) for i in range(3)])
        self.rgb = mi.Color3f(*[owned(c[:, i], mi.Float) for i in range(3)])
        self.image = owned(np.concatenate(image), mi.UInt32)
        dr.eval(self.o, self.d, self.rgb, self.image)

    def arrays(self):
        """The bank's Dr.Jit arrays (a frozen step takes them as inputs)."""
        return self.o, self.d, self.rgb, self.image

    @classmethod
    def from_arrays(cls, o, d, rgb, image):
        """A bank over the arrays of :meth:`arrays`."""
        bank = cls.__new__(cls)
        bank.o, bank.d, bank.rgb, bank.image = o, d, rgb, image
        bank.size = dr.width(rgb)
        return bank

    def batch(self, index):
        """``(origin, direction, colour)`` of the rays ``index``."""
        i = mi.UInt32(index)
        return (dr.gather(mi.Point3f, self.o, i), dr.gather(mi.Vector3f, self.d, i),
                dr.gather(mi.Color3f, self.rgb, i))

    def images(self, index):
        """The training-image index of the rays ``index`` (UInt32)."""
        return dr.gather(mi.UInt32, self.image, mi.UInt32(index))


def in_model_frame(dataset, normalization):
    """The dataset's splits with their cameras moved into the model frame of ``normalization``:
    ``{'train': Split, 'validation': Split, 'test': Split}``."""
    return {name: dataclasses.replace(split, cameras=reframe_cameras(
                split.cameras, dataset.normalization, normalization))
            for name, split in (('train', dataset.train), ('validation', dataset.validation),
                                ('test', dataset.test))}


def psnr_from_mse(m):
    return -10.0 * math.log10(m) if m > 0 else float('inf')


class Trainer:
    """Owns the model, the optimizer, the ray bank and the run directory."""

    def __init__(self, dataset, out_dir, config: TrainConfig, resume=False):
        self.dataset, self.out, self.cfg = dataset, out_dir, config
        os.makedirs(out_dir, exist_ok=True)
        self.checkpoint_path = os.path.join(out_dir, 'model.npz')
        remove_stale_temporaries(out_dir, 'model.npz')    # left by a process killed mid-save
        normalization = config.model_normalization(dataset.normalization)
        # --near-gradient is a length in the dataset's frame (NeRF++'s unit sphere); the NeRF
        # baseline's model frame is shrunk about it.
        self.near_gradient = config.near_gradient * normalization.scale / dataset.normalization.scale
        splits = in_model_frame(dataset, normalization)
        self.train, self.validation, self.test = (splits[k] for k in ('train', 'validation',
                                                                      'test'))
        self.rays = RayBank(self.train)
        self.iteration, self.elapsed, self.history = 0, 0.0, []

        meta, state = {}, {}
        if resume and os.path.exists(self.checkpoint_path):
            self.model, meta, state = load_checkpoint(self.checkpoint_path)
            conflicts = (config.resume_conflicts(meta.get('config', {}))
                         + data_conflicts(meta.get('data', {}), self.data_summary()))
            if (self.model.composite != config.composite and self.model.color_space == 'srgb'
                    and 'composite' not in meta.get('config', {})):     # a pre-issue-11 file
                conflicts.append(f'--composite: the checkpoint composites in '
                                 f'{self.model.composite!r}, this run asks for '
                                 f'{config.composite!r}')
            if conflicts:
                raise TrainingError(f'{self.checkpoint_path} cannot be resumed with other model '
                                    f'options or data: ' + '; '.join(conflicts))
            self.iteration = int(meta['iteration'])
            self.elapsed = float(meta['elapsed'])
            self.history = meta.get('history', [])
        elif resume:
            raise TrainingError(f'--resume: no checkpoint at {self.checkpoint_path}')
        else:
            self.model = NeRFPPModel.create(
                background=config.model == 'nerfpp', seed=config.seed,
                normalization=normalization,
                color_space=dataset.color_space, composite=config.composite,
                appearance_images=len(self.train) if config.appearance else 0,
                pose_images=len(self.train) if config.refine_poses else 0,
                fg_config=config.field_config(config.field, 'ball'),
                bg_config=config.field_config(config.bg_field, 'inverted_sphere'))
            if config.occupancy:
                self.model.enable_occupancy(config.occupancy_res, config.occupancy_threshold)
        self.saved_iteration = self.iteration if resume else None
        self.rng = np.random.default_rng(config.seed)
        if 'rng' in meta:
            self.rng.bit_generator.state = meta['rng']

        self.opt = optim.adam(self.model.parameters(), config.lr_mlp, lazy=config.lazy_adam,
                              beta_2=config.adam_beta2)
        self._restore_optimizer(state)
        # One step's kernels, recorded on the first call and replayed after (drjit.freeze):
        # tracing the step in Python took ~18 of ~76 ms (README, "Measured performance").
        self._compute = (dr.freeze(self._forward_backward) if config.freeze
                         else self._forward_backward)

    # ------------------------------------------------------------------ optimizer state
    def _optimizer_state(self):
        state = {}
        for k, (_, _, _, (t, m, v, _)) in self.opt.state.items():
            state[f'adam.t/{k}'] = np.array(t, dtype=np.uint32)
            state[f'adam.m/{k}'] = np.array(m, dtype=np.float32)
            state[f'adam.v/{k}'] = np.array(v, dtype=np.float32)
        return state

    def _restore_optimizer(self, state):
        # drjit.opt.Adam keeps (value, promoted, lr, (t, m, v, v_max)) per key (drjit 1.5).
        for k in list(self.opt.keys()):
            if f'adam.m/{k}' not in state:
                continue
            value, promoted, lr, _ = self.opt.state[k]
            # Owned copies: the first frozen step releases them (see :mod:`.arrays`).
            self.opt.state[k] = (value, promoted, lr,
                                 (dr.opaque(mi.UInt32, int(np.ravel(state[f'adam.t/{k}'])[0])),
                                  owned(state[f'adam.m/{k}'], mi.Float),
                                  owned(state[f'adam.v/{k}'], mi.Float), None))

    # ------------------------------------------------------------------ training
    def progress(self):
        """Fraction of the run done, by iterations or by time (whichever is nearer the end)."""
        p = 0.0
        if self.cfg.iterations:
            p = max(p, self.iteration / self.cfg.iterations)
        if self.cfg.minutes:
            p = max(p, self.elapsed / (60.0 * self.cfg.minutes))
        return p

    def step(self):
        """One optimization step. Returns ``(loss, fine-pass MSE)`` as Python floats.

        A Ctrl-C (or SIGTERM) anywhere in the step raises :class:`KeyboardInterrupt`, also when
        it lands in Python code that Dr.Jit calls and re-raises wrapped (:func:`_interrupt_in`)."""
        try:
            if self.model.poses is None:
                return self._step()
            with poses.gradient_scope():
                return self._step()
        except RuntimeError as e:
            interrupt = _interrupt_in(e)
            if interrupt is None:
                raise
            raise interrupt from None

    def _step(self):
        cfg = self.cfg
        self._coarse_to_fine()
        optim.set_learning_rates(self.opt, self.progress(), cfg.lr_grid, cfg.lr_mlp, cfg.lr_final,
                                 {'appearance': cfg.lr_appearance, 'poses': cfg.lr_poses})
        if self.model.occupancy and self.iteration % cfg.occupancy_every == 0:
            with stage('occupancy refresh'):
                self.model.set_parameters({k: dr.detach(self.opt[k]) for k in self.opt.keys()})
                self.model.update_occupancy(int(self.rng.integers(0, 2 ** 31)))
        inputs = self._step_inputs()
        # No cyclic garbage collection while a step is recorded: releasing a collected
        # array that maps NumPy memory cannot be recorded (:mod:`.arrays`).
        collecting = gc.isenabled()
        gc.disable()
        threshold = dr.expand_threshold()
        dr.set_expand_threshold(GRADIENT_EXPAND_THRESHOLD)
        try:
            loss, fine = self._compute(inputs)
        finally:
            dr.set_expand_threshold(threshold)
            if collecting:
                gc.enable()
        # The model's fields read the parameters after the update (previews, evaluations);
        # a replayed frozen step runs no Python, so the step itself cannot set them.
        self.model.set_parameters({k: dr.detach(self.opt[k]) for k in self.opt.keys()})
        self.iteration += 1
        return float(loss.array[0]), float(fine.array[0])

    def _step_inputs(self):
        """Everything a step reads, as :func:`drjit.freeze` traverses it: the optimizer (its
        parameters, moments and learning rates), the occupancy grids, this step's random
        draws (Dr.Jit arrays from a generator seeded by the run's RNG, so a resumed run
        draws the same), and as Python values the phase of the run (which priors apply) and
        the grids' shapes: a change of either records the step anew."""
        cfg, n, p = self.cfg, self.cfg.batch_rays, self.progress()
        gen = dr.rng(seed=int(self.rng.integers(0, 2 ** 63)))
        sparse = [field is not None and weight > 0 and p >= start
                  for field, weight, start in zip((self.model.fg, self.model.bg),
                                                  per_volume(cfg.sparsity),
                                                  per_volume(cfg.sparsity_start))]
        grids = [k for k in self.opt.keys() if optim.is_grid(k)] if cfg.tv > 0 else []
        draws = {
            'index': gen.integers(mi.UInt32, n, 0, self.rays.size),
            'seed': gen.integers(mi.UInt32, n, 0, 2 ** 32 - 1),
            'sparsity': [[gen.random(mi.Float, n) for _ in range(4)] if on else None
                         for on in sparse],
            'tv': {k: gen.integers(mi.UInt32, min(cfg.tv_cells, self._cells(k)), 0,
                                   self._cells(k)) for k in grids},
        }
        dr.eval(draws)
        phase = dict(refine=self.model.poses is not None and p >= cfg.poses_start,
                     entropy=cfg.opacity_entropy > 0 and p >= cfg.entropy_start,
                     shapes=tuple(tuple(self.opt[k].shape) for k in self.opt.keys()))
        return {'opt': self.opt, 'draws': draws, 'phase': phase, 'rays': self.rays.arrays(),
                'occupancy': {k: g.density for k, g in self.model.occupancy.items()}}

    def _cells(self, key):
        shape = self.opt[key].shape
        return shape[0] * shape[1] * shape[2]

    def _forward_backward(self, inputs):
        """Loss, gradients and the Adam update of one step from :meth:`_step_inputs` alone
        (recorded once and replayed when ``freeze`` is on). Returns ``(loss, fine-pass
        MSE)`` as Dr.Jit arrays."""
        cfg, model = self.cfg, self.model
        opt, draws, phase = inputs['opt'], inputs['draws'], inputs['phase']
        rays = RayBank.from_arrays(*inputs['rays'])
        index = draws['index']
        o, d, gt = rays.batch(index)
        occupancy = {}
        for k, grid in model.occupancy.items():       # the model's grids are left untouched
            occupancy[k] = copy.copy(grid)
            occupancy[k].density = inputs['occupancy'][k]
        model.set_parameters({k: opt[k] for k in opt.keys()})
        refine = phase['refine']
        if model.poses is not None:    # the rays of the corrected cameras (:mod:`.poses`)
            params = opt['poses'] if refine else dr.detach(opt['poses'])
            o, d = poses.correct_rays(params, rays.images(index), o, d)
        res = render_rays(o, d, *model.radiance_fields(), cfg.sampling, seed=draws['seed'],
                          occupancy=occupancy, ray_gradients=refine,
                          near_gradient=self.near_gradient)
        # Radiance is linear; the loss compares it in the encoding of the images, after the
        # image's colour transform when appearance is learned.
        encode = model.loss_encoding
        if model.appearance is not None:
            image, params = rays.images(index), opt['appearance']
            encode = lambda c, e=encode: e(app.transform_rays(params, image, c))  # noqa: E731
        pred = encode(res.fine.rgb)
        color_loss = optim.COLOR_LOSSES[cfg.color_loss]
        if res.coarse is not None:
            loss = color_loss(pred, gt) + color_loss(encode(res.coarse.rgb), gt)
        else:
            loss = PHOTOMETRIC_WEIGHT * color_loss(pred, gt)
        fine = dr.detach(optim.mse(pred, gt))     # for the PSNR shown while training
        if model.appearance is not None and cfg.appearance_prior > 0:
            loss += cfg.appearance_prior * app.prior(opt['appearance'])
        if cfg.distortion > 0 and cfg.distortion_scope == 'ray':
            loss += cfg.distortion * dr.mean(ray_distortion(res))
        elif cfg.distortion > 0:
            for vol in (res.fg, res.bg):
                if vol is not None:
                    loss += cfg.distortion * dr.mean(distortion(vol.weights, vol.position, vol.n))
        if phase['entropy']:
            loss += cfg.opacity_entropy * priors.opacity_entropy(res.fg.fine.opacity)
        loss += self._sparsity_loss(draws['sparsity'])
        if cfg.tv > 0:
            loss += cfg.tv * sum((priors.grid_tv(opt[k], idx) for k, idx in draws['tv'].items()),
                                 mi.Float(0.0))
        with stage('losses and reverse pass'):
            dr.backward(loss)
        with stage('adam'):
            opt.step()
        return loss, fine

    def _coarse_to_fine(self):
        """Double the grids' resolution at each ``coarse_to_fine`` fraction of the run passed."""
        due = sum(self.progress() >= f for f in self.cfg.coarse_to_fine)
        for volume, field in (('fg', self.model.fg), ('bg', self.model.bg)):
            if field is None or field.kind != 'grid':
                continue
            for level, final in enumerate(self.cfg.levels(field.domain)):
                target = max(final >> (len(self.cfg.coarse_to_fine) - due), 4)
                if field.resolutions[level] < target:
                    key = f'{volume}.grid{level}'
                    field.set_parameters({f'grid{level}': dr.detach(self.opt[key])})
                    field.upsample(level, target)
                    self.opt[key] = field.params[f'grid{level}']   # new shape: fresh Adam moments

    def _sparsity_loss(self, points):
        """Cauchy sparsity of each volume's density at ``batch_rays`` random points, weighted
        by the volume's ``sparsity`` (``points``: 4 uniform Floats per volume, None where the
        volume is absent, its weight is 0 or the run has not reached its ``sparsity_start``)."""
        total = mi.Float(0.0)
        for field, weight, u in zip((self.model.fg, self.model.bg), per_volume(self.cfg.sparsity),
                                    points):
            if u is not None:
                total += weight * priors.cauchy_sparsity(
                    field.density(priors.random_points(field.domain, u)))
        return total

    def data_summary(self):
        """What a checkpoint records of its training data, to refuse resuming on other data."""
        return {'dataset': os.path.abspath(self.dataset.root), 'train_views': len(self.train),
                'training_rays': self.rays.size}

    def save(self):
        """Write the checkpoint atomically. A failed write (disk full, read-only) raises
        :class:`TrainingError` at once; the previous checkpoint stays as it was."""
        self.model.set_parameters({k: dr.detach(self.opt[k]) for k in self.opt.keys()})
        meta = {'iteration': self.iteration, 'elapsed': self.elapsed,
                'rng': self.rng.bit_generator.state, 'history': self.history,
                'config': dataclasses.asdict(self.cfg), 'dataset': self.dataset.root,
                'data': self.data_summary()}
        try:
            save_checkpoint(self.checkpoint_path, self.model, meta=meta,
                            state=self._optimizer_state())
        except OSError as e:
            kept = ('nothing was saved before' if self.saved_iteration is None else
                    f'the previous checkpoint (iteration {self.saved_iteration}) is intact')
            raise TrainingError(f'cannot save the checkpoint {self.checkpoint_path} at iteration '
                                f'{self.iteration}: {e.strerror or e}; {kept}. Free space or '
                                f'choose a writable --out, then --resume') from e
        self.saved_iteration = self.iteration

    def done(self):
        return ((self.cfg.iterations is not None and self.iteration >= self.cfg.iterations)
                or (self.cfg.minutes is not None and self.elapsed >= 60.0 * self.cfg.minutes))

    def run(self, on_step=None, on_preview=None):
        """Train until done; checkpoints periodically, on Ctrl-C and at the end.

        ``on_step(trainer, loss, psnr)`` is called after every step; ``on_preview(trainer)``
        every ``preview_every`` iterations. Raises :class:`TrainingError` on a non-finite
        loss, leaving the last good checkpoint in place. Returns False if interrupted.
        """
        last_good = self.iteration
        # A scheduler's SIGTERM stops training like Ctrl-C: the checkpoint is saved.
        terminate = _raise_interrupt if _in_main_thread() else None
        previous = signal.signal(signal.SIGTERM, terminate) if terminate else None
        try:
            while not self.done():
                t0 = time.perf_counter()
                loss, fine = self.step()
                self.elapsed += time.perf_counter() - t0
                if not math.isfinite(loss):
                    raise TrainingError(
                        f'the loss became {loss} at iteration {self.iteration}; stopping. '
                        f'The last good checkpoint ({self.checkpoint_path}, iteration '
                        f'{last_good}) is kept. Lower the learning rates (--lr-grid, --lr-mlp) '
                        f'and resume with --resume.')
                p = psnr_from_mse(fine)
                if self.iteration % 10 == 0 or self.iteration == 1:
                    self.history.append([self.iteration, round(self.elapsed, 3), loss, p])
                if on_step:
                    on_step(self, loss, p)
                if self.cfg.checkpoint_every and self.iteration % self.cfg.checkpoint_every == 0:
                    self.save()
                    last_good = self.iteration
                if on_preview and self.cfg.preview_every and \
                        self.iteration % self.cfg.preview_every == 0:
                    on_preview(self)
        except KeyboardInterrupt:
            with _signals_deferred(terminate is not None):    # a second Ctrl-C must not
                self.save()                                   # break the save
            return False
        finally:
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)
        self.save()
        return True

    def samples_per_second(self):
        """Field evaluations per second of training so far (coarse + fine, both volumes)."""
        return samples_per_second(self.cfg, self.iteration, self.elapsed)


def _in_main_thread():
    import threading
    return threading.current_thread() is threading.main_thread()


@contextlib.contextmanager
def _signals_deferred(enabled):
    """SIGINT and SIGTERM ignored inside (main thread only), their handlers restored after."""
    if not enabled:
        yield
        return
    saved = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt(f'signal {signum}')


def _interrupt_in(error):
    """The :class:`KeyboardInterrupt` that ``error`` wraps, or None. Dr.Jit re-raises an
    exception from Python code that it calls - a step being recorded by ``drjit.freeze``, a
    loop body, a search predicate - as a RuntimeError caused by it, once per level: a Ctrl-C
    or SIGTERM that lands there arrives as such a chain."""
    while error is not None:
        if isinstance(error, KeyboardInterrupt):
            return error
        error = error.__cause__
    return None


def data_conflicts(stored: dict, now: dict) -> list[str]:
    """How the training data of a checkpoint (:meth:`Trainer.data_summary`) differs from now."""
    names = {'dataset': 'dataset', 'train_views': 'training views',
             'training_rays': 'training rays (images, sizes or --downscale)'}
    return [f'{names[k]}: the checkpoint was trained on {stored[k]!r}, this run has {now[k]!r}'
            for k in names if k in stored and stored[k] != now[k]]


def samples_per_second(cfg, iterations, seconds):
    return iterations * cfg.batch_rays * cfg.samples_per_ray / seconds if seconds > 0 else 0.0


def run_config(meta) -> TrainConfig:
    """The :class:`TrainConfig` a checkpoint's ``meta`` was trained with (fields it does not
    store, from versions before them, take today's defaults)."""
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    return TrainConfig(**{k: v for k, v in meta.get('config', {}).items() if k in fields})


def open_run(run_dir):
    """A finished or interrupted run: ``(model, meta, config, splits)``.

    The dataset is re-read from where the run found it, with the same options; ``splits``
    (``{'train', 'validation', 'test'}``) are in the model's frame.
    """
    from .data import load_dataset
    model, meta, _ = load_checkpoint(os.path.join(run_dir, 'model.npz'))
    cfg = run_config(meta)
    root = meta.get('dataset')
    if not root or not os.path.exists(root):
        raise TrainingError(f'{run_dir}/model.npz: its dataset {root!r} is not there any more')
    dataset = load_dataset(root, downscale=cfg.downscale, background=cfg.background)
    return model, meta, cfg, dataclasses.replace(dataset, **in_model_frame(dataset,
                                                                           model.normalization))
