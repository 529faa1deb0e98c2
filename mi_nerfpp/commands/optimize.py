"""``python optimize.py`` / ``python -m mi_nerfpp optimize``: fit a NeRF++ to posed images.

Progress bar with loss and PSNR, a preview of a held-out view every few hundred
iterations, checkpoints that resume, and at the end held-out PSNR/SSIM
(``metrics.json``), per-view EXRs and PNGs, a ready-to-render ``render.xml`` and a
loss/PSNR-vs-time plot.

Three steps: :func:`inputs` (dataset and :class:`~mi_nerfpp.train.TrainConfig` from the
command line), :func:`train` (the :class:`~mi_nerfpp.train.Trainer` with a progress bar,
previews and evaluations along the way) and :func:`report` (held-out evaluation, files and
the summary printed).
"""
from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass

# The embedded default (no DATA): the default capture is trained for this budget and also
# evaluated after these minutes.
DEFAULT_MINUTES = 10.0
DEFAULT_EVAL_AT = (2.0, 5.0)


def add_parser(sub):
    from ..options import add_options
    from ..train import TrainConfig
    p = sub.add_parser('optimize', help='fit both volumes to a posed-image dataset',
                       description=__doc__)
    p.add_argument('data', nargs='?', help='dataset folder (NeRF++ layout, transforms.json, '
                   'LLFF or COLMAP) or a folder of photos without poses (structure from motion '
                   'runs first, cached in OUT/sfm); default: synthesize and cache the embedded '
                   f'default scene and train it for {DEFAULT_MINUTES:g} minutes')
    p.add_argument('--out', help='run folder (default: runs/<dataset name>)')
    p.add_argument('--resume', action='store_true', help='continue from OUT/model.npz')
    p.add_argument('--overwrite', action='store_true',
                   help='replace the trained run in OUT (model.npz, metrics.json, test/, ...); '
                        'without it, training into a folder that holds a run is refused')
    p.add_argument('--eval-at', type=float, nargs='*', metavar='MIN',
                   help='also evaluate the held-out views after these minutes of training '
                   '(default run: ' + ' '.join(f'{m:g}' for m in DEFAULT_EVAL_AT) +
                   '); recorded in metrics.json as "progress"')
    add_options(p, TrainConfig)
    p.set_defaults(func=run)
    return p


@dataclass
class Inputs:
    data: str
    dataset: object
    cfg: object
    out: str
    eval_at: list


def inputs(args) -> Inputs:
    """The dataset, the training config, the run folder and the evaluation times."""
    from ..data import DatasetError, load_dataset
    from ..options import values
    from ..synth import default_capture
    from ..train import TrainConfig

    options = values(args, TrainConfig)
    data, eval_at = args.data, args.eval_at
    if data is None:
        data = default_capture()
        if options['iterations'] is None and options['minutes'] is None:
            options['minutes'] = DEFAULT_MINUTES
            eval_at = list(DEFAULT_EVAL_AT) if eval_at is None else eval_at
    if not os.path.exists(data):
        raise DatasetError(f'{data}: dataset folder not found')
    cfg = TrainConfig(**options)      # validates every option (ValueError naming the flag)
    out = args.out or os.path.join('runs', os.path.basename(os.path.normpath(data)))
    check_run_folder(out, resume=args.resume, overwrite=getattr(args, 'overwrite', False))
    data = photos_to_dataset(data, os.path.join(out, 'sfm'))
    dataset = load_dataset(data, downscale=cfg.downscale, background=cfg.background)
    if cfg.downscale is None:           # chosen from the image size: announced when it shrinks
        cfg.downscale = dataset.downscale
        if cfg.downscale > 1:
            train = dataset.train.cameras[0]
            print(f'downscale {cfg.downscale} chosen from the image size: {len(dataset.train)} '
                  f'train images of {train.width}x{train.height} after it (pass --downscale to '
                  f'choose)')
    return Inputs(data, dataset, cfg, out, sorted(eval_at or []))


def check_run_folder(out, resume, overwrite):
    """Refuse, before any work, a run folder that cannot hold the run or would lose one.

    ``out`` must be a folder (or not exist yet) that can be written; a folder that holds a
    trained run (``model.npz``) is only continued (``--resume``) or replaced (``--overwrite``).
    Raises ValueError / OSError with what to do.
    """
    from ..files import check_writable_folder
    if os.path.exists(out) and not os.path.isdir(out):
        raise ValueError(f'--out {out} is an existing file, not a folder: choose another --out')
    checkpoint = os.path.join(out, 'model.npz')
    if os.path.exists(checkpoint) and not (resume or overwrite):
        raise ValueError(f'{out} already holds a trained run ({checkpoint}): continue it with '
                         f'--resume, replace it with --overwrite, or choose another --out')
    if resume and overwrite:
        raise ValueError('--resume and --overwrite exclude each other')
    check_writable_folder(out, what='run folder (--out)')


def photos_to_dataset(data: str, sfm_out: str) -> str:
    """``data`` if it is a dataset; for a folder of photos without poses, the NeRF++ dataset
    structure from motion writes to ``sfm_out`` (run once, then reused)."""
    from ..data import DatasetError, detect_format
    from ..sfm import is_photo_folder, run_sfm
    try:
        detect_format(data)
        return data
    except DatasetError:
        if not is_photo_folder(data):
            return data  # load_dataset reports what is wrong
    print(f'{data}: a folder of photos without poses; running structure from motion '
          f'(COLMAP) into {sfm_out}')
    run_sfm(data, sfm_out)       # SfmError: reported at the command boundary
    return sfm_out


