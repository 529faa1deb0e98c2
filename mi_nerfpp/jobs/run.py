"""One training run, as a library: inputs -> train -> evaluate -> report.

    from mi_nerfpp.jobs import run
    from mi_nerfpp.training.config import TrainConfig

    result = run.optimize('data/garden', TrainConfig.from_options(minutes=5), 'runs/garden')
    print(result.metrics['test']['psnr'])

The steps, each usable on its own:

* :func:`prepare`: the inputs - a dataset folder (or a folder of photos, posed by structure
  from motion into ``OUT/sfm`` first), the :class:`~mi_nerfpp.training.config.TrainConfig` (its
  automatic downscale resolved) and the run folder, checked before any work;
  :func:`default_job` is the embedded default (the default capture, its time budget);
* :func:`start`: the :class:`~mi_nerfpp.training.train.Trainer`, new or resumed from ``OUT/model.npz``;
* :func:`train`: training with held-out previews (``OUT/preview/``) and the evaluations at
  the config's ``eval_at`` minutes (``OUT/test_at_<m>min/``);
* :func:`report`: the held-out evaluation (``OUT/test/``), ``metrics.json``, ``render.xml``
  and the plot ``training.png``.

Nothing here prints: progress is reported to a :class:`RunObserver` (the ``optimize``
command's shows a progress bar, a sweep's :class:`LogObserver` writes a log), and
:func:`summary` words the outcome for whoever shows it. Errors are raised: bad input as
ValueError / :class:`~mi_nerfpp.data.DatasetError`, a diverged or mismatched run as
:class:`~mi_nerfpp.training.train.TrainingError`, an unwritable place as OSError.

:func:`open_run` reopens a run folder (its model, config and dataset) and
:func:`evaluate_run` evaluates it again.
"""
from __future__ import annotations

import contextlib
import dataclasses
import os
import shlex
import shutil
import time
from dataclasses import dataclass, field

import matplotlib
import matplotlib.pyplot as plt
import numpy as np

from mi_nerfpp.core import budget
from mi_nerfpp.data import (AutoDownscale, DatasetError, detect_format,
                            load_dataset)
from mi_nerfpp.data import video
from mi_nerfpp.data.sfm import is_photo_folder, run_sfm, run_sfm_on_videos, video_inputs
from mi_nerfpp.data.synth import default_capture
from mi_nerfpp.files.atomic import (LOCK_NAME, check_not_a_file,
                                    check_writable_folder, lock_folder)
from mi_nerfpp.files.checkpoint import load_checkpoint, progress, read_meta
from mi_nerfpp.files.preview import write_linear_png
from mi_nerfpp.output.views import ViewRenderer, rgb
from mi_nerfpp.training import choices
from mi_nerfpp.training.config import (DEFAULT_JOB_EVAL_AT, DEFAULT_JOB_MINUTES, TrainConfig,
                                       stored_config)
from mi_nerfpp.training.evaluate import (choose_coverage_fill, evaluate_split, finish_run,
                                         matte_warning)
from mi_nerfpp.training.optim import COLOR_LOSS_NAMES
from mi_nerfpp.training.pose_check import check_outliers
from mi_nerfpp.training.signs import sign_lines
from mi_nerfpp.training.errors import TrainingError
from mi_nerfpp.training.train import Trainer, in_model_frame, samples_per_second


class RunObserver:
    """What a run reports as it goes; every method does nothing here (override those you
    need). ``shows_progress``: whether the steps that report their own progress (structure
    from motion, synthesizing the default capture) may print it."""

    shows_progress = False

    def notice(self, text: str):
        """Something the user should know: a choice made for them, a long step started."""

    def planned(self, plan: budget.Plan):
        """The run was sized (:func:`mi_nerfpp.core.budget.plan`), once, before any work."""

    def started(self, trainer, inputs: 'RunInputs'):
        """The trainer is ready (new, or resumed at ``trainer.iteration``)."""

    def step(self, trainer, loss: float, psnr: float):
        """A training step is done (``psnr``: of its batch)."""

    def evaluated(self, point: dict):
        """A held-out evaluation during training: ``{'minutes', 'iteration', 'psnr',
        'ssim'}`` (as recorded in metrics.json's ``progress``)."""

    def preview(self, trainer, path: str):
        """A held-out preview was written to ``path``."""

    def trained(self, trainer, finished: bool | None):
        """Training stopped: finished (True), interrupted (False) or failed (None)."""

    def track(self, iterable, desc: str = '', unit: str = 'it', leave: bool = True):
        """``iterable`` of a long step (the views of an evaluation), e.g. with a progress
        bar around it."""
        return iterable


