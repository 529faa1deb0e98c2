"""Fitting the foreground and background volumes to posed images (Dr.Jit AD, CPU or GPU).

One training step: draw a batch of random rays across all training images
(:mod:`.raybank`), render them with :func:`mi_nerfpp.core.render.render_rays` (the same code
the integrator uses), take the loss as named terms - the colour loss of the composite against
the pixels (Charbonnier by default, or the squared error; radiance is composited in linear
light, and for sRGB photos the composite is sRGB-encoded before the loss, see
:meth:`~mi_nerfpp.core.model.NeRFPPModel.radiance_fields`) and the priors (:mod:`.priors`) -,
back-propagate with Dr.Jit and take an Adam step (``drjit.opt``). Learning rates
decay exponentially to ``lr_final`` times their start over the run (:mod:`.optim`, shared
with :mod:`.ambiguity`). With ``freeze`` (the default) the kernels of a step are recorded once
by :func:`drjit.freeze` and replayed: a step is a function of :meth:`Trainer._step_inputs`
alone (optimizer, occupancy grids, ray bank, random draws as Dr.Jit arrays, and the phase of
the run as Python values, whose change records the step anew).

The run directory holds ``model.npz`` (the latest checkpoint, written atomically with
the optimizer and RNG state and the loss history, so ``resume=True`` continues exactly); a
run (:mod:`.run`) adds ``preview/`` and, at the end, the evaluation outputs. The options of
training are a :class:`~mi_nerfpp.training.config.TrainConfig`; the model stores the sample counts it
is trained with as its render settings (:class:`~mi_nerfpp.core.model.RenderSettings`), so that
renders of it use them.
"""
from __future__ import annotations

import contextlib
import copy
import dataclasses
import gc
import math
import os
import signal
import threading
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_nerfpp import _start
from mi_nerfpp.core import appearance as app
from mi_nerfpp.core import poses
from mi_nerfpp.core.arrays import llvm_backend
from mi_nerfpp.core.coverage import CoverageFill
from mi_nerfpp.core.frame import reframe_cameras
from mi_nerfpp.core.model import NeRFPPModel
from mi_nerfpp.core.profiling import stage
from mi_nerfpp.core.render import RenderOptions, render_rays
from mi_nerfpp.errors import interrupt_in
from mi_nerfpp.files.atomic import remove_stale_temporaries
from mi_nerfpp.files.checkpoint import REMEDY as CHECKPOINT_REMEDY
from mi_nerfpp.files.checkpoint import (CheckpointError, NonFiniteStateError, load_checkpoint,
                                        migration_notes, progress, read_version,
                                        save_checkpoint)
from mi_nerfpp.training import choices, optim, priors, transients
from mi_nerfpp.training.config import RETIRED_AFTER, TrainConfig, per_volume, stored_config
from mi_nerfpp.training.error_map import ErrorMap
from mi_nerfpp.training.transients import TransientWeights
from mi_nerfpp.training.errors import TrainingError
from mi_nerfpp.training.metrics import psnr_from_mse
from mi_nerfpp.training.raybank import RayBank
from mi_nerfpp.training.schedule import (ImagePyramid, OccupancyRefresh, SparseAllocation,
                                         passed, sparse_levels)
from mi_nerfpp.training.signs import CaptureSigns

# Gradients scattered into arrays of up to this many entries are summed in one copy per thread
# and added up after the kernel (Dr.Jit's "expand" reduction) instead of by atomic adds, in steps
# of at least EXPAND_MIN_SAMPLES field samples: a copy per thread of the 8.4 M-entry grid levels
# costs a fixed memset and reduction per step, atomics a cost per sample. Measured on the default
# capture (median step, `benchmarks/train.py --batch-rays B`): 1,024 rays of 48 samples 31.5 ms
# with atomics against 42.5 ms expanded, 2,048 rays 43.5 against 50.1 ms, 4,096 rays 71.9
# against 65.8 ms. Expansion is Dr.Jit's LLVM backend's (on 2 cores, measured); on CUDA a step
# keeps Dr.Jit's defaults (:meth:`Trainer._step`).
GRADIENT_EXPAND_THRESHOLD = 1 << 25
EXPAND_MIN_SAMPLES = 1 << 17
# Whether a step's atomic gradient sums first add up, within a SIMD packet, the operands that
# target the same entry (Dr.Jit's JitFlag.ScatterReduceLocal, on by default). Off, measured on
# the default capture: the grids' gradient kernels 8.8 against 13.6 ms per step (kernel
# history, two runs one after the other), and steps 1.01-1.06x as fast side by side in five
# runs (`python benchmarks/versus.py train --base HEAD --rounds 16`): the pre-reduction costs
# more than the atomic collisions it saves. Measured on the CPU (LLVM), and set there only: CUDA
# keeps its default (a warp's pre-reduction, what the flag was made for).
GRADIENT_LOCAL_REDUCTION = False


