"""``python optimize.py`` / ``python -m mi_nerfpp optimize``: fit a NeRF++ to posed images.

Progress bar with loss and PSNR, a preview of a held-out view every few hundred
iterations, checkpoints that resume, and at the end held-out PSNR/SSIM
(``metrics.json``), per-view EXRs and PNGs, a ready-to-render ``render.xml`` and a
loss/PSNR-vs-time plot.
"""
from __future__ import annotations

import dataclasses
import os
import sys
import time

DEFAULT_SCENE = 'gt_garden.xml'
DEFAULT_CAPTURE = dict(views=60, res=(128, 96), spp=64, trajectory='orbit', seed=0)
DEFAULT_MINUTES = 10.0
DEFAULT_EVAL_AT = [2.0, 5.0]


def add_parser(sub):
    p = sub.add_parser('optimize', help='fit both volumes to a posed-image dataset',
                       description=__doc__)
    p.add_argument('data', nargs='?', help='dataset folder (NeRF++ layout, transforms.json or '
                   'LLFF); default: synthesize and cache the embedded default scene')
    p.add_argument('--out', help='run folder (default: runs/<dataset name>)')
    g = p.add_mutually_exclusive_group()
    g.add_argument('--iterations', type=int, help='training steps')
    g.add_argument('--minutes', type=float, help=f'wall-time budget (default without '
                   f'--iterations: {DEFAULT_MINUTES:g})')
    p.add_argument('--model', choices=['nerfpp', 'nerf'], default='nerfpp',
                   help="'nerf': the paper's baseline, one bounded volume (default: nerfpp)")
    p.add_argument('--field', choices=['grid', 'nerf', 'vanilla'], default='grid',
                   help='field kind of both volumes (default: grid)')
    p.add_argument('--bg-field', choices=['grid', 'nerf', 'vanilla'],
                   help='field kind of the background volume (default: as --field)')
    p.add_argument('--downscale', type=int, default=1, help='integer image downscale factor')
    p.add_argument('--batch-rays', type=int, default=512, help='rays per step (default 512)')
    p.add_argument('--samples', type=int, nargs=3, metavar=('FG', 'BG', 'FINE'),
                   default=[32, 32, 32], help='coarse fg, coarse bg and fine samples per volume')
    p.add_argument('--grid-levels', type=int, nargs='+', default=[32, 128], metavar='RES',
                   help='grid field: resolution of each level (default: 32 128)')
    p.add_argument('--grid-channels', type=int, default=4, help='grid field: channels per level')
    p.add_argument('--dir-octaves', type=int, default=4,
                   help='grid field: frequencies of the view-direction encoding (default 4)')
    p.add_argument('--color-layers', type=int, default=1,
                   help='grid field: hidden layers of the colour MLP (default 1)')
    p.add_argument('--color-width', type=int, default=32,
                   help='grid field: width of the colour MLP (default 32)')
    p.add_argument('--lr-grid', type=float, default=0.1)
    p.add_argument('--lr-mlp', type=float, default=5e-3)
    p.add_argument('--distortion', type=float, default=0.0,
                   help='weight of the mip-NeRF 360 distortion loss against floaters (default 0: '
                   'off; 0.01 measured 0.9 dB worse after 2 minutes on the default capture)')
    p.add_argument('--resume', action='store_true', help='continue from OUT/model.npz')
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--preview-every', type=int, default=500, help='iterations (0: never)')
    p.add_argument('--checkpoint-every', type=int, default=500, help='iterations')
    p.add_argument('--eval-at', type=float, nargs='*', metavar='MIN',
                   help='also evaluate the held-out views after these minutes of training '
                   '(default run: 2 5); recorded in metrics.json as "progress"')
    p.add_argument('--background', default='1,1,1',
                   help='colour that transparent (RGBA) images are composited over (default 1,1,1)')
    p.set_defaults(func=run)
    return p


def default_dataset():
    """Synthesize (once, cached) the embedded default capture and return its folder."""
    from . import synth
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    scene = os.path.join(root, 'scenes', DEFAULT_SCENE)
    out = os.path.join(root, 'data_cache', 'default')
    synth.synthesize(scene, out, **DEFAULT_CAPTURE)
    return out


def _background(text):
    try:
        values = tuple(float(v) for v in text.split(','))
    except ValueError:
        values = ()
    if len(values) != 3:
        raise SystemExit(f"--background expects three numbers like 1,1,1, got '{text}'")
    return values


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


def finish_run(out, model, held_out, cfg, checkpoint_path, metrics):
    """Evaluate the held-out views; write metrics.json (with ``metrics``) and render.xml."""
    from tqdm import tqdm

    from .evaluate import evaluate_split, world_camera, write_json
    from .scene_xml import write_render_xml

    metrics = dict(metrics, config=dataclasses.asdict(cfg))
    background = cfg.model == 'nerfpp'
    if len(held_out):
        metrics['test'] = evaluate_split(model, held_out, os.path.join(out, 'test'),
                                         cfg.sampling, background=background, progress=tqdm)
        write_render_xml(os.path.join(out, 'render.xml'), checkpoint_path,
                         world_camera(model, held_out.cameras[0]), cfg.sampling,
                         near_clip=1e-3 / model.scale, background=background)
    write_json(os.path.join(out, 'metrics.json'), metrics)
    return metrics