class LogObserver(RunObserver):
    """Writes a run's progress as lines of text to ``stream`` (a sweep's ``optimize.log``):
    notices, a line every ``every`` steps, the evaluations and the end of training."""

    def __init__(self, stream, every: int = 100):
        self.stream, self.every = stream, every

    def _write(self, text):
        self.stream.write(text + '\n')
        self.stream.flush()

    def notice(self, text):
        self._write(text)

    def planned(self, plan):
        self._write(plan.describe())

    def started(self, trainer, inputs):
        self._write(dataset_line(trainer, inputs))

    def step(self, trainer, loss, psnr):
        if trainer.iteration % self.every == 0:
            self._write(f'iteration {trainer.iteration}: loss {loss:.4f}, batch PSNR '
                        f'{psnr:.2f} dB, {trainer.elapsed:.0f} s')

    def evaluated(self, point):
        self._write(evaluation_line(point))

    def trained(self, trainer, finished):
        what = {True: 'finished', False: 'interrupted', None: 'failed'}[finished]
        self._write(f'training {what} at iteration {trainer.iteration}')


@dataclass
class RunInputs:
    """What a run trains: ``data`` (the dataset folder; for photos, the one structure from
    motion wrote), its ``dataset``, the ``config``, the run folder ``out`` and the ``lock``
    this process holds on it (:func:`mi_nerfpp.files.atomic.lock_folder`)."""
    data: str
    dataset: object
    config: TrainConfig
    out: str
    lock: object = None
    created: bool = False

    def release(self):
        """Release the run folder's lock (:func:`prepare`) before this process ends; a run
        folder that :func:`prepare` created and nothing was written to is removed."""
        if self.lock is not None:
            self.lock.release()
            self.lock = None
        if self.created:
            _remove_if_unused(self.out)


@dataclass
class RunResult:
    """What :func:`optimize` did: ``finished`` (False: interrupted, the checkpoint saved),
    the held-out evaluations during training (``progress``), the ``metrics`` written (None
    when interrupted) and the wall time of training (``wall_seconds``)."""
    inputs: RunInputs
    trainer: object
    finished: bool
    progress: list = field(default_factory=list)
    metrics: dict | None = None
    wall_seconds: float = 0.0


# ---------------------------------------------------------------------------------- inputs

def default_job(options: dict, progress: bool = False) -> tuple[str, dict]:
    """The embedded default run: the default capture (synthesized and cached on first use;
    ``progress``: show it) and ``options`` (by option name, see
    :meth:`~mi_nerfpp.training.config.TrainConfig.from_options`) with, unless they set a budget,
    :data:`~mi_nerfpp.training.config.DEFAULT_JOB_MINUTES` of training and evaluations after
    :data:`~mi_nerfpp.training.config.DEFAULT_JOB_EVAL_AT` minutes (unless they set ``eval_at``)."""
    options = dict(options)
    if options.get('iterations') is None and options.get('minutes') is None:
        options['minutes'] = DEFAULT_JOB_MINUTES
        if options.get('eval_at') is None:
            options['eval_at'] = DEFAULT_JOB_EVAL_AT
    return default_capture(progress=progress), options