def train(trainer, inp: Inputs):
    """Run ``trainer`` with a progress bar, previews and the evaluations of ``--eval-at``.

    Returns ``(finished, progress_log)``; raises :class:`~mi_nerfpp.train.TrainingError`.
    """
    from tqdm import tqdm

    from ..evaluate import evaluate_split
    from ..preview import write_linear_png
    from ..views import ViewRenderer, rgb

    cfg, out, eval_at = inp.cfg, inp.out, list(inp.eval_at)
    background = cfg.model == 'nerfpp'
    held_out = trainer.validation if len(trainer.validation) else trainer.test
    test_views = trainer.test if len(trainer.test) else trainer.validation
    by_time = cfg.iterations is None
    bar = tqdm(total=round(60 * cfg.minutes) if by_time else cfg.iterations, unit='s' if by_time
               else 'it', desc='optimize', dynamic_ncols=True, initial=round(trainer.elapsed)
               if by_time else trainer.iteration)
    progress_log = []
    previews = ViewRenderer(trainer.model, cfg.sampling, background) if len(held_out) else None

    def on_step(tr, loss, psnr):
        bar.update(round(tr.elapsed) - bar.n if by_time else 1)
        if tr.iteration % 10 == 0:
            bar.set_postfix(it=tr.iteration, loss=f'{loss:.4f}', psnr=f'{psnr:.2f}')
        while eval_at and tr.elapsed >= 60 * eval_at[0] and len(test_views):
            minute = eval_at.pop(0)
            r = evaluate_split(tr.model, test_views, os.path.join(out, f'test_at_{minute:g}min'),
                               cfg.sampling, background=background,
                               fit_appearance=cfg.appearance)
            progress_log.append({'minutes': minute, 'iteration': tr.iteration,
                                 'psnr': r['psnr'], 'ssim': r['ssim']})
            bar.write(f'after {minute:g} min ({tr.iteration} iterations): held-out PSNR '
                      f'{r["psnr"]:.2f} dB, SSIM {r["ssim"]:.3f}')

    def on_preview(tr):
        if previews is not None:
            write_linear_png(os.path.join(out, 'preview', f'iter_{tr.iteration:06d}.png'),
                             rgb(previews.render(held_out.cameras[0])))

    try:
        return trainer.run(on_step=on_step, on_preview=on_preview), progress_log
    finally:
        bar.close()


def plot_history(history, path):
    """Loss and training PSNR against wall time."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    if not history:
        return
    it, t, loss, psnr = zip(*history)
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    ax[0].semilogy(t, loss)
    ax[0].set(xlabel='seconds', ylabel='loss (coarse + fine MSE)')
    ax[1].plot(t, psnr)
    ax[1].set(xlabel='seconds', ylabel='training-batch PSNR (dB)')
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def report(trainer, inp: Inputs, progress_log, wall_seconds):
    """Evaluate the held-out views, write the run's files and print the summary."""
    from ..evaluate import finish_run, matte_warning

    out = inp.out
    metrics = finish_run(out, trainer.model, trainer.test if len(trainer.test) else
                         trainer.validation, inp.cfg, trainer.checkpoint_path,
                         {'dataset': os.path.abspath(inp.data), 'iterations': trainer.iteration,
                          'train_seconds': round(trainer.elapsed, 2),
                          'train_samples_per_second': trainer.samples_per_second(),
                          'progress': progress_log})
    plot_history(trainer.history, os.path.join(out, 'training.png'))

    print(f'\ntrained {trainer.iteration} iterations in {trainer.elapsed / 60:.1f} min '
          f'({metrics["train_samples_per_second"] / 1e6:.2f} M samples/s); '
          f'wall time {wall_seconds:.0f} s')
    if 'test' in metrics:
        print(f'held-out views: PSNR {metrics["test"]["psnr"]:.2f} dB, '
              f'SSIM {metrics["test"]["ssim"]:.3f} over {len(metrics["test"]["views"])} views')
        if 'psnr_neutral' in metrics['test']:
            print(f'  (scored NeRF-W style: each view\'s appearance fitted on its left half, '
                  f'right half scored; neutral whole views: PSNR '
                  f'{metrics["test"]["psnr_neutral"]:.2f} dB)')
        warning = matte_warning(metrics['test'])
        if warning:
            print(warning, file=sys.stderr)
    written = ['model.npz', 'metrics.json', 'training.png']
    if 'test' in metrics:
        written[2:2] = ['test/*.exr|png', 'render.xml']
    if os.path.isdir(os.path.join(out, 'preview')):
        written.append('preview/')
    print(f'written to {out}/: ' + ', '.join(written))
    if 'test' in metrics:
        print(f'render a view: python -m mi_nerfpp render {os.path.join(out, "render.xml")} '
              f'-o view.exr --preview view.png')
    return metrics


def run(args):
    from ..train import Trainer, TrainingError

    inp = inputs(args)
    trainer = Trainer(inp.dataset, inp.out, inp.cfg, resume=args.resume)
    ds = inp.dataset
    print(f'dataset {inp.data} ({ds.format}): {len(ds.train)} train / {len(ds.validation)} '
          f'validation / {len(ds.test)} test views, {trainer.rays.size} training rays; '
          f'run folder {inp.out}')
    t_start = time.perf_counter()
    try:
        finished, progress_log = train(trainer, inp)
    except TrainingError as e:
        print(f'error: {e}', file=sys.stderr)
        return 1
    if not finished:
        print(f'interrupted at iteration {trainer.iteration}: checkpoint saved to '
              f'{trainer.checkpoint_path}; continue with --resume', file=sys.stderr)
        return 130
    report(trainer, inp, progress_log, time.perf_counter() - t_start)
    return 0
