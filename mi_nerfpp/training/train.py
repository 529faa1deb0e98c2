"""Fitting the foreground and background volumes to posed images (Dr.Jit AD, CPU or GPU).

One training step: draw a batch of random rays across all training images, render
them with :func:`mi_nerfpp.core.render.render_rays` (the same code the integrator uses),
take the colour loss (Charbonnier by default, or the squared error) of the coarse and the
fine composite against the pixels (radiance is
composited in linear light; for sRGB photos the composite is sRGB-encoded before the loss,
see :meth:`~mi_nerfpp.core.model.NeRFPPModel.radiance_fields`),
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

from mi_nerfpp.core import appearance as app
from mi_nerfpp.core import bricks, poses
from mi_nerfpp.core.arrays import llvm_backend, owned
from mi_nerfpp.core.frame import reframe_cameras
from mi_nerfpp.core.model import NeRFPPModel
from mi_nerfpp.core.profiling import stage
from mi_nerfpp.core.rays import Rays
from mi_nerfpp.core.render import RenderOptions, render_rays
from mi_nerfpp.core.coverage import CoverageFill
from mi_nerfpp.data import masks
from mi_nerfpp.data.storage import MAX_STORED_BYTES
from mi_nerfpp.errors import interrupt_in
from mi_nerfpp.files.atomic import remove_stale_temporaries
from mi_nerfpp.files.checkpoint import (NonFiniteStateError, load_checkpoint,
                                        migration_notes, read_version, save_checkpoint)
from mi_nerfpp.training import optim, priors
from mi_nerfpp.training.config import RETIRED_AFTER, TrainConfig, default_minutes, per_volume
from mi_nerfpp.training.error_map import ErrorMap
from mi_nerfpp.training.signs import CaptureSigns
from mi_nerfpp.training.metrics import psnr_from_mse

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


class TrainingError(RuntimeError):
    """Training cannot go on (diverged, or a resume that does not match)."""


class RayBank:
    """The training pixels of a split as rays, built per batch from the cameras (Dr.Jit arrays).

    Ray ``index = (image · H + y) · W + x`` of a split of images of H x W pixels starts at the
    centre of camera ``image`` and goes through the centre of pixel (x, y), as
    :func:`~mi_nerfpp.data.pixel_rays` computes it (in Float64, then rounded to float32); its
    colour is the pixel's stored value (:mod:`mi_nerfpp.data.storage`) converted to float32
    as :attr:`Split.images <mi_nerfpp.data.dataset.Split.images>` converts it. The bank holds
    per image its camera (``fx, s, cx, fy, cy`` of K, the rotation and the centre, Float64)
    and the stored pixels: a training pixel costs the bytes its file stored (3 for 8 bits).

    Image pyramid (:meth:`level`): at ``factor`` F the images are H/F x W/F pixels (a
    remainder cropped, as :func:`~mi_nerfpp.data.images.downscale_image`); ray ``(image,
    y, x)`` goes through the centre of the F x F block of pixels at ``(F·x, F·y)``, as the
    camera :meth:`downscaled <mi_nerfpp.data.Camera.downscaled>` by F sees it, and its colour
    is the block's mean: a box-filtered downsample, read from the same stored pixels (no copy
    per level). :meth:`footprint` gives each ray's pixel width per unit distance at its level.

    Masks (``masks=True`` and a split with masks, :mod:`mi_nerfpp.data.masks`): one byte a
    pixel, the mask's coverage (255 where a photo has no mask); :meth:`mask` gives each ray's
    in [0, 1], at a pyramid level its block's mean or least.
    """

    def __init__(self, split, masks: bool = False):
        if len(split) == 0:
            raise TrainingError('the training split is empty')
        images = split.images
        if images.nbytes > MAX_STORED_BYTES:
            raise TrainingError(f'the training images take {images.nbytes / 2 ** 30:.1f} GiB '
                                f'as stored, more than the {MAX_STORED_BYTES / 2 ** 30:.0f} GiB '
                                f'a training step can address: choose a --downscale')
        h, w = images.stored[0].shape[:2]
        n = len(split)
        cams = split.cameras
        K = np.array([[c.K[0, 0], c.K[0, 1], c.K[0, 2], c.K[1, 1], c.K[1, 2]] for c in cams])
        R = np.array([c.c2w[:3, :3] for c in cams])
        center = np.array([c.c2w[:3, 3] for c in cams])
        # Owned copies (:mod:`.arrays`): a frozen step of another Trainer may outlive this one.
        self.cameras = tuple(owned(a.ravel(), _Float64) for a in (K, R, center))
        kind = images.dtype.name
        stored = [a.astype('<u2').view(np.uint8) if kind == 'uint16' else a
                  for a in images.stored]
        self.pixels = _owned_concatenation(stored, _STORE_TYPES[kind])
        self.masks = None
        if masks and split.masks is not None:
            full = np.full((h, w), 255, dtype=np.uint8)
            self.masks = _owned_concatenation([full if m is None else m for m in split.masks],
                                              _UInt8)
        self.layout = (n, h, w, kind, images.scale)
        self.factor = 1
        self.size = n * h * w

    def level(self, factor):
        """The same bank at pyramid level ``factor`` (a power of two; 1: the images as
        stored), sharing its arrays."""
        return RayBank.from_arrays(dict(self.arrays(), factor=int(factor)))

    def max_factor(self):
        """The coarsest pyramid factor that leaves the images at least one pixel."""
        h, w = self.layout[1:3]
        return 1 << (min(h, w).bit_length() - 1)

    def arrays(self):
        """The bank's Dr.Jit arrays and its layout and level as Python values (a frozen step
        takes them as inputs; another layout or level records the step anew)."""
        return {'cameras': self.cameras, 'pixels': self.pixels, 'masks': self.masks,
                'layout': self.layout, 'factor': self.factor}

    @classmethod
    def from_arrays(cls, arrays):
        """A bank over what :meth:`arrays` returned."""
        bank = cls.__new__(cls)
        bank.cameras, bank.pixels, bank.layout = (arrays['cameras'], arrays['pixels'],
                                                  arrays['layout'])
        bank.masks = arrays.get('masks')
        bank.factor = int(arrays.get('factor', 1))
        n, h, w = bank.layout[:3]
        if bank.factor < 1 or h // bank.factor < 1 or w // bank.factor < 1:
            raise ValueError(f'pyramid factor {bank.factor} leaves no pixel of {w}x{h} images')
        bank.size = n * (h // bank.factor) * (w // bank.factor)
        return bank

    def _pixel(self, i):
        """``(image, x, y)`` of rays ``i`` at this level (UInt32)."""
        f = self.factor
        h, w = self.layout[1] // f, self.layout[2] // f
        image = i // (h * w)
        within = i - image * (h * w)                  # the pixel (x, y) in its image
        y = within // w
        return image, within - y * w, y

    def _camera_plane(self, image, x, y):
        """``K⁻¹ [u', v', 1] = (u, v, 1)`` at the centre ``(u', v')`` of this level's pixel
        ``(x, y)`` (in the stored image's pixel units), by back substitution (K is upper
        triangular), in Float64; and ``k(j)``, the gather of entry j of each ray's K."""
        K = self.cameras[0]
        f = self.factor

        def k(j):
            return dr.gather(_Float64, K, image * 5 + j)
        v = (_Float64(y) * f + 0.5 * f - k(4)) / k(3)
        u = (_Float64(x) * f + 0.5 * f - k(1) * v - k(2)) / k(0)
        return u, v, k

    def batch(self, index, footprint: bool = False):
        """``(rays, colour)`` of the rays ``index``: :class:`~mi_nerfpp.core.rays.Rays` with their
        training ``image`` (and their :meth:`footprint` when asked), and the pixels' colour."""
        i = mi.UInt32(index)
        image, x, y = self._pixel(i)
        u, v, _ = self._camera_plane(image, x, y)
        _, R, center = self.cameras
        d = [dr.gather(_Float64, R, image * 9 + 3 * a) * u
             + dr.gather(_Float64, R, image * 9 + 3 * a + 1) * v
             + dr.gather(_Float64, R, image * 9 + 3 * a + 2) for a in range(3)]
        norm = dr.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        o = [dr.gather(_Float64, center, image * 3 + a) for a in range(3)]
        rays = Rays(mi.Point3f(*[mi.Float(c) for c in o]),
                    mi.Vector3f(*[mi.Float(c / norm) for c in d]), image=image,
                    footprint=self.footprint(index) if footprint else None)
        return rays, mi.Color3f(*self._colour(image, x, y))

    def footprint(self, index):
        """The pixel footprint of the rays ``index``: the width of their pixel at this level
        per unit distance, ``F·sqrt(cos³θ / (fx·fy))`` (the square root of the pixel's solid
        angle, θ the ray's angle to the optical axis), as
        :func:`~mi_nerfpp.core.geometry.pixel_footprint` measures it on a Mitsuba camera."""
        image, x, y = self._pixel(mi.UInt32(index))
        u, v, k = self._camera_plane(image, x, y)
        cos = dr.rsqrt(u * u + v * v + 1.0)
        return mi.Float(self.factor * dr.sqrt(cos * cos * cos / (k(0) * k(3))))

    def images(self, index):
        """The training-image index of the rays ``index`` (UInt32)."""
        return self._pixel(mi.UInt32(index))[0]

    def mask(self, index, least: bool = False):
        """The mask coverage of the rays ``index`` in [0, 1] (Float; the bank has masks): the
        mean over their pixel block at a pyramid level, or with ``least`` its least pixel's
        (a block's colour holds what any of its pixels shows)."""
        image, x, y = self._pixel(mi.UInt32(index))
        n, h, w = self.layout[:3]
        f = self.factor
        first = image * (h * w) + (y * f) * w + x * f
        total = None
        for dy in range(f):
            for dx in range(f):
                value = mi.UInt32(dr.gather(_UInt8, self.masks, first + (dy * w + dx)))
                total = value if total is None else (
                    dr.minimum(total, value) if least else total + value)
        return mi.Float(total) / (255.0 * (1 if least else f * f))

    def _colour(self, image, x, y):
        """The colour (three Floats) of this level's pixels ``(x, y)`` of ``image``: the mean
        of the stored F x F block, summed in Float64 (integers exactly) and rounded once."""
        n, h, w, kind, scale = self.layout
        f = self.factor
        first = image * (h * w) + (y * f) * w + x * f      # the block's top-left pixel
        out = []
        for c in range(3):
            total = None
            for dy in range(f):
                for dx in range(f):
                    value = self._stored(3 * (first + (dy * w + dx)) + c)
                    total = value if total is None else total + value
            if kind in ('uint8', 'uint16'):
                # In Float64, then rounded: the float32 quotient value / scale, as NumPy's.
                out.append(mi.Float(_Float64(total) / (scale * f * f)))
            else:                                   # exact for F = 1
                out.append(mi.Float(total / (f * f)))
        return out

    def _stored(self, at):
        """The stored value at flat position ``at``: UInt32 for integer stores, Float64 for
        float stores."""
        kind = self.layout[3]
        if kind == 'uint8':
            return mi.UInt32(dr.gather(_UInt8, self.pixels, at))
        if kind == 'uint16':                      # little-endian byte pairs
            return (mi.UInt32(dr.gather(_UInt8, self.pixels, 2 * at))
                    | (mi.UInt32(dr.gather(_UInt8, self.pixels, 2 * at + 1)) << 8))
        return _Float64(dr.gather(_STORE_TYPES[kind], self.pixels, at))