def prepare(data: str, config: TrainConfig, out: str | None = None, resume: bool = False,
            overwrite: bool = False, observer: RunObserver | None = None,
            plan: budget.Plan | None = None, frames: int | None = None) -> RunInputs:
    """The inputs of a run, checked before any work.

    ``data``: a dataset folder (NeRF++ layout, transforms.json, LLFF or COLMAP), a folder
    of photos without poses, or a video or folder of videos (structure from motion runs
    first, cached in ``OUT/sfm``; ``frames``: frames kept per video, None: the default count).
    ``out``: the run folder (default ``runs/<dataset name>``); one that holds a trained run
    is only continued (``resume``) or replaced (``overwrite``). What the config leaves to the
    capture is chosen and announced (in a copy of ``config``): the resolution
    (``downscale=None``: the photos' own unless they do not fit in memory,
    :func:`resolution_line`; a resumed run keeps the one it was trained at) and the budget
    (neither ``iterations`` nor ``minutes``: :func:`~mi_nerfpp.training.config.default_minutes`).

    The run folder is locked for this process (:func:`mi_nerfpp.files.atomic.lock_folder`) before
    anything is written to it: a second run into it is refused while this one lives
    (``RunInputs.lock``, released by :func:`optimize` at the end, else at exit). With
    ``overwrite`` the old run's outputs are removed once the new inputs are known to be good,
    so the folder never holds parts of two runs. A run folder that this call created is
    removed again when the inputs are refused.
    """
    observer = observer or RunObserver()
    plan = plan or budget.plan(config.sizing())
    budget.check(plan)
    observer.planned(plan)
    if not os.path.exists(data):
        raise DatasetError(f'{data}: dataset folder not found')
    name = os.path.basename(os.path.normpath(data))
    if video.is_video(data):
        name = os.path.splitext(name)[0]
    out = out or os.path.join('runs', name)
    if resume and overwrite:
        raise ValueError('--resume and --overwrite exclude each other')
    check_not_a_file(out)
    created = not os.path.exists(out)
    check_writable_folder(out, what='run folder (--out)')
    lock = None
    try:
        lock = lock_folder(out, what='run folder (--out)')
        finish_replacement(out, observer)
        check_run_folder(out, resume=resume, overwrite=overwrite)
        # Masks of people and cars keep them out of the features too; silhouettes do not.
        data = photos_to_dataset(data, os.path.join(out, 'sfm'), observer,
                                 mask_features=config.losses.masks in (None, 'ignore'),
                                 frames=frames)
        downscale = config.data.downscale
        checkpoint = os.path.join(out, 'model.npz')
        stored = (stored_config(read_meta(checkpoint), checkpoint)
                  if resume and os.path.exists(checkpoint) else {})
        unknown = TrainConfig.unknown_stored(stored)
        if unknown:     # written by another version: said, not dropped silently
            observer.notice(f'{checkpoint}: its training config has '
                            f'{", ".join(unknown)}, which this version of mi-nerfpp does not '
                            f'know: ignored (the options that shape the model are read from '
                            f'its weights)')
        if downscale is None and stored:
            # A resumed run goes on at the resolution it was trained at, whatever memory is
            # free.
            downscale = TrainConfig.stored_options(stored).get('downscale')
            if downscale is not None:
                config = dataclasses.replace(config, data=dataclasses.replace(
                    config.data, downscale=downscale))
        if downscale is None:    # the photos' own resolution, unless it does not fit in memory
            downscale = AutoDownscale(plan.images)
        dataset = load_dataset(data, downscale=downscale, background=config.data.background)
        if isinstance(downscale, AutoDownscale):
            config = dataclasses.replace(config, data=dataclasses.replace(
                config.data, downscale=dataset.downscale))
            observer.notice(resolution_line(dataset, downscale, plan))
        config = choices.from_capture(config, dataset, stored, observer.notice)
        if overwrite:
            replace_run(out)
    except BaseException:
        if lock is not None:
            lock.release()
        if created:
            _remove_if_unused(out)
        raise
    return RunInputs(data, dataset, config, out, lock, created)


# The files and folders of a trained run in its folder (``test_at_<m>min/`` too): what
# ``--overwrite`` replaces. The folder's ``sfm/`` (structure from motion of its photos, an
# input) and a sweep's ``optimize.log`` stay.
RUN_OUTPUTS = ('model.npz', 'metrics.json', 'render.xml', 'training.png', 'test', 'preview',
               'video.mp4', 'video.gif', 'video_frames', 'transients')