def in_model_frame(dataset, normalization):
    """The dataset's splits with their cameras moved into the model frame of ``normalization``:
    ``{'train': Split, 'validation': Split, 'test': Split}``."""
    return {name: dataclasses.replace(split, cameras=reframe_cameras(
                split.cameras, dataset.normalization, normalization))
            for name, split in (('train', dataset.train), ('validation', dataset.validation),
                                ('test', dataset.test))}


class Trainer:
    """Owns the model, the optimizer (which owns the parameters: :func:`.optim.write_back`
    gives them to the model), the ray bank, the run directory, and the parts that act at
    times of their own (:mod:`.schedule`: the occupancy refresh, the sparse levels' allocation,
    the image pyramid; the priors' starts, :mod:`.priors`).

    A step (:meth:`_step`): the learning rates of this point of the run, the parts that are due,
    the step's inputs (:meth:`_step_inputs`), the loss and its gradients and the Adam update
    (:meth:`_forward_backward`, recorded once and replayed), then what reads the step's errors
    (the error map, the capture's signs). The loss is a dictionary of named terms
    (:meth:`_loss_terms`), each kept in the run's history."""

    def __init__(self, dataset, out_dir, config: TrainConfig, resume=False):
        self.dataset, self.out = dataset, out_dir
        os.makedirs(out_dir, exist_ok=True)
        self.checkpoint_path = os.path.join(out_dir, 'model.npz')
        remove_stale_temporaries(out_dir, 'model.npz')    # left by a process killed mid-save
        # What the options leave to the capture (jobs.run.prepare chose and announced it).
        self.cfg = config = choices.from_capture(config, dataset, sparse=False)
        normalization = config.model_normalization(dataset.normalization)
        # --near-gradient is a length in the dataset's frame (NeRF++'s unit sphere); the NeRF
        # baseline's model frame is shrunk about it.
        self.near_gradient = (config.losses.near_gradient * normalization.scale
                              / dataset.normalization.scale)
        splits = in_model_frame(dataset, normalization)
        self.train, self.validation, self.test = (splits[k] for k in ('train', 'validation',
                                                                      'test'))
        self.masks = config.losses.masks or 'none'      # (:mod:`mi_nerfpp.data.masks`)
        self.rays = RayBank(self.train, masks=self.masks != 'none')
        self.iteration, self.elapsed, self.history = 0, 0.0, []
        meta, state = self._open_model(resume, normalization)
        self.saved_iteration = self.iteration if resume else None
        if self.model.bg is not None and self.model.coverage is None:
            with stage('coverage fill'):
                self.model.coverage = CoverageFill.of_views(
                    self.train.cameras, self.train.images, dataset.color_space,
                    weights=self._background_weights())
        self.rng = np.random.default_rng(config.schedule.seed)
        if 'rng' in meta:
            self.rng.bit_generator.state = meta['rng']      # checked: files.checkpoint.META
        o, s, losses = config.optimizer, config.schedule, config.losses
        self.opt = optim.adam(self.model.parameters(), o.lr_mlp, beta_2=o.adam_beta2)
        optim.restore_adam(self.opt, state)
        # The similarity the refined cameras may not drift by together (:func:`~mi_nerfpp.
        # core.poses.gauge_basis`): taken out of the corrections after every step.
        self.gauge = (poses.gauge_basis([cam.c2w[:3, 3] for cam in self.train.cameras])
                      if self.model.poses is not None else None)

        # The parts that act at times of their own; a resumed run has their past behind it.
        self.occupancy = (OccupancyRefresh(config.sampling.occupancy_every)
                          if self.model.occupancy else None)
        self.sparse = SparseAllocation(s.sparse_at, s.sparse_entries, self.model,
                                       self.progress(), bank=self.rays)
        self.pyramid = ImagePyramid(self.rays, s.pyramid)
        self.sparsity = priors.Sparsity(per_volume(losses.sparsity),
                                        per_volume(losses.sparsity_start))
        # Where the rays go (:mod:`.error_map`) and what the run tells about the capture
        # (:mod:`.signs`, read at its end); both resume with the run.
        self.error_map = (ErrorMap(*self.rays.layout[:3], s.error_tile, s.error_rays)
                          if s.error_rays > 0 else None)
        if self.error_map is not None:
            try:
                self.error_map.restore(state)
            except ValueError as e:     # a damaged file: one line, not NumPy's (issue 63)
                raise CheckpointError(f'{self.checkpoint_path}: {e}: {CHECKPOINT_REMEDY}, or '
                                      f'resume with --error-rays 0') from None
        self._tiles = None          # the error map's tiles of this step's rays
        # Transients without masks (:mod:`.transients`): loss weights from how the other photos
        # that see a tile's point are fitted; resumes with the run.
        self.transients = None
        if config.losses.transients > 0:
            n, h, w = self.rays.layout[:3]
            self.transients = TransientWeights(self.train.cameras, h, w, transients.TILE,
                                               config.losses.transients)
            try:
                self.transients.restore(state)
            except ValueError as e:
                raise CheckpointError(f'{self.checkpoint_path}: {e}: {CHECKPOINT_REMEDY}, or '
                                      f'resume with --transients 0') from None
        self._transient_tiles = None
        self.signs = CaptureSigns(len(self.train))
        self.signs.restore(state)

        # One step's kernels, recorded on the first call and replayed after (drjit.freeze):
        # tracing the step in Python took ~18 of ~76 ms (README, "Measured performance").
        self._compute = dr.freeze(self._forward_backward) if s.freeze else self._forward_backward
        self._recorded = None       # the Python values the frozen step was recorded for
        self._non_finite = None     # the last step's guard (see parameters_finite)
        self.terms = {}             # the last step's loss terms (Dr.Jit arrays)
        # The scatter-reduction settings measured on the CPU (see GRADIENT_*) apply on LLVM.
        self._llvm = llvm_backend()

    def _open_model(self, resume, normalization):
        """The model: the checkpoint's when resuming (refused where it does not match this run),
        else a new one. Returns the checkpoint's ``(meta, state)`` (empty for a new model)."""
        config = self.cfg
        if resume and os.path.exists(self.checkpoint_path):
            self.model, meta, state = load_checkpoint(self.checkpoint_path)
            self._check_resumable(meta)
            self.iteration, self.elapsed = progress(meta, self.checkpoint_path)
            self._check_allocations(meta)
            self.history = meta.get('history', [])
            self.model.sampling = config.render_sampling     # --samples may change
            return meta, state
        if resume:
            raise TrainingError(f'--resume: no checkpoint at {self.checkpoint_path}')
        m, s, n = config.model, config.sampling, len(self.train)
        self.model = NeRFPPModel.create(
            background=m.kind == 'nerfpp', seed=config.schedule.seed,
            normalization=normalization, color_space=self.dataset.color_space,
            appearance_images=n if m.appearance else 0,
            embedding_images=n if m.appearance_embedding else 0,
            pose_images=n if m.refine_poses else 0,
            fg_config=config.field_config(m.field, 'ball'),
            bg_config=config.field_config(m.bg_field, 'inverted_sphere'),
            sampling=config.render_sampling)
        if s.occupancy:
            self.model.enable_occupancy(s.occupancy_res, s.occupancy_threshold)
        return {}, {}

    def _check_resumable(self, meta):
        """Refuse, in one line, a checkpoint that this run cannot continue: trained with an
        option since removed, or with other model options or data."""
        weights = self.model.config
        stored = stored_config(meta, self.checkpoint_path, weights)
        retired = self.cfg.retired_in(stored, weights)
        if retired:
            raise TrainingError(
                f'{self.checkpoint_path} was trained with {", ".join(retired)}, which this '
                f'version no longer has (measured and not kept: docs/experiments.md): resume '
                f'it with mi-nerfpp at commit {RETIRED_AFTER} or before, or evaluate and '
                f'render it as it is')
        model_conflicts = self.cfg.resume_conflicts(stored, weights)
        conflicts = model_conflicts + data_conflicts(meta.get('data', {}), self.data_summary())
        if conflicts:       # why an older file's weights differ from today's defaults
            version = read_version(self.checkpoint_path)
            why = ''.join(f'; {note} (a version {version} checkpoint)'
                          for note in migration_notes(version) if model_conflicts)
            raise TrainingError(f'{self.checkpoint_path} cannot be resumed with other model '
                                f'options or data: ' + '; '.join(conflicts) + why)

    def _check_allocations(self, meta):
        """Refuse, in one line, a resumed run that changes how the sparse levels' bricks are
        chosen (``--sparse-entries``, ``--sparse-at``) when they were allocated and no
        allocation is ahead of it: the model keeps the bricks chosen the old way, and the
        run would record a value that never took effect (issue 63)."""
        if not any(len(b) for b in self.model.allocated_bricks().values()):
            return
        stored = TrainConfig.stored_options(stored_config(meta, self.checkpoint_path))
        s = self.cfg.schedule
        if passed(s.sparse_at, self.progress()) < len(s.sparse_at):
            return      # an allocation is ahead: the new values take effect there
        changed = [f'{self.cfg.flag(name)} {_words(stored[name])}'
                   for name, now in (('sparse_entries', s.sparse_entries),
                                     ('sparse_at', s.sparse_at))
                   if name in stored and stored[name] != now]
        if changed:
            raise TrainingError(
                f'{self.checkpoint_path}: its sparse levels were allocated with '
                f'{" and ".join(changed)}, and no allocation is ahead of this run to take '
                f'other values: resume with {" ".join(changed)} (other values need a new run, '
                f'or a --sparse-at fraction still ahead)')

    def _background_weights(self):
        """Per training image how much each pixel shows of the background (for the coverage
        fill's colours): masked-out pixels none (``--masks ignore``), the object's none
        (``--masks object``); None: all of them."""
        if self.masks == 'none':
            return None
        return [None if m is None else (m / 255.0 if self.masks == 'ignore' else 1 - m / 255.0)
                for m in self.train.masks]

    @property
    def allocations(self) -> list[dict]:
        """What the sparse levels allocated, one dict per level and allocation."""
        return self.sparse.records

    # ------------------------------------------------------------------ training
    def progress(self):
        """Fraction of the run done, by iterations or by time (whichever is nearer the end)."""
        p, schedule = 0.0, self.cfg.schedule
        if schedule.iterations:
            p = max(p, self.iteration / schedule.iterations)
        if schedule.minutes:
            p = max(p, self.elapsed / (60.0 * schedule.minutes))
        return p

    def step(self):
        """One optimization step. Returns ``(loss, fine-pass MSE)`` as Python floats.

        A Ctrl-C (or SIGTERM) anywhere in the step raises :class:`KeyboardInterrupt`, also when
        it lands in Python code that Dr.Jit calls and re-raises wrapped (:func:`~mi_nerfpp.errors.interrupt_in`)."""
        try:
            if self.model.poses is None:
                return self._step()
            with poses.gradient_scope():
                return self._step()
        except RuntimeError as e:
            interrupt = interrupt_in(e)
            if interrupt is None:
                raise
            raise interrupt from None

    def _step(self):
        p, o = self.progress(), self.cfg.optimizer
        optim.set_learning_rates(self.opt, p, o.lr_grid, o.lr_mlp, o.lr_final,
                                 {'appearance': o.lr_appearance, 'embedding': o.lr_appearance,
                                  'poses': o.lr_poses})
        if self.occupancy is not None and self.occupancy.due(self.iteration):
            optim.write_back(self.opt, self.model)
            self.occupancy(self.model, int(self.rng.integers(0, 2 ** 31)))
        if self.sparse.due(p):
            self.sparse(self.model, self.opt, self.iteration, p)
        inputs = self._step_inputs(p)
        self._fresh_recording(inputs)
        try:
            big = self.cfg.schedule.batch_rays * self.cfg.samples_per_ray >= EXPAND_MIN_SAMPLES
            with _step_settings(self._llvm, big):
                loss, fine, self.terms, per_ray = self._compute(inputs)
        finally:
            self.model.set_appearance(None)     # renders outside the step: the neutral code
        self._non_finite = inputs['non_finite']   # the step's guard (see parameters_finite)
        if self.gauge is not None and inputs['phase']['refine']:
            self.opt['poses'] = mi.TensorXf(poses.pin_gauge(self.opt['poses'].numpy(),
                                                            self.gauge).astype(np.float32))
        if 'appearance' in self.opt:            # the transforms' gauge: their mean
            self.opt['appearance'] = mi.TensorXf(app.center(self.opt['appearance'].numpy())
                                                 .astype(np.float32))
        # A replayed frozen step runs no Python, so the step itself cannot give the model the
        # updated parameters (previews and evaluations read them).
        optim.write_back(self.opt, self.model)
        squared_error, predicted, photographed = (v.numpy() for v in per_ray[:3])
        if self.error_map is not None:
            self.error_map.update(self._tiles, squared_error)
        if self.transients is not None:
            self.transients.update(self._transient_tiles, squared_error, per_ray[3].numpy())
        self.signs.update(self._view_of(inputs), squared_error, predicted, photographed)
        self.iteration += 1
        return float(loss.array[0]), float(fine.array[0])

    def _view_of(self, inputs) -> np.ndarray:
        """The training view of each ray of a step's ``inputs``."""
        bank = RayBank.from_arrays(inputs['rays'])
        return bank.images(inputs['draws']['index']).numpy().astype(np.int64)

    def _fresh_recording(self, inputs):
        """A new frozen step whenever the Python values of the step's inputs change (the
        phase, the grids' shapes, the image pyramid's level): Dr.Jit's frozen function crashed
        (SIGSEGV) recording a second key after several replays of the first (--pyramid 0.5 0.6
        0.7 0.8 on 32x24 images, at the move to the next level). These values only move
        forward during a run, so a discarded recording is not needed again."""
        if not self.cfg.schedule.freeze:
            return
        rays = inputs['rays']
        key = (repr(inputs['phase']), rays.get('layout'), rays.get('factor'))
        if self._recorded is not None and key != self._recorded:
            self._compute = dr.freeze(self._forward_backward)
        self._recorded = key

    def _step_inputs(self, progress):
        """Everything a step reads, as :func:`drjit.freeze` traverses it: the optimizer (its
        parameters, moments and learning rates), the occupancy grids, the ray bank at this
        level of the image pyramid, this step's random draws (Dr.Jit arrays from a generator
        seeded by the run's RNG, so a resumed run draws the same), and as Python values the
        phase of the run (which priors apply) and the grids' shapes: a change of either
        records the step anew."""
        n = self.cfg.schedule.batch_rays
        gen = dr.rng(seed=int(self.rng.integers(0, 2 ** 63)))
        rays = self.pyramid.level(progress)
        fields = (self.model.fg, self.model.bg)
        if self.error_map is not None:
            index, self._tiles = self.error_map.draw(self.rng, n, rays.factor)
            index = mi.UInt32(index)
        else:
            index = gen.integers(mi.UInt32, n, 0, rays.size)
        draws = {'index': index, 'seed': gen.integers(mi.UInt32, n, 0, 2 ** 32 - 1),
                 'sparsity': self.sparsity.draw(gen, n, fields, progress)}
        if self.transients is not None:
            self._transient_tiles = self.transients.tiles(index.numpy(), rays.factor)
            draws['weight'] = mi.Float(self.transients.weights(self._transient_tiles, progress))
        dr.eval(draws)
        refine = (self.model.poses is not None
                  and progress >= self.cfg.optimizer.poses_start)
        phase = dict(refine=refine,
                     shapes=tuple(tuple(self.opt[k].shape) for k in self.opt.keys()))
        return {'opt': self.opt, 'draws': draws, 'phase': phase, 'rays': rays.arrays(),
                'occupancy': {k: g.density for k, g in self.model.occupancy.items()},
                'slots': [field.sparse.bricks[i].slots
                          for _, field, i in sparse_levels(self.model)],
                'non_finite': dr.opaque(mi.UInt32, 0, 1),     # set by the step's guard
                # Coarse to fine while poses are refined (:func:`~mi_nerfpp.core.poses.blur`):
                # a value, not a Python number, so that the frozen step is not recorded anew.
                'blur': dr.opaque(mi.Float, poses.blur(progress, self.cfg.optimizer.poses_blur))
                if self.model.poses is not None else None}

    def _forward_backward(self, inputs):
        """Loss, gradients and the Adam update of one step from :meth:`_step_inputs` alone
        (recorded once and replayed when ``freeze`` is on). Returns ``(loss, fine-pass MSE,
        loss terms, per-ray errors)`` as Dr.Jit arrays."""
        model, opt, draws = self.model, inputs['opt'], inputs['draws']
        # -------- The rays of this step and their pixels (dataset -> rays)
        bank = RayBank.from_arrays(inputs['rays'])
        index = draws['index']
        rays, gt = bank.batch(index, footprint=model.antialias)
        rays.seed = draws['seed']
        if rays.footprint is not None and inputs['blur'] is not None:
            rays.footprint = dr.maximum(rays.footprint, inputs['blur'])
        # -------- The model as this step sees it: the optimizer's parameters, the occupancy
        # grids and sparse bricks of the inputs (the model's own are left untouched)
        occupancy = {}
        for k, grid in model.occupancy.items():
            occupancy[k] = copy.copy(grid)
            occupancy[k].density = inputs['occupancy'][k]
        optim.write_back(opt, model, detach=False)
        for (_, field, i), slots in zip(sparse_levels(model), inputs['slots']):
            field.sparse.bricks[i].slots = slots
        refine = inputs['phase']['refine']
        if model.poses is not None:    # the rays of the corrected cameras (:mod:`.poses`)
            params = opt['poses'] if refine else dr.detach(opt['poses'])
            rays.o, rays.d = poses.correct_rays(params, rays.image, rays.o, rays.d)
        if model.embedding is not None:     # each ray's photo's code (:mod:`.appearance`)
            model.set_appearance(app.codes(opt['embedding'], rays.image))
        # -------- Samples, fields, quadrature and Eq. 4 (the integrator's code)
        res = render_rays(rays, *model.radiance_fields(), model.sampling,
                          RenderOptions(occupancy=occupancy, ray_gradients=refine,
                                        near_gradient=self.near_gradient))
        # -------- The loss: named terms, summed
        terms, fine, per_ray = self._loss_terms(res, rays, gt, bank.mask(
            index, least=self.masks == 'ignore') if self.masks != 'none' else None, inputs)
        loss = None
        for term in terms.values():
            loss = term if loss is None else loss + term
        with stage('losses and reverse pass'):
            dr.backward(loss)
        with stage('adam'):
            opt.step(eval=False)
            flag_non_finite(opt, inputs['non_finite'])
            dr.eval()
        return loss, fine, terms, per_ray

    def _loss_terms(self, res, rays, gt, mask, inputs):
        """The step's loss as named, weighted terms (``colour``, and where they apply
        ``silhouette``, ``appearance``, ``embedding``, ``distortion``, ``sparsity``), the
        fine pass's MSE (for the PSNR shown while training) and per ray the squared error and
        the luminances (for the error map and the capture's signs)."""
        cfg, model, opt = self.cfg.losses, self.model, inputs['opt']
        # Radiance is linear; the loss compares it in the encoding of the images, after the
        # image's colour transform when appearance is learned.
        encode = model.loss_encoding
        if model.appearance is not None:
            params = opt['appearance']
            encode = lambda c, e=encode: e(app.transform_rays(params, rays.image, c))  # noqa: E731
        pred = encode(res.composite.rgb)
        # Masks: the pixels kept in the colour loss (ignore), or the object's silhouette;
        # transients (:mod:`.transients`): each ray's weight.
        kept = mask if self.masks == 'ignore' else None
        weight = inputs['draws'].get('weight')
        if weight is not None:
            kept = weight if kept is None else kept * weight
        terms = {'color': optim.COLOR_LOSS_WEIGHT
                 * optim.COLOR_LOSSES[cfg.color_loss](pred, gt, kept)}
        if self.masks == 'object':
            terms['silhouette'] = cfg.mask_weight * optim.silhouette_loss(res.fg.shading.opacity,
                                                                          mask)
        if model.appearance is not None and cfg.appearance_prior > 0:
            terms['appearance'] = cfg.appearance_prior * app.prior(opt['appearance'])
        if model.embedding is not None and cfg.appearance_prior > 0:
            terms['embedding'] = cfg.appearance_prior * app.prior(opt['embedding'])
        if cfg.distortion > 0:
            terms['distortion'] = cfg.distortion * dr.mean(priors.ray_distortion(res))
        points = inputs['draws']['sparsity']
        if any(u is not None for u in points):
            terms['sparsity'] = self.sparsity.loss((model.fg, model.bg), points)
        fine = dr.detach(optim.mse(pred, gt, kept))
        error = optim.squared_error(pred, gt)
        if self.masks == 'ignore':
            error = error * mask
        per_ray = (dr.detach(error), dr.detach(optim.luminance(pred)),
                   dr.detach(optim.luminance(gt)))
        if self.transients is not None:      # each ray's distance, for its tile's point
            c = res.composite
            per_ray += (dr.detach(c.depth / dr.maximum(c.opacity, 1e-6)),)
        return terms, fine, per_ray

    def data_summary(self):
        """What a checkpoint records of its training data, to refuse resuming on other data."""
        return {'dataset': os.path.abspath(self.dataset.root), 'train_views': len(self.train),
                'training_rays': self.rays.size}

    def parameters_finite(self) -> bool:
        """Whether every parameter (and its Adam moments) stayed finite in the last step: a
        flag the step sets in the kernel of its Adam update (:func:`flag_non_finite`), so the
        guard costs no pass over the parameters."""
        flag = self._non_finite
        return flag is None or int(flag.array[0]) == 0

    def _kept(self):
        """What is on disk of this run, in words (for the messages of a stopped run)."""
        if self.saved_iteration is None:
            return 'nothing was saved before'
        return (f'the last good checkpoint ({self.checkpoint_path}, iteration '
                f'{self.saved_iteration}) is kept')

    def _diverged(self, what):
        """The :class:`TrainingError` of a run whose state stopped being finite."""
        again = ('train again' if self.saved_iteration is None else
                 'resume with --resume')
        return TrainingError(f'{what} at iteration {self.iteration}; stopping before it is '
                             f'used or saved: {self._kept()}. {self.cfg.divergence_hint()}, '
                             f'then {again}')

    def save(self):
        """Write the checkpoint atomically. A failed write (disk full, read-only) raises
        :class:`TrainingError` at once, and so does state that is not finite (NaN or inf
        parameters or optimizer moments, which :func:`save_checkpoint` refuses): the previous
        checkpoint stays as it was."""
        optim.write_back(self.opt, self.model)
        meta = {'iteration': self.iteration, 'elapsed': self.elapsed,
                'rng': self.rng.bit_generator.state, 'history': self.history,
                'config': self.cfg.to_dict(), 'dataset': self.dataset.root,
                'data': self.data_summary()}
        try:
            state = optim.adam_state(self.opt)
            if self.error_map is not None:
                state.update(self.error_map.state())
            if self.transients is not None:
                state.update(self.transients.state())
            state.update(self.signs.state())
            save_checkpoint(self.checkpoint_path, self.model, meta=meta, state=state)
        except NonFiniteStateError as e:
            raise self._diverged(f'{e}, so the checkpoint was not written') from None
        except OSError as e:
            kept = ('nothing was saved before' if self.saved_iteration is None else
                    f'the previous checkpoint (iteration {self.saved_iteration}) is intact')
            raise TrainingError(f'cannot save the checkpoint {self.checkpoint_path} at iteration '
                                f'{self.iteration}: {e.strerror or e}; {kept}. Free space or '
                                f'choose a writable --out, then --resume') from e
        self.saved_iteration = self.iteration

    def done(self):
        schedule = self.cfg.schedule
        return ((schedule.iterations is not None and self.iteration >= schedule.iterations)
                or (schedule.minutes is not None and self.elapsed >= 60.0 * schedule.minutes))

    def run(self, on_step=None, on_preview=None):
        """Train until done; checkpoints periodically, on Ctrl-C and at the end.

        ``on_step(trainer, loss, psnr)`` is called after every step; ``on_preview(trainer)``
        every ``preview_every`` iterations. Raises :class:`TrainingError` on a non-finite
        loss or parameters (checked after every step, before they are used or saved),
        leaving the last good checkpoint in place. Returns False if interrupted: SIGINT
        (Ctrl-C) and SIGTERM (a scheduler's) stop training and save the checkpoint, also in a
        process that was started with SIGINT ignored (a background job of a script, which
        Python leaves deaf to SIGINT), since their handlers are set here.
        """
        with _stop_signals(_in_main_thread()):
            return self._run(on_step, on_preview)

    def _run(self, on_step, on_preview):
        try:
            while not self.done():
                t0 = time.perf_counter()
                loss, fine = self.step()
                self.elapsed += time.perf_counter() - t0
                if not math.isfinite(loss):
                    raise self._diverged(f'the loss became {loss}')
                if not self.parameters_finite():
                    raise self._diverged('the parameters became NaN or infinite (the loss '
                                         'was still finite)')
                p = psnr_from_mse(fine)
                if self.iteration % 10 == 0 or self.iteration == 1:
                    # (iteration, seconds, loss, PSNR of the batch, the loss's terms)
                    self.history.append([self.iteration, round(self.elapsed, 3), loss, p,
                                         {k: float(v.array[0]) for k, v in self.terms.items()}])
                if on_step:
                    on_step(self, loss, p)
                output = self.cfg.output
                if output.checkpoint_every and self.iteration % output.checkpoint_every == 0:
                    self.save()
                if on_preview and output.preview_every and \
                        self.iteration % output.preview_every == 0:
                    on_preview(self)
        except (KeyboardInterrupt, RuntimeError) as e:
            # Also one that lands in Python code Dr.Jit calls from on_step or on_preview (a
            # preview's loop body), which arrives wrapped.
            if interrupt_in(e) is None:
                raise
            with _signals_deferred(_in_main_thread()):    # a second Ctrl-C must not
                self.save()                               # break the save
            return False
        self.save()
        return True

    def samples_per_second(self):
        """Field evaluations per second of training so far (coarse + fine, both volumes)."""
        return samples_per_second(self.cfg, self.iteration, self.elapsed)


