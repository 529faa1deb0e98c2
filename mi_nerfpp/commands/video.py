"""``python -m mi_nerfpp video RUN``: a novel-view video (orbit or test path) of a training run."""
from __future__ import annotations

import os


def add_parser(sub):
    from . import positive_int, resolution
    p = sub.add_parser('video', help='render a novel-view video of a training run')
    p.add_argument('run', help='run folder written by optimize (holds model.npz)')
    p.add_argument('-o', '--output', help='.mp4 or .gif (default: RUN/video.mp4)')
    p.add_argument('--path', choices=['orbit', 'test'], default='orbit',
                   help="an orbit around the scene, or the dataset's test cameras")
    p.add_argument('--frames', type=positive_int, default=60, help='orbit frames (default 60)')
    p.add_argument('--fps', type=positive_int, default=24)
    p.add_argument('--res', type=resolution, metavar='WxH',
                   help='WxH (default: the training images)')
    p.set_defaults(func=run)
    return p


def run(args):
    import numpy as np
    from tqdm import tqdm

    from ..preview import to_srgb8
    from ..video import orbit_cameras, resized, write_video
    from ..views import ViewRenderer, rgb
    from . import open_run_or_exit

    model, meta, cfg, dataset = open_run_or_exit(args.run)
    template = dataset.train.cameras[0]
    if args.res:
        template = resized(template, *args.res)
    if args.path == 'orbit':
        cameras = orbit_cameras(dataset.train.cameras, args.frames, template)
    else:
        cameras = [resized(c, template.width, template.height) for c in dataset.test.cameras]
        if not cameras:
            raise SystemExit(f'{dataset.root} has no test cameras: use --path orbit')
    out = args.output or os.path.join(args.run, 'video.mp4')
    renderer = ViewRenderer(model, cfg.sampling, cfg.model == 'nerfpp')
    frames = [to_srgb8(np.clip(rgb(renderer.render(cam)), 0, 1), 'linear')
              for cam in tqdm(cameras, desc='video', unit='frame')]
    try:
        write_video(out, frames, fps=args.fps)
    except (RuntimeError, ValueError) as e:
        raise SystemExit(f'error: {e}') from None
    print(f'wrote {out} ({len(frames)} frames)')