# The folder of what --transients weighed down, per training photo (write_transient_masks).
TRANSIENT_MASKS = 'transients'
EVALUATION_PREFIX = 'test_at_'
# Where --overwrite moves the old run's outputs before deleting them (see replace_run).
REPLACED = '.replaced'


def run_outputs(out) -> list[str]:
    """The outputs of a run that ``out`` holds (names, ``model.npz`` first)."""
    if not os.path.isdir(out):
        return []
    names = set(os.listdir(out))
    found = [n for n in RUN_OUTPUTS if n in names]
    return found + sorted(n for n in names if n.startswith(EVALUATION_PREFIX))


def replace_run(out):
    """Remove the run in ``out`` so that a new one can be trained there: its outputs are
    moved into ``OUT/.replaced/`` (each move atomic, ``model.npz`` first), then that folder
    is deleted. A replacement cut short is finished by :func:`finish_replacement`, so the
    folder never holds outputs of the old run beside a new model."""
    aside = os.path.join(out, REPLACED)
    os.makedirs(aside, exist_ok=True)
    for name in run_outputs(out):
        target = os.path.join(aside, name)
        if os.path.lexists(target):                # from a replacement cut short before
            shutil.rmtree(target) if os.path.isdir(target) else os.remove(target)
        os.rename(os.path.join(out, name), target)
    shutil.rmtree(aside)


def finish_replacement(out, observer: RunObserver | None = None):
    """Finish a replacement (:func:`replace_run`) that was cut short: without the old
    ``model.npz`` the outputs left are orphans of a replaced run and are removed too."""
    aside = os.path.join(out, REPLACED)
    if not os.path.isdir(aside):
        return
    if not os.path.exists(os.path.join(out, 'model.npz')) and run_outputs(out):
        (observer or RunObserver()).notice(
            f'{out}: finishing the replacement of an earlier run that was cut short (removing '
            f'{", ".join(run_outputs(out))})')
        replace_run(out)
    shutil.rmtree(aside, ignore_errors=True)


def _remove_if_unused(out):
    """Remove a run folder this process created and wrote nothing to but its lock file."""
    try:
        if set(os.listdir(out)) <= {LOCK_NAME}:
            with contextlib.suppress(FileNotFoundError):
                os.remove(os.path.join(out, LOCK_NAME))
            os.rmdir(out)
    except OSError:
        pass


def resolution_line(dataset, choice, plan: budget.Plan) -> str:
    """The resolution :class:`~mi_nerfpp.data.AutoDownscale` ``choice`` chose for
    ``dataset``, and why, in one line (``plan``: the run's, :func:`mi_nerfpp.core.budget.plan`)."""
    step_bytes, available = plan.total, plan.machine.available

    size = bytes_text
    cam = dataset.train.cameras[0]
    views = f'{len(dataset.train)} views of {cam.width}x{cam.height}'
    usable = f'{size(budget.USABLE_FRACTION * available)} usable of {size(available)} available'
    if choice.factor == 1:
        return (f"training at the images' own resolution, {views} (images {size(choice.used)} "
                f'+ training ~{size(step_bytes)}; {usable}; --downscale to shrink)')
    return (f'downscale {choice.factor} chosen: {views}, because at their own '
            f'{choice.size[0]}x{choice.size[1]} the images would take {size(choice.needed)} + '
            f'training ~{size(step_bytes)}, more than the {usable} (--downscale to choose)')


def bytes_text(n: float) -> str:
    """A number of bytes for people: ``'1.5 GiB'``, ``'340.2 MiB'``, ``'90.0 KiB'``."""
    for unit, scale in (('GiB', 2 ** 30), ('MiB', 2 ** 20), ('KiB', 2 ** 10)):
        if n >= scale:
            return f'{n / scale:.1f} {unit}'
    return f'{n:.0f} bytes'