@contextlib.contextmanager
def _step_settings(llvm: bool, big: bool):
    """Dr.Jit's settings while a step runs (and is recorded): no cyclic garbage collection
    (releasing a collected array that maps NumPy memory cannot be recorded, :mod:`.arrays`);
    on LLVM the scatter reductions measured there (:data:`GRADIENT_LOCAL_REDUCTION`, and with
    ``big`` steps :data:`GRADIENT_EXPAND_THRESHOLD`). All restored after."""
    collecting = gc.isenabled()
    gc.disable()
    if llvm:
        threshold = dr.expand_threshold()
        local = dr.flag(dr.JitFlag.ScatterReduceLocal)
        dr.set_flag(dr.JitFlag.ScatterReduceLocal, GRADIENT_LOCAL_REDUCTION)
        if big:
            dr.set_expand_threshold(GRADIENT_EXPAND_THRESHOLD)
    try:
        yield
    finally:
        if llvm:
            dr.set_expand_threshold(threshold)
            dr.set_flag(dr.JitFlag.ScatterReduceLocal, local)
        if collecting:
            gc.enable()


def _in_main_thread():
    return threading.current_thread() is threading.main_thread()


def flag_non_finite(opt, flag):
    """Set ``flag`` (UInt32 of one entry) to 1 where a parameter of ``opt`` or one of its
    Adam moments is NaN or infinite after a step taken with ``opt.step(eval=False)``: a
    masked scatter that never runs in a healthy step, fused into the kernel of the update
    (the next ``dr.eval()``), so the guard reads no parameter again. Each parameter scatters
    into a flag of its own: scatters of kernels of different sizes into one array would
    order them, and split the updates from their checks."""
    flags = []
    for value, _, _, extra in opt.state.values():
        finite = dr.isfinite(dr.detach(value).array)
        for moment in (extra[1], extra[2]) if isinstance(extra, tuple) and len(extra) > 2 \
                else ():
            finite &= dr.isfinite(moment)
        own = dr.zeros(mi.UInt32, 1)
        dr.scatter(own, mi.UInt32(1), mi.UInt32(0), active=~finite)
        flags.append(own)
    if flags:
        dr.scatter(flag, mi.UInt32(1), mi.UInt32(0), active=sum(flags[1:], flags[0]) > 0)


