"""Fitting the foreground and background volumes to posed images (Dr.Jit AD on the CPU).

One training step: draw a batch of random rays across all training images, render
them with :func:`mi_nerfpp.render.render_rays` (the same code the integrator uses),
take the squared error of the coarse and the fine composite against the pixels,
back-propagate with Dr.Jit and take an Adam step (``drjit.opt``). Learning rates
decay exponentially to ``lr_final`` times their start over the run.

The run directory holds ``model.npz`` (the latest checkpoint, written atomically with
the optimizer and RNG state, so ``resume=True`` continues exactly), ``preview/``,
``history.json`` and, at the end, the evaluation outputs.
"""
from __future__ import annotations

import dataclasses
import math
import os
import time
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .checkpoint import load_checkpoint, save_checkpoint
from .data import apply_normalization, pixel_rays
from .model import NeRFPPModel, default_field_config
from .render import Sampling, distortion, render_rays

# NeRF baseline (paper §5): cameras scaled into radius 1/8 instead of NeRF++'s 1/1.1.
NERF_CAMERA_RADIUS = 1.0 / 8.0
NERFPP_CAMERA_RADIUS = 1.0 / 1.1


class TrainingError(RuntimeError):
    """Training cannot go on (diverged, or a resume that does not match)."""


@dataclass
class TrainConfig:
    """Options of a training run (the ``optimize`` command line)."""
    iterations: int | None = None        # stop after this many steps ...
    minutes: float | None = None         # ... or after this wall time (whichever comes first)
    model: str = 'nerfpp'                # 'nerfpp', or 'nerf': one bounded volume
    field: str = 'grid'                  # 'grid', 'nerf' (NeRF-MLP), 'vanilla'
    bg_field: str | None = None          # background field kind (None: same as ``field``)
    batch_rays: int = 512
    fg_samples: int = 32
    bg_samples: int = 32
    fine_samples: int = 32
    lr_grid: float = 0.1
    lr_mlp: float = 5e-3
    lr_final: float = 0.1                # learning rates decay to lr * lr_final
    distortion: float = 0.0              # weight of the mip-NeRF 360 distortion loss (0: off)
    grid_levels: tuple = (32, 128)       # grid field: resolution of each level
    grid_channels: int = 4
    dir_octaves: int = 4                 # grid field: γ^L of the view direction in the colour MLP
    color_layers: int = 1                # grid field: hidden layers of the colour MLP ...
    color_width: int = 32                # ... and their width
    seed: int = 0
    checkpoint_every: int = 500          # iterations
    preview_every: int = 500             # iterations (0: never)
    downscale: int = 1                   # how the dataset was loaded (recorded for evaluate)
    background: tuple = (1.0, 1.0, 1.0)

    def __post_init__(self):
        if self.model not in ('nerfpp', 'nerf'):
            raise ValueError(f"model must be 'nerfpp' or 'nerf', not '{self.model}'")
        if self.iterations is None and self.minutes is None:
            self.iterations = 2000
        for name in ('batch_rays', 'fg_samples', 'bg_samples', 'color_layers', 'color_width'):
            if getattr(self, name) < 1:
                raise ValueError(f'{name} must be >= 1')
        if self.bg_field is None:
            self.bg_field = self.field

    def field_config(self, kind, domain):
        """The field config of one volume: the grid options apply to grid fields only."""
        if kind != 'grid':
            return default_field_config(kind, domain)
        return dict(kind='grid', domain=domain, resolutions=list(self.grid_levels),
                    channels=self.grid_channels, dir_octaves=self.dir_octaves,
                    color_layers=self.color_layers, hidden=self.color_width)

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


class RayBank:
    """Every pixel ray of a split (model frame) and its colour, as Dr.Jit arrays."""

    def __init__(self, split):
        if len(split) == 0:
            raise TrainingError('the training split is empty')
        o, d, c = [], [], []
        for cam, img in zip(split.cameras, split.images):
            h, w = img.shape[:2]
            py, px = np.mgrid[0:h, 0:w] + 0.5
            oi, di = pixel_rays(cam, px, py)
            o.append(oi)
            d.append(di)
            c.append(img.reshape(-1, 3))
        o, d, c = (np.concatenate(a).astype(np.float32) for a in (o, d, c))
        self.size = len(c)
        self.o = mi.Point3f(*[mi.Float(o[:, i]) for i in range(3)])
        self.d = mi.Vector3f(*[mi.Float(d[:, i]) for i in range(3)])
        self.rgb = mi.Color3f(*[mi.Float(c[:, i]) for i in range(3)])
        dr.eval(self.o, self.d, self.rgb)

    def batch(self, index):
        i = mi.UInt32(index)
        return (dr.gather(mi.Point3f, self.o, i), dr.gather(mi.Vector3f, self.d, i),
                dr.gather(mi.Color3f, self.rgb, i))


def to_model_frame(split, factor):
    """Cameras scaled about the origin by ``factor`` (1 for NeRF++)."""
    if factor == 1.0:
        return split
    cams = [apply_normalization(c, np.zeros(3), factor) for c in split.cameras]
    return dataclasses.replace(split, cameras=cams)


def mse(a, b):
    return dr.mean(dr.square(a.x - b.x) + dr.square(a.y - b.y) + dr.square(a.z - b.z)) / 3.0


def psnr_from_mse(m):
    return -10.0 * math.log10(m) if m > 0 else float('inf')