def check_run_folder(out, resume, overwrite):
    """Refuse, before any work, a run folder that would mix two runs or lose one.

    A folder that holds a trained run (``model.npz``) is only continued (``--resume``) or
    replaced (``--overwrite``); one that holds outputs of a run (``metrics.json``,
    ``test/``, ...) without its model only replaced. Raises ValueError with what to do.
    """
    checkpoint = os.path.join(out, 'model.npz')
    if resume and overwrite:
        raise ValueError('--resume and --overwrite exclude each other')
    if os.path.exists(checkpoint) and not (resume or overwrite):
        raise ValueError(f'{out} already holds a trained run ({checkpoint}): continue it with '
                         f'--resume, replace it with --overwrite, or choose another --out')
    orphans = run_outputs(out)
    if orphans and not os.path.exists(checkpoint) and not overwrite:
        raise ValueError(f'{out} holds outputs of an earlier run ({", ".join(orphans)}) '
                         f'without its model.npz: remove them with --overwrite, or choose '
                         f'another --out')


def photos_to_dataset(data: str, sfm_out: str, observer: RunObserver | None = None,
                      mask_features: bool = True, frames: int | None = None) -> str:
    """``data`` if it is a dataset; for a folder of photos without poses, or a video or a
    folder of videos, the NeRF++ dataset structure from motion writes to ``sfm_out`` (run
    once, then reused; ``mask_features``: as :func:`~mi_nerfpp.data.sfm.run_sfm`; ``frames``:
    as :func:`~mi_nerfpp.data.sfm.run_sfm_on_videos`)."""
    observer = observer or RunObserver()
    videos = video_inputs(data)
    if videos:
        observer.notice(f'{data}: {len(videos)} video(s); choosing their sharpest frames and '
                        f'running structure from motion (COLMAP) into {sfm_out}')
        run_sfm_on_videos(videos, sfm_out, frames=frames, progress=observer.shows_progress,
                          mask_features=mask_features)
        return sfm_out
    if frames is not None:
        raise ValueError(f'--frames: {data} is not a video or a folder of videos')
    try:
        detect_format(data)
        return data
    except DatasetError:
        if not is_photo_folder(data):
            return data  # load_dataset reports what is wrong
    observer.notice(f'{data}: a folder of photos without poses; running structure from motion '
                    f'(COLMAP) into {sfm_out}')
    run_sfm(data, sfm_out, progress=observer.shows_progress,     # SfmError: to the caller
            mask_features=mask_features)
    return sfm_out


# ---------------------------------------------------------------------------------- training

def start(inputs: RunInputs, resume: bool = False, observer: RunObserver | None = None):
    """The :class:`~mi_nerfpp.training.train.Trainer` of the inputs: new, or (``resume``) continued
    from ``OUT/model.npz``."""
    trainer = Trainer(inputs.dataset, inputs.out, inputs.config, resume=resume)
    (observer or RunObserver()).started(trainer, inputs)
    return trainer


@dataclass
class Training:
    """The outcome of :func:`train`: ``finished`` (False: interrupted, the checkpoint saved)
    and the held-out evaluations done along the way (``progress``)."""
    finished: bool
    progress: list


def train(trainer, observer: RunObserver | None = None) -> Training:
    """Train until the budget is spent, with a held-out preview every ``preview_every``
    steps (``OUT/preview/iter_NNNNNN.png``) and a held-out evaluation after each of the
    config's ``eval_at`` minutes (``OUT/test_at_<m>min/``). Raises
    :class:`~mi_nerfpp.training.train.TrainingError` (the last good checkpoint is kept)."""

    observer = observer or RunObserver()
    cfg, out = trainer.cfg, trainer.out
    eval_at = list(cfg.output.eval_at)
    held_out = trainer.validation if len(trainer.validation) else trainer.test
    test_views = trainer.test if len(trainer.test) else trainer.validation
    previews = ViewRenderer(trainer.model) if len(held_out) else None
    progress = []

    def on_step(tr, loss, psnr):
        observer.step(tr, loss, psnr)
        while eval_at and tr.elapsed >= 60 * eval_at[0] and len(test_views):
            minute = eval_at.pop(0)
            r = evaluate_split(tr.model, test_views, os.path.join(out, f'test_at_{minute:g}min'),
                               fit_appearance=cfg.model.per_photo_appearance,
                               masks=tr.cfg.losses.masks or 'none')
            point = {'minutes': minute, 'iteration': tr.iteration, 'psnr': r['psnr'],
                     'ssim': r['ssim']}
            progress.append(point)
            observer.evaluated(point)

    def on_preview(tr):
        if previews is not None:
            path = os.path.join(out, 'preview', f'iter_{tr.iteration:06d}.png')
            write_linear_png(path, rgb(previews.render(held_out.cameras[0])))
            observer.preview(tr, path)

    finished = None
    try:
        finished = trainer.run(on_step=on_step, on_preview=on_preview)
    finally:
        observer.trained(trainer, finished)
    return Training(finished, progress)