@contextlib.contextmanager
def _stop_signals(enabled):
    """SIGINT and SIGTERM raise :class:`KeyboardInterrupt` inside (main thread only), their
    previous handlers restored after. Set here rather than inherited: Python installs no
    SIGINT handler in a process started with SIGINT ignored (``cmd &`` in a script), where
    a SIGINT would otherwise go unanswered."""
    if not enabled:
        yield
        return
    saved = {sig: signal.signal(sig, _raise_interrupt) for sig in (signal.SIGINT,
                                                                    signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)


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
    _start.note_stop(signum)
    raise KeyboardInterrupt(f'signal {signum}')


def _words(value) -> str:
    """An option's value as command-line words."""
    return ' '.join(f'{v:g}' for v in value) if isinstance(value, tuple) else str(value)


def data_conflicts(stored: dict, now: dict) -> list[str]:
    """How the training data of a checkpoint (:meth:`Trainer.data_summary`) differs from now."""
    names = {'dataset': 'dataset', 'train_views': 'training views',
             'training_rays': 'training rays (images, sizes or --downscale)'}
    return [f'{names[k]}: the checkpoint was trained on {stored[k]!r}, this run has {now[k]!r}'
            for k in names if k in stored and stored[k] != now[k]]


def samples_per_second(cfg, iterations, seconds):
    rays = iterations * cfg.schedule.batch_rays
    return rays * cfg.samples_per_ray / seconds if seconds > 0 else 0.0