class Trainer:
    """Owns the model, the optimizer, the ray bank and the run directory."""

    def __init__(self, dataset, out_dir, config: TrainConfig, resume=False):
        self.dataset, self.out, self.cfg = dataset, out_dir, config
        os.makedirs(out_dir, exist_ok=True)
        self.checkpoint_path = os.path.join(out_dir, 'model.npz')
        self.frame_factor = (NERF_CAMERA_RADIUS / NERFPP_CAMERA_RADIUS
                             if config.model == 'nerf' else 1.0)
        self.train = to_model_frame(dataset.train, self.frame_factor)
        self.validation = to_model_frame(dataset.validation, self.frame_factor)
        self.test = to_model_frame(dataset.test, self.frame_factor)
        self.rays = RayBank(self.train)
        self.iteration, self.elapsed, self.history = 0, 0.0, []

        meta, state = {}, {}
        if resume and os.path.exists(self.checkpoint_path):
            self.model, meta, state = load_checkpoint(self.checkpoint_path)
            if meta.get('config', {}).get('model') != config.model:
                raise TrainingError(f"{self.checkpoint_path} was trained with --model "
                                    f"{meta.get('config', {}).get('model')}, not {config.model}")
            self.iteration = int(meta['iteration'])
            self.elapsed = float(meta['elapsed'])
            self.history = meta.get('history', [])
        elif resume:
            raise TrainingError(f'--resume: no checkpoint at {self.checkpoint_path}')
        else:
            self.model = NeRFPPModel.create(
                background=config.model == 'nerfpp', seed=config.seed,
                center=dataset.center, scale=dataset.scale * self.frame_factor,
                color_space=dataset.color_space,
                fg_config=config.field_config(config.field, 'ball'),
                bg_config=config.field_config(config.bg_field, 'inverted_sphere'))
        self.rng = np.random.default_rng(config.seed)
        if 'rng' in meta:
            self.rng.bit_generator.state = meta['rng']

        self.opt = dr.opt.Adam(lr=config.lr_mlp)
        for k, v in self.model.parameters().items():
            self.opt[k] = v
        self._restore_optimizer(state)

    # ------------------------------------------------------------------ optimizer state
    def _is_grid(self, key):
        return '.grid' in key

    def _set_learning_rates(self, progress):
        decay = self.cfg.lr_final ** min(max(progress, 0.0), 1.0)
        self.opt.set_learning_rate({k: (self.cfg.lr_grid if self._is_grid(k) else self.cfg.lr_mlp)
                                    * decay for k in self.opt.keys()})

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
            self.opt.state[k] = (value, promoted, lr,
                                 (mi.UInt32(state[f'adam.t/{k}']), mi.Float(state[f'adam.m/{k}']),
                                  mi.Float(state[f'adam.v/{k}']), None))

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
        """One optimization step. Returns ``(loss, fine-pass MSE)`` as Python floats."""
        cfg = self.cfg
        self._set_learning_rates(self.progress())
        index = self.rng.integers(0, self.rays.size, cfg.batch_rays)
        seed = mi.UInt32(self.rng.integers(0, 2 ** 32, cfg.batch_rays, dtype=np.uint64)
                         .astype(np.uint32))
        o, d, gt = self.rays.batch(index)
        self.model.set_parameters({k: self.opt[k] for k in self.opt.keys()})
        res = render_rays(o, d, self.model.fg, self.model.bg, cfg.sampling, seed=seed)
        fine = mse(res.fine.rgb, gt)
        loss = fine + mse(res.coarse.rgb, gt)
        if cfg.distortion > 0:
            for vol in (res.fg, res.bg):
                if vol is not None:
                    loss += cfg.distortion * dr.mean(distortion(vol.weights, vol.position, vol.n))
        dr.backward(loss)
        self.opt.step()
        self.iteration += 1
        return float(loss.array[0]), float(fine.array[0])

    def save(self):
        self.model.set_parameters({k: dr.detach(self.opt[k]) for k in self.opt.keys()})
        meta = {'iteration': self.iteration, 'elapsed': self.elapsed,
                'rng': self.rng.bit_generator.state, 'history': self.history,
                'config': dataclasses.asdict(self.cfg), 'dataset': self.dataset.root}
        save_checkpoint(self.checkpoint_path, self.model, meta=meta,
                        state=self._optimizer_state())

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
            self.save()
            return False
        self.save()
        return True

    def samples_per_second(self):
        """Field evaluations per second of training so far (coarse + fine, both volumes)."""
        return samples_per_second(self.cfg, self.iteration, self.elapsed)


def samples_per_second(cfg, iterations, seconds):
    return iterations * cfg.batch_rays * cfg.samples_per_ray / seconds if seconds > 0 else 0.0


def open_run(run_dir):
    """A finished or interrupted run: ``(model, meta, config, dataset)``.

    The dataset is re-read from where the run found it, with the same options; the
    returned splits are in the model's frame.
    """
    from .data import load_dataset
    model, meta, _ = load_checkpoint(os.path.join(run_dir, 'model.npz'))
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    cfg = TrainConfig(**{k: v for k, v in meta.get('config', {}).items() if k in fields})
    cfg.background = tuple(cfg.background)
    root = meta.get('dataset')
    if not root or not os.path.exists(root):
        raise TrainingError(f'{run_dir}/model.npz: its dataset {root!r} is not there any more')
    dataset = load_dataset(root, downscale=cfg.downscale, background=cfg.background)
    factor = NERF_CAMERA_RADIUS / NERFPP_CAMERA_RADIUS if cfg.model == 'nerf' else 1.0
    dataset = dataclasses.replace(dataset, **{name: to_model_frame(getattr(dataset, name), factor)
                                              for name in ('train', 'validation', 'test')})
    return model, meta, cfg, dataset