# ---------------------------------------------------------------------------------- report

def report(trainer, progress: list, observer: RunObserver | None = None) -> dict:
    """Evaluate the held-out views (test, else validation) and write the run's files:
    ``test/`` (layered EXRs and PNGs), ``metrics.json``, ``render.xml`` and ``training.png``.
    Returns the metrics written."""
    observer = observer or RunObserver()
    held_out = trainer.test if len(trainer.test) else trainer.validation
    fill = choose_coverage_fill(trainer.model, trainer.validation, trainer.train.cameras)
    if fill is not None and not fill['kept']:
        trainer.save()                                  # the checkpoint without it
    metrics = finish_run(trainer.out, trainer.model, held_out, trainer.cfg,
                         trainer.checkpoint_path,
                         {'dataset': os.path.abspath(trainer.dataset.root),
                          'iterations': trainer.iteration,
                          'train_seconds': round(trainer.elapsed, 2),
                          'train_samples_per_second': trainer.samples_per_second(),
                          'progress': progress,
                          'sparse_allocations': trainer.allocations,
                          'coverage_fill': fill,
                          'capture_signs': capture_signs(trainer, observer),
                          **({'transients': write_transient_masks(trainer)}
                             if trainer.transients is not None else {})},
                         progress=observer.track)
    plot_training(trainer.history, metrics, trainer.cfg.losses.color_loss,
                  os.path.join(trainer.out, 'training.png'))
    return metrics


def capture_signs(trainer, observer) -> dict:
    """The run's signs about its capture (:mod:`mi_nerfpp.training.signs`), with the views
    that fit far worse than the rest checked for a wrong pose (:mod:`.pose_check`) and whether
    the run refined its poses (what the advice for a wrong one is)."""
    signs = trainer.signs.summary([os.path.basename(p) for p in trainer.train.image_paths],
                                  error_map=trainer.error_map)
    checks = check_outliers(trainer, signs, progress=observer.track)
    if checks:
        signs['pose_checks'] = checks
    if signs:
        signs['poses_refined'] = trainer.model.poses is not None
    return signs


def write_transient_masks(trainer) -> dict:
    """Write what ``--transients`` weighed down, per training photo, as
    ``RUN/transients/<photo>.png`` (white: kept, black: left out of the colour loss) and return
    ``{'share': the share of the training pixels weighed below one half, 'masks': folder}``."""
    weights = trainer.transients.masks()
    folder = os.path.join(trainer.out, TRANSIENT_MASKS)
    os.makedirs(folder, exist_ok=True)
    for path, mask in zip(trainer.train.image_paths, trainer.transients.pixel_masks(weights)):
        stem = os.path.splitext(os.path.basename(path))[0]
        write_linear_png(os.path.join(folder, stem + '.png'), np.repeat(mask[..., None], 3, 2))
    return {'share': round(trainer.transients.transient_share(weights), 4),
            'masks': TRANSIENT_MASKS + '/'}