_Float64 = dr.float64_array_t(mi.Float)
_UInt8 = dr.uint8_array_t(mi.Float)
# The Dr.Jit array a split's stored dtype is kept in (16-bit integers as their bytes).
_STORE_TYPES = {'uint8': _UInt8, 'uint16': _UInt8, 'float16': dr.float16_array_t(mi.Float),
                'float32': mi.Float}


def _owned_concatenation(arrays, tp):
    """The NumPy ``arrays`` one after the other in one Dr.Jit array of type ``tp`` that owns its
    memory (:func:`~mi_nerfpp.core.arrays.owned`), copied one array at a time: no concatenated
    copy of them all is ever made."""
    out = dr.empty(tp, sum(a.size for a in arrays))
    offset = 0
    for a in arrays:
        src = tp(np.ascontiguousarray(a).ravel())
        dr.scatter(out, src, dr.arange(mi.UInt32, a.size) + dr.opaque(mi.UInt32, offset))
        dr.eval(out)
        dr.sync_thread()      # the copy is done before NumPy may move on
        offset += a.size
    return out


def in_model_frame(dataset, normalization):
    """The dataset's splits with their cameras moved into the model frame of ``normalization``:
    ``{'train': Split, 'validation': Split, 'test': Split}``."""
    return {name: dataclasses.replace(split, cameras=reframe_cameras(
                split.cameras, dataset.normalization, normalization))
            for name, split in (('train', dataset.train), ('validation', dataset.validation),
                                ('test', dataset.test))}


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
        self.near_gradient = (config.losses.near_gradient * normalization.scale
                              / dataset.normalization.scale)
        splits = in_model_frame(dataset, normalization)
        self.train, self.validation, self.test = (splits[k] for k in ('train', 'validation',
                                                                      'test'))
        # What the photos' masks mean (:mod:`mi_nerfpp.data.masks`); not given: ignore when
        # the photos have masks (:func:`mi_nerfpp.jobs.run.prepare` chooses and announces it).
        self.masks = config.losses.masks or (masks.DEFAULT_MEANING if self.train.masks
                                             is not None else 'none')
        if self.masks != 'none' and self.train.masks is None:
            raise TrainingError(f'--masks {self.masks}: no training photo has a mask (see '
                                f'docs/data.md, "Masks", for where masks are looked for)')
        if self.train.masks is not None:        # (a capture without masks stores none)
            self.cfg = config = config.replace(masks=self.masks)
        self.rays = RayBank(self.train, masks=True) if self.masks != 'none' else RayBank(self.train)
        if config.schedule.iterations is None and config.schedule.minutes is None:
            # No budget given (:func:`mi_nerfpp.jobs.run.prepare` chooses and announces it first).
            self.cfg = config = config.replace(minutes=default_minutes(self.rays.size))
        self.iteration, self.elapsed, self.history = 0, 0.0, []

        meta, state = {}, {}
        if resume and os.path.exists(self.checkpoint_path):
            self.model, meta, state = load_checkpoint(self.checkpoint_path)
            stored = meta.get('config', {})
            retired = config.retired_in(stored, self.model.config)
            if retired:
                raise TrainingError(
                    f'{self.checkpoint_path} was trained with {", ".join(retired)}, which this '
                    f'version no longer has (measured and not kept: docs/experiments.md): resume '
                    f'it with mi-nerfpp at commit {RETIRED_AFTER} or before, or evaluate and '
                    f'render it as it is')
            model_conflicts = config.resume_conflicts(stored, self.model.config)
            conflicts = model_conflicts + data_conflicts(meta.get('data', {}),
                                                         self.data_summary())
            if conflicts:       # why an older file's weights differ from today's defaults
                version = read_version(self.checkpoint_path)
                why = ''.join(f'; {note} (a version {version} checkpoint)'
                              for note in migration_notes(version) if model_conflicts)
                raise TrainingError(f'{self.checkpoint_path} cannot be resumed with other model '
                                    f'options or data: ' + '; '.join(conflicts) + why)
            self.iteration = int(meta['iteration'])
            self.elapsed = float(meta['elapsed'])
            self.history = meta.get('history', [])
            self.model.sampling = config.render_sampling     # --samples may change
        elif resume:
            raise TrainingError(f'--resume: no checkpoint at {self.checkpoint_path}')
        else:
            m, s = config.model, config.sampling
            self.model = NeRFPPModel.create(
                background=m.kind == 'nerfpp', seed=config.schedule.seed,
                normalization=normalization,
                color_space=dataset.color_space,
                appearance_images=len(self.train) if m.appearance else 0,
                embedding_images=len(self.train) if m.appearance_embedding else 0,
                pose_images=len(self.train) if m.refine_poses else 0,
                fg_config=config.field_config(m.field, 'ball'),
                bg_config=config.field_config(m.bg_field, 'inverted_sphere'),
                sampling=config.render_sampling)
            if s.occupancy:
                self.model.enable_occupancy(s.occupancy_res, s.occupancy_threshold)
        if self.model.bg is not None and self.model.coverage is None:
            with stage('coverage fill'):
                self.model.coverage = CoverageFill.of_views(
                    self.train.cameras, self.train.images, dataset.color_space,
                    weights=self._background_weights())
        self.saved_iteration = self.iteration if resume else None
        # Sparse levels allocate at each ``sparse_at`` passed; a resumed run has those behind it.
        self.allocations = []
        self._brick_stage = sum(self.progress() >= f for f in config.schedule.sparse_at) \
            if any(len(g) for g in self.model.allocated_bricks().values()) else 0
        self.rng = np.random.default_rng(config.schedule.seed)
        if 'rng' in meta:
            self.rng.bit_generator.state = meta['rng']

        o = config.optimizer
        self.opt = optim.adam(self.model.parameters(), o.lr_mlp, beta_2=o.adam_beta2)
        self._restore_optimizer(state)
        # One step's kernels, recorded on the first call and replayed after (drjit.freeze):
        # tracing the step in Python took ~18 of ~76 ms (README, "Measured performance").
        self._compute = (dr.freeze(self._forward_backward) if config.schedule.freeze
                         else self._forward_backward)
        self._recorded = None       # the Python values the frozen step was recorded for
        # Where the rays go (:mod:`.error_map`); its state resumes with the run.
        if config.schedule.error_rays is None:     # not given: uniform (:mod:`.error_map`)
            self.cfg = config = config.replace(error_rays=0.0)
        s = config.schedule
        self.error_map = (ErrorMap(*self.rays.layout[:3], s.error_tile, s.error_rays)
                          if s.error_rays > 0 else None)
        if self.error_map is not None:
            self.error_map.restore(state)
        self._tiles = None          # the error map's tiles of this step's rays
        # What the run can tell about the capture (:mod:`.signs`), read at its end.
        self.signs = CaptureSigns(len(self.train))
        self.signs.restore(state)
        # The scatter-reduction settings measured on the CPU (see GRADIENT_*) apply on LLVM.
        self._llvm = llvm_backend()

    def _background_weights(self):
        """Per training image how much each pixel shows of the background (for the coverage
        fill's colours): masked-out pixels none (``--masks ignore``), the object's none
        (``--masks object``); None: all of them."""
        if self.masks == 'none':
            return None
        return [None if m is None else (m / 255.0 if self.masks == 'ignore' else 1 - m / 255.0)
                for m in self.train.masks]

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
        o = self.cfg.optimizer
        optim.set_learning_rates(self.opt, self.progress(), o.lr_grid, o.lr_mlp, o.lr_final,
                                 {'appearance': o.lr_appearance, 'embedding': o.lr_appearance,
                                  'poses': o.lr_poses})
        refresh = self.iteration % self.cfg.sampling.occupancy_every == 0
        if self.model.occupancy and refresh:
            with stage('occupancy refresh'):
                self.model.set_parameters({k: dr.detach(self.opt[k]) for k in self.opt.keys()})
                self.model.update_occupancy(int(self.rng.integers(0, 2 ** 31)))
        self._allocate_bricks()
        inputs = self._step_inputs()
        self._fresh_recording(inputs)
        # No cyclic garbage collection while a step is recorded: releasing a collected
        # array that maps NumPy memory cannot be recorded (:mod:`.arrays`).
        collecting = gc.isenabled()
        gc.disable()
        llvm = self._llvm
        if llvm:
            threshold = dr.expand_threshold()
            local = dr.flag(dr.JitFlag.ScatterReduceLocal)
            dr.set_flag(dr.JitFlag.ScatterReduceLocal, GRADIENT_LOCAL_REDUCTION)
            if self.cfg.schedule.batch_rays * self.cfg.samples_per_ray >= EXPAND_MIN_SAMPLES:
                dr.set_expand_threshold(GRADIENT_EXPAND_THRESHOLD)
        try:
            loss, fine, per_ray = self._compute(inputs)
        finally:
            self.model.set_appearance(None)     # renders outside the step: the neutral code
            if llvm:
                dr.set_expand_threshold(threshold)
                dr.set_flag(dr.JitFlag.ScatterReduceLocal, local)
            if collecting:
                gc.enable()
        self._non_finite = inputs['non_finite']   # the step's guard (see parameters_finite)
        # The model's fields read the parameters after the update (previews, evaluations);
        # a replayed frozen step runs no Python, so the step itself cannot set them.
        self.model.set_parameters({k: dr.detach(self.opt[k]) for k in self.opt.keys()})
        squared_error, predicted, photographed = (v.numpy() for v in per_ray)
        if self.error_map is not None:
            self.error_map.update(self._tiles, squared_error)
        self.signs.update(self._view_of(inputs['draws']['index']), squared_error, predicted,
                          photographed)
        self.iteration += 1
        return float(loss.array[0]), float(fine.array[0])

    def _view_of(self, index) -> np.ndarray:
        """The training view of each ray ``index`` (UInt32) of this step's ray bank level."""
        return self._level().images(index).numpy().astype(np.int64)

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

    def _step_inputs(self):
        """Everything a step reads, as :func:`drjit.freeze` traverses it: the optimizer (its
        parameters, moments and learning rates), the occupancy grids, this step's random
        draws (Dr.Jit arrays from a generator seeded by the run's RNG, so a resumed run
        draws the same), and as Python values the phase of the run (which priors apply) and
        the grids' shapes: a change of either records the step anew."""
        cfg, n, p = self.cfg.losses, self.cfg.schedule.batch_rays, self.progress()
        gen = dr.rng(seed=int(self.rng.integers(0, 2 ** 63)))
        rays = self._level()
        sparse = [field is not None and weight > 0 and p >= start
                  for field, weight, start in zip((self.model.fg, self.model.bg),
                                                  per_volume(cfg.sparsity),
                                                  per_volume(cfg.sparsity_start))]
        if self.error_map is not None:
            index, self._tiles = self.error_map.draw(self.rng, n, rays.factor)
            index = mi.UInt32(index)
        else:
            index = gen.integers(mi.UInt32, n, 0, rays.size)
        draws = {
            'index': index,
            'seed': gen.integers(mi.UInt32, n, 0, 2 ** 32 - 1),
            'sparsity': [[gen.random(mi.Float, n) for _ in range(4)] if on else None
                         for on in sparse],
        }
        dr.eval(draws)
        phase = dict(refine=self.model.poses is not None and p >= self.cfg.optimizer.poses_start,
                     shapes=tuple(tuple(self.opt[k].shape) for k in self.opt.keys()))
        return {'opt': self.opt, 'draws': draws, 'phase': phase, 'rays': rays.arrays(),
                'occupancy': {k: g.density for k, g in self.model.occupancy.items()},
                'slots': [field.bricks[i].slots for _, field, i in self._sparse_levels()],
                'non_finite': dr.opaque(mi.UInt32, 0, 1),     # set by the step's guard
                # Coarse to fine while poses are refined (:func:`~mi_nerfpp.core.poses.blur`):
                # a value, not a Python number, so that the frozen step is not recorded anew.
                'blur': dr.opaque(mi.Float, poses.blur(p, self.cfg.optimizer.poses_blur))
                if self.model.poses is not None else None}

    def _level(self):
        """The ray bank at this point of the run's image pyramid (``--pyramid``), at most as
        coarse as leaves the images a pixel."""
        factor = self.cfg.schedule.pyramid_factor(self.progress())
        if factor == 1:
            return self.rays
        return self.rays.level(min(factor, self.rays.max_factor()))

    def _forward_backward(self, inputs):
        """Loss, gradients and the Adam update of one step from :meth:`_step_inputs` alone
        (recorded once and replayed when ``freeze`` is on). Returns ``(loss, fine-pass
        MSE)`` as Dr.Jit arrays."""
        cfg, model = self.cfg.losses, self.model
        opt, draws, phase = inputs['opt'], inputs['draws'], inputs['phase']
        bank = RayBank.from_arrays(inputs['rays'])
        index = draws['index']
        # The rays and their pixels; their footprints for fields that filter lookups by them.
        rays, gt = bank.batch(index, footprint=model.antialias)
        rays.seed = draws['seed']
        if rays.footprint is not None and inputs['blur'] is not None:
            rays.footprint = dr.maximum(rays.footprint, inputs['blur'])
        occupancy = {}
        for k, grid in model.occupancy.items():       # the model's grids are left untouched
            occupancy[k] = copy.copy(grid)
            occupancy[k].density = inputs['occupancy'][k]
        model.set_parameters({k: opt[k] for k in opt.keys()})
        for (_, field, i), slots in zip(self._sparse_levels(), inputs['slots']):
            field.bricks[i].slots = slots        # (an input of the frozen step, as the grids)
        refine = phase['refine']
        if model.poses is not None:    # the rays of the corrected cameras (:mod:`.poses`)
            params = opt['poses'] if refine else dr.detach(opt['poses'])
            rays.o, rays.d = poses.correct_rays(params, rays.image, rays.o, rays.d)
        if model.embedding is not None:     # each ray's photo's code (:mod:`.appearance`)
            model.set_appearance(app.codes(opt['embedding'], rays.image))
        res = render_rays(rays, *model.radiance_fields(), model.sampling,
                          RenderOptions(occupancy=occupancy, ray_gradients=refine,
                                        near_gradient=self.near_gradient))
        # Radiance is linear; the loss compares it in the encoding of the images, after the
        # image's colour transform when appearance is learned.
        encode = model.loss_encoding
        if model.appearance is not None:
            image, params = rays.image, opt['appearance']
            encode = lambda c, e=encode: e(app.transform_rays(params, image, c))  # noqa: E731
        pred = encode(res.fine.rgb)
        # Masks: the pixels kept in the colour loss (ignore), or the object's silhouette.
        mask = (bank.mask(index, least=self.masks == 'ignore') if self.masks != 'none'
                else None)
        kept = mask if self.masks == 'ignore' else None
        loss = optim.COLOR_LOSS_WEIGHT * optim.COLOR_LOSSES[cfg.color_loss](pred, gt, kept)
        fine = dr.detach(optim.mse(pred, gt, kept))     # for the PSNR shown while training
        if self.masks == 'object':
            loss += cfg.mask_weight * optim.silhouette_loss(res.fg.fine.opacity, mask)
        # Per ray, for the error map and the capture's signs (:mod:`.signs`).
        error = optim.squared_error(pred, gt)
        per_ray = (dr.detach(error if kept is None else error * kept),
                   dr.detach(optim.luminance(pred)), dr.detach(optim.luminance(gt)))
        if model.appearance is not None and cfg.appearance_prior > 0:
            loss += cfg.appearance_prior * app.prior(opt['appearance'])
        if model.embedding is not None and cfg.appearance_prior > 0:
            loss += cfg.appearance_prior * app.prior(opt['embedding'])
        if cfg.distortion > 0:
            loss += cfg.distortion * dr.mean(priors.ray_distortion(res))
        loss += self._sparsity_loss(draws['sparsity'])
        with stage('losses and reverse pass'):
            dr.backward(loss)
        with stage('adam'):
            opt.step(eval=False)
            flag_non_finite(opt, inputs['non_finite'])
            dr.eval()
        return loss, fine, per_ray

    def _sparse_levels(self):
        """``(volume, field, level)`` of every sparse grid level of the model."""
        return [(volume, field, i) for volume, field in (('fg', self.model.fg), ('bg', self.model.bg))
                if field is not None for i in range(len(getattr(field, 'bricks', ())))]

    def _allocate_bricks(self):
        """At each ``sparse_at`` fraction of the run passed, allocate the sparse levels'
        bricks where the occupancy grid is occupied (grown by :data:`~mi_nerfpp.core.bricks.
        DILATION`), at most ``sparse_entries`` entries a level, the densest first."""
        due = sum(self.progress() >= f for f in self.cfg.schedule.sparse_at)
        if due <= self._brick_stage:
            return
        self._brick_stage = due
        for volume, field, i in self._sparse_levels():
            grid, brick = self.model.occupancy[volume], field.bricks[i]
            density = grid.numpy()
            occupied = bricks.block_mask(density > grid.threshold, brick.blocks)
            mask = bricks.dilate(occupied, bricks.DILATION[field.domain],
                                 periodic_x=field.domain == 'inverted_sphere')
            score = bricks.block_max(density, brick.blocks)
            limit = self.cfg.schedule.sparse_entries // (brick.texels_per_brick * brick.channels)
            chosen = bricks.choose(mask, score, max(limit, 1))
            key = f'{volume}.sparse{i}'
            field.set_parameters({f'sparse{i}': dr.detach(self.opt[key])})
            field.set_bricks({f'sparse{i}': chosen})
            self.opt[key] = field.params[f'sparse{i}']     # new shape: fresh Adam moments
            self.allocations.append({'iteration': self.iteration, 'level': key,
                                     'bricks': int(chosen.size), 'of': brick.n_blocks,
                                     'occupied': int(mask.sum()),
                                     'entries': int(np.prod(brick.pool_shape()))})

    def _sparsity_loss(self, points):
        """Cauchy sparsity of each volume's density at ``batch_rays`` random points, weighted
        by the volume's ``sparsity`` (``points``: 4 uniform Floats per volume, None where the
        volume is absent, its weight is 0 or the run has not reached its ``sparsity_start``)."""
        total = mi.Float(0.0)
        for field, weight, u in zip((self.model.fg, self.model.bg),
                                    per_volume(self.cfg.losses.sparsity), points):
            if u is not None:
                total += weight * priors.cauchy_sparsity(
                    field.density(priors.random_points(field.domain, u)))
        return total

    def data_summary(self):
        """What a checkpoint records of its training data, to refuse resuming on other data."""
        return {'dataset': os.path.abspath(self.dataset.root), 'train_views': len(self.train),
                'training_rays': self.rays.size}

    def parameters_finite(self) -> bool:
        """Whether every parameter (and its Adam moments) stayed finite in the last step: a
        flag the step sets in the kernel of its Adam update (:func:`flag_non_finite`), so the
        guard costs no pass over the parameters."""
        flag = getattr(self, '_non_finite', None)
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
        self.model.set_parameters({k: dr.detach(self.opt[k]) for k in self.opt.keys()})
        meta = {'iteration': self.iteration, 'elapsed': self.elapsed,
                'rng': self.rng.bit_generator.state, 'history': self.history,
                'config': self.cfg.to_dict(), 'dataset': self.dataset.root,
                'data': self.data_summary()}
        try:
            state = self._optimizer_state()
            if self.error_map is not None:
                state.update(self.error_map.state())
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
                    self.history.append([self.iteration, round(self.elapsed, 3), loss, p])
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
    raise KeyboardInterrupt(f'signal {signum}')


def data_conflicts(stored: dict, now: dict) -> list[str]:
    """How the training data of a checkpoint (:meth:`Trainer.data_summary`) differs from now."""
    names = {'dataset': 'dataset', 'train_views': 'training views',
             'training_rays': 'training rays (images, sizes or --downscale)'}
    return [f'{names[k]}: the checkpoint was trained on {stored[k]!r}, this run has {now[k]!r}'
            for k in names if k in stored and stored[k] != now[k]]


def samples_per_second(cfg, iterations, seconds):
    rays = iterations * cfg.schedule.batch_rays
    return rays * cfg.samples_per_ray / seconds if seconds > 0 else 0.0
