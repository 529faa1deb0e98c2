"""Command-line entry points: ``python -m mi_nerfpp <command>`` (also installed as ``mi-nerfpp``)."""
from __future__ import annotations

import argparse
import os
import sys
import time


def _defines(pairs):
    out = {}
    for pair in pairs or []:
        if '=' not in pair:
            raise SystemExit(f"-D expects name=value, got '{pair}'")
        k, v = pair.split('=', 1)
        out[k] = v
    return out


def film_channel_names(film, integrator):
    """Channel names of ``mi.render``'s output for this film and integrator."""
    import mitsuba as mi
    base = ['R', 'G', 'B', 'A'] if mi.has_flag(film.flags(), mi.FilmFlags.Alpha) else ['R', 'G', 'B']
    return base + list(integrator.aov_names())


def render_to_files(scene, out, spp=0, preview=None, seed=0, progress=True):
    """Render ``scene``'s first sensor and write a multi-layer EXR (and a PNG preview).

    Returns the image as a dict of channel name -> HxW float32 array.
    """
    import mitsuba as mi
    import numpy as np

    from .exr import split_channels, write_exr
    from .integrator import NeRFPPIntegrator
    from .preview import write_png

    integrator = scene.integrator()
    if isinstance(integrator, NeRFPPIntegrator):
        integrator.show_progress = progress
    film = scene.sensors()[0].film()
    image = np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float32)
    channels = split_channels(image, film_channel_names(film, integrator))
    write_exr(out, channels)
    if preview:
        color_space = integrator.model.color_space if isinstance(integrator, NeRFPPIntegrator) else 'linear'
        write_png(preview, np.stack([channels[c] for c in 'RGB'], axis=-1), color_space)
    return channels


def cmd_render(args):
    import mitsuba as mi

    if not os.path.isfile(args.scene):
        raise SystemExit(f'{args.scene}: scene file not found')
    t0 = time.perf_counter()
    scene = mi.load_file(args.scene, **_defines(args.define))
    render_to_files(scene, args.output, spp=args.spp, preview=args.preview, seed=args.seed)
    print(f'wrote {args.output}' + (f' and {args.preview}' if args.preview else '')
          + f' in {time.perf_counter() - t0:.1f} s')


def cmd_evaluate(args):
    from .optimize import finish_run
    from .train import TrainingError, open_run, samples_per_second
    try:
        model, meta, cfg, dataset = open_run(args.run)
    except (TrainingError, ValueError) as e:
        raise SystemExit(f'error: {e}') from None
    held_out = dataset.test if len(dataset.test) else dataset.validation
    metrics = finish_run(args.run, model, held_out, cfg, os.path.join(args.run, 'model.npz'), {
        'dataset': dataset.root, 'iterations': meta['iteration'],
        'train_seconds': round(meta['elapsed'], 2),
        'train_samples_per_second': samples_per_second(cfg, meta['iteration'], meta['elapsed'])})
    if 'test' in metrics:
        print(f'{len(held_out)} held-out views: PSNR {metrics["test"]["psnr"]:.2f} dB, '
              f'SSIM {metrics["test"]["ssim"]:.3f}; written to {args.run}/metrics.json and test/')
    else:
        print(f'{dataset.root} has no test or validation views to evaluate')


def cmd_video(args):
    import numpy as np
    from tqdm import tqdm

    from .evaluate import render_view, rgb
    from .preview import to_srgb8
    from .train import TrainingError, open_run
    from .video import orbit_cameras, resized, write_video
    try:
        model, meta, cfg, dataset = open_run(args.run)
    except (TrainingError, ValueError) as e:
        raise SystemExit(f'error: {e}') from None
    template = dataset.train.cameras[0]
    if args.res:
        w, h = (int(v) for v in args.res.lower().split('x'))
        template = resized(template, w, h)
    if args.path == 'orbit':
        cameras = orbit_cameras(dataset.train.cameras, args.frames, template)
    else:
        cameras = [resized(c, template.width, template.height) for c in dataset.test.cameras]
        if not cameras:
            raise SystemExit(f'{dataset.root} has no test cameras: use --path orbit')
    out = args.output or os.path.join(args.run, 'video.mp4')
    frames = [to_srgb8(np.clip(rgb(render_view(model, cam, cfg.sampling, cfg.model == 'nerfpp')),
                               0, 1), model.color_space)
              for cam in tqdm(cameras, desc='video', unit='frame')]
    try:
        write_video(out, frames, fps=args.fps)
    except (RuntimeError, ValueError) as e:
        raise SystemExit(f'error: {e}') from None
    print(f'wrote {out} ({len(frames)} frames)')


def build_parser():
    p = argparse.ArgumentParser(prog='python -m mi_nerfpp',
                                description='NeRF++ for Mitsuba 3: render, optimize, evaluate.')
    sub = p.add_subparsers(dest='command', required=True)

    r = sub.add_parser('render', help='render a scene XML (nerfpp integrator) to a multi-layer EXR')
    r.add_argument('scene', help='Mitsuba scene XML')
    r.add_argument('-o', '--output', default='render.exr', help='EXR to write (default: render.exr)')
    r.add_argument('--spp', type=int, default=0, help="samples per pixel (default: the scene's)")
    r.add_argument('--preview', help='also write an sRGB PNG preview here')
    r.add_argument('--seed', type=int, default=0, help='sampler seed')
    r.add_argument('-D', '--define', action='append', metavar='NAME=VALUE',
                   help='set a <default> parameter of the scene (repeatable)')
    r.set_defaults(func=cmd_render)

    from . import optimize
    optimize.add_parser(sub)
    from .synth import add_parser as add_synth_parser; add_synth_parser(sub)  # noqa: E702

    e = sub.add_parser('evaluate', help='re-run the held-out evaluation of a training run')
    e.add_argument('run', help='run folder written by optimize (holds model.npz)')
    e.set_defaults(func=cmd_evaluate)

    v = sub.add_parser('video', help='render a novel-view video of a training run')
    v.add_argument('run', help='run folder written by optimize (holds model.npz)')
    v.add_argument('-o', '--output', help='.mp4 or .gif (default: RUN/video.mp4)')
    v.add_argument('--path', choices=['orbit', 'test'], default='orbit',
                   help="an orbit around the scene, or the dataset's test cameras")
    v.add_argument('--frames', type=int, default=60, help='orbit frames (default 60)')
    v.add_argument('--fps', type=int, default=24)
    v.add_argument('--res', help='WxH (default: the training images)')
    v.set_defaults(func=cmd_video)
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    try:
        return args.func(args) or 0
    except KeyboardInterrupt:
        print('interrupted', file=sys.stderr)
        return 130