def plot_training(history, metrics, color_loss, path):
    """``training.png``: the training loss, and the PSNR of the training batches with the
    held-out PSNR of the evaluations (metrics.json's ``progress`` and the final ``test``)
    as points, against seconds of training."""
    matplotlib.use('Agg')

    if not history:
        return
    it, t, loss, psnr = zip(*[row[:4] for row in history])     # (row[4]: the loss's terms)
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    ax[0].semilogy(t, loss)
    ax[0].set(xlabel='seconds of training',
              ylabel=f'loss ({COLOR_LOSS_NAMES[color_loss]} + priors)')
    ax[1].plot(t, psnr, label='training batches')
    points = [(60 * p['minutes'], p['psnr']) for p in metrics.get('progress', [])]
    if 'test' in metrics:
        points.append((metrics['train_seconds'], metrics['test']['psnr']))
    if points:
        ax[1].plot(*zip(*points), 'o', color='C3', label='held-out views')
    ax[1].set(xlabel='seconds of training', ylabel='PSNR (dB)')
    ax[1].legend(loc='lower right')
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ---------------------------------------------------------------------------------- a whole run

def optimize(data: str, config: TrainConfig, out: str | None = None, resume: bool = False,
             overwrite: bool = False, observer: RunObserver | None = None,
             plan: budget.Plan | None = None, frames: int | None = None) -> RunResult:
    """A whole run: :func:`prepare`, :func:`start`, :func:`train` and, when training
    finished (not interrupted), :func:`report`. ``plan``: the run's sizing, when the caller
    made it already (:func:`mi_nerfpp.core.budget.plan`; made here otherwise); ``frames``: as
    :func:`prepare`."""
    observer = observer or RunObserver()
    inputs = prepare(data, config, out, resume=resume, overwrite=overwrite, observer=observer,
                     plan=plan, frames=frames)
    try:
        trainer = start(inputs, resume=resume, observer=observer)
        t0 = time.perf_counter()
        training = train(trainer, observer)
        result = RunResult(inputs, trainer, training.finished, training.progress,
                           wall_seconds=time.perf_counter() - t0)
        if training.finished:
            result.metrics = report(trainer, training.progress, observer)
    finally:
        inputs.release()
    return result


def dataset_line(trainer, inputs: RunInputs) -> str:
    """What a run trains on, in one line."""
    ds = inputs.dataset
    return (f'dataset {inputs.data} ({ds.format}): {len(ds.train)} train / '
            f'{len(ds.validation)} validation / {len(ds.test)} test views, {trainer.rays.size} '
            f'training rays; run folder {inputs.out}')


def evaluation_line(point: dict) -> str:
    """A held-out evaluation during training, in one line."""
    return (f'after {point["minutes"]:g} min ({point["iteration"]} iterations): held-out PSNR '
            f'{point["psnr"]:.2f} dB, SSIM {point["ssim"]:.3f}')


def allocation_lines(allocations: list[dict]) -> list[str]:
    """The last allocation of each sparse level in words: how many bricks it holds of those
    its rule asked for (the foreground's occupancy grid, the background's training rays:
    :class:`~mi_nerfpp.training.schedule.SparseAllocation`)."""
    last = {a['level']: a for a in allocations}
    lines = []
    for level, a in last.items():
        capped = a['bricks'] < a['occupied']
        rule, where = (('the training rays', 'where the training rays take their colour from')
                       if level.startswith('bg.') else
                       ('the occupancy grid', 'where the occupancy grid found surfaces'))
        lines.append(f'sparse level {level}: {a["bricks"]:,} bricks ({a["entries"] / 1e6:.1f} M '
                     f'entries) ' + (f'of the {a["occupied"]:,} {rule} asked for: '
                                     f'--sparse-entries held it back' if capped else
                                     f'{where}, of {a["of"]:,}'))
    return lines