def run(args):
    from tqdm import tqdm

    from .data import DatasetError, load_dataset
    from .evaluate import evaluate_split, render_view, rgb
    from .preview import write_png
    from .train import TrainConfig, Trainer, TrainingError

    data = args.data
    minutes = args.minutes
    eval_at = args.eval_at
    if data is None:
        data = default_dataset()
        if args.iterations is None and minutes is None:
            minutes = DEFAULT_MINUTES
            eval_at = DEFAULT_EVAL_AT if eval_at is None else eval_at
    eval_at = sorted(eval_at or [])
    if not os.path.exists(data):
        raise SystemExit(f'{data}: dataset folder not found')
    try:
        dataset = load_dataset(data, downscale=args.downscale,
                               background=_background(args.background))
    except DatasetError as e:
        raise SystemExit(f'error: {e}') from None
    out = args.out or os.path.join('runs', os.path.basename(os.path.normpath(data)))
    fg, bg, fine = args.samples
    cfg = TrainConfig(iterations=args.iterations, minutes=minutes, model=args.model,
                      field=args.field, bg_field=args.bg_field, batch_rays=args.batch_rays, fg_samples=fg,
                      bg_samples=bg, fine_samples=fine, lr_grid=args.lr_grid,
                      lr_mlp=args.lr_mlp, distortion=args.distortion, seed=args.seed,
                      preview_every=args.preview_every, grid_levels=tuple(args.grid_levels),
                      grid_channels=args.grid_channels, dir_octaves=args.dir_octaves,
                      color_layers=args.color_layers, color_width=args.color_width,
                      checkpoint_every=args.checkpoint_every, downscale=args.downscale,
                      background=_background(args.background))
    try:
        trainer = Trainer(dataset, out, cfg, resume=args.resume)
    except TrainingError as e:
        raise SystemExit(f'error: {e}') from None
    held_out = trainer.validation if len(trainer.validation) else trainer.test
    print(f'dataset {data} ({dataset.format}): {len(dataset.train)} train / '
          f'{len(dataset.validation)} validation / {len(dataset.test)} test views, '
          f'{trainer.rays.size} training rays; run folder {out}')

    by_time = cfg.iterations is None
    bar = tqdm(total=round(60 * cfg.minutes) if by_time else cfg.iterations, unit='s' if by_time
               else 'it', desc='optimize', dynamic_ncols=True, initial=round(trainer.elapsed)
               if by_time else trainer.iteration)

    progress_log = []
    test_views = trainer.test if len(trainer.test) else trainer.validation

    def on_step(tr, loss, psnr):
        bar.update(round(tr.elapsed) - bar.n if by_time else 1)
        if tr.iteration % 10 == 0:
            bar.set_postfix(it=tr.iteration, loss=f'{loss:.4f}', psnr=f'{psnr:.2f}')
        while eval_at and tr.elapsed >= 60 * eval_at[0] and len(test_views):
            minute = eval_at.pop(0)
            r = evaluate_split(tr.model, test_views, os.path.join(out, f'test_at_{minute:g}min'),
                               cfg.sampling, background=cfg.model == 'nerfpp')
            progress_log.append({'minutes': minute, 'iteration': tr.iteration,
                                 'psnr': r['psnr'], 'ssim': r['ssim']})
            bar.write(f'after {minute:g} min ({tr.iteration} iterations): held-out PSNR '
                      f'{r["psnr"]:.2f} dB, SSIM {r["ssim"]:.3f}')

    def on_preview(tr):
        if len(held_out) == 0:
            return
        layers = render_view(tr.model, held_out.cameras[0], cfg.sampling, cfg.model == 'nerfpp')
        write_png(os.path.join(out, 'preview', f'iter_{tr.iteration:06d}.png'), rgb(layers),
                  tr.model.color_space)

    t_start = time.perf_counter()
    try:
        finished = trainer.run(on_step=on_step, on_preview=on_preview)
    except TrainingError as e:
        bar.close()
        print(f'error: {e}', file=sys.stderr)
        return 1
    bar.close()
    if not finished:
        print(f'interrupted at iteration {trainer.iteration}: checkpoint saved to '
              f'{trainer.checkpoint_path}; continue with --resume')
        return 130

    metrics = finish_run(out, trainer.model, trainer.test if len(trainer.test) else
                         trainer.validation, cfg, trainer.checkpoint_path,
                         {'dataset': os.path.abspath(data), 'iterations': trainer.iteration,
                          'train_seconds': round(trainer.elapsed, 2),
                          'train_samples_per_second': trainer.samples_per_second(),
                          'progress': progress_log})
    plot_history(trainer.history, os.path.join(out, 'training.png'))

    print(f'\ntrained {trainer.iteration} iterations in {trainer.elapsed / 60:.1f} min '
          f'({metrics["train_samples_per_second"] / 1e6:.2f} M samples/s); '
          f'wall time {time.perf_counter() - t_start:.0f} s')
    if 'test' in metrics:
        print(f'held-out views: PSNR {metrics["test"]["psnr"]:.2f} dB, '
              f'SSIM {metrics["test"]["ssim"]:.3f} over {len(metrics["test"]["views"])} views')
    print(f'written to {out}/: model.npz, metrics.json, test/*.exr|png, render.xml, '
          f'training.png, preview/')
    if 'test' in metrics:
        print(f'render a view: python -m mi_nerfpp render {os.path.join(out, "render.xml")} '
              f'-o view.exr --preview view.png')
    return 0