def summary(result: RunResult) -> tuple[list[str], list[str]]:
    """The outcome of a finished run in words: ``(lines, warnings)``."""
    trainer, metrics, out = result.trainer, result.metrics, result.inputs.out
    lines = [f'trained {trainer.iteration} iterations in {trainer.elapsed / 60:.1f} min '
             f'({metrics["train_samples_per_second"] / 1e6:.2f} M samples/s); '
             f'wall time {result.wall_seconds:.0f} s']
    lines += allocation_lines(metrics.get('sparse_allocations', []))
    fill = metrics.get('coverage_fill')
    if fill:
        lines.append(f'coverage fill {"kept" if fill["kept"] else "not kept"}: the validation '
                     f'views\' {fill["pixels"]:,} pixels that no two training views saw score '
                     f'{fill["psnr_fill"]:.2f} dB with it, {fill["psnr_volume"]:.2f} dB with the '
                     f'background volume')
    warnings = sign_lines(metrics.get('capture_signs') or {})
    transient = metrics.get('transients')
    if transient:
        lines.append(f'transients: {100 * transient["share"]:.1f} % of the training pixels '
                     f'weighed below one half in the colour loss (masks in '
                     f'{os.path.join(out, transient["masks"])})')
    if 'test' in metrics:
        test = metrics['test']
        lines.append(f'held-out views: PSNR {test["psnr"]:.2f} dB, SSIM {test["ssim"]:.3f} over '
                     f'{len(test["views"])} views')
        if 'psnr_neutral' in test:
            lines.append(f'  (scored NeRF-W style: each view\'s appearance fitted on its left '
                         f'half, right half scored; neutral whole views: PSNR '
                         f'{test["psnr_neutral"]:.2f} dB)')
        if 'matte_iou' in test:
            lines.append(f'  with the object masks: foreground matte IoU {test["matte_iou"]:.3f}, '
                         f'PSNR inside the masks {test["psnr_masked"]:.2f} dB')
        elif 'psnr_masked' in test:
            lines.append(f'  PSNR over the pixels the masks keep {test["psnr_masked"]:.2f} dB')
        warning = matte_warning(test)
        if warning:
            warnings.append(warning)
    written = ['model.npz', 'metrics.json', 'training.png']
    if 'test' in metrics:
        written[2:2] = ['test/*.exr|png', 'render.xml']
    if os.path.isdir(os.path.join(out, 'preview')):
        written.append('preview/')
    lines.append(f'written to {out}/: ' + ', '.join(written))
    if 'test' in metrics:
        lines.append(f'render a view: python -m mi_nerfpp render '
                     f'{shlex.quote(os.path.join(out, "render.xml"))} -o view.exr '
                     f'--preview view.png')     # quoted: a path with spaces pastes whole
    return lines, warnings


# ---------------------------------------------------------------------------------- a run folder

def open_run(run_dir):
    """A finished or interrupted run: ``(model, meta, config, splits)``.

    The dataset is re-read from where the run found it, with the same options; ``splits``
    (a dataset with ``train``, ``validation`` and ``test``) are in the model's frame.
    Raises :class:`~mi_nerfpp.training.train.TrainingError` when the dataset is not there any more.
    """
    path = os.path.join(run_dir, 'model.npz')
    model, meta, _ = load_checkpoint(path)
    cfg = TrainConfig.from_stored(stored_config(meta, path, model.config), weights=model.config)
    root = meta.get('dataset')
    if not root or not os.path.exists(root):
        raise TrainingError(f'{run_dir}/model.npz: its dataset {root!r} is not there any more')
    dataset = load_dataset(root, downscale=cfg.data.downscale, background=cfg.data.background)
    return model, meta, cfg, dataclasses.replace(dataset, **in_model_frame(dataset,
                                                                           model.normalization))


def evaluate_run(run_dir, observer: RunObserver | None = None) -> dict:
    """Evaluate a run folder's model on its held-out views again (test, else validation):
    ``test/``, ``metrics.json`` and ``render.xml`` are written anew, with the run folder
    locked (refused while a run trains there). Returns the metrics."""
    observer = observer or RunObserver()
    model, meta, cfg, dataset = open_run(run_dir)
    checkpoint = os.path.join(run_dir, 'model.npz')
    iterations, seconds = progress(meta, checkpoint)
    held_out = dataset.test if len(dataset.test) else dataset.validation
    with lock_folder(run_dir, what='run folder'):     # not while a run trains there
        return finish_run(run_dir, model, held_out, cfg, checkpoint, {
            'dataset': dataset.root, 'iterations': iterations,
            'train_seconds': round(seconds, 2),
            'train_samples_per_second': samples_per_second(cfg, iterations, seconds)},
            progress=observer.track)
