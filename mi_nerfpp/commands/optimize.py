"""``python optimize.py`` / ``python -m mi_nerfpp optimize``: fit a NeRF++ to posed images.

Progress bar with loss and PSNR, a preview of a held-out view every few hundred
iterations, checkpoints that resume, and at the end held-out PSNR/SSIM
(``metrics.json``), per-view EXRs and PNGs, a ready-to-render ``render.xml`` and a
loss/PSNR-vs-time plot. The training options follow, by group.
"""
# The run itself is mi_nerfpp.jobs.run.optimize; this command parses the options (generated from
# mi_nerfpp.training.config.TrainConfig, one section of --help per group) and prints what it reports.
from __future__ import annotations

import sys

from mi_nerfpp import _start
from mi_nerfpp.commands.colmap import add_frames_option
from mi_nerfpp.commands.view import add_port_options
from mi_nerfpp.core import budget
from mi_nerfpp.jobs import run as runs
from mi_nerfpp.jobs.console import ConsoleObserver
from mi_nerfpp.jobs.viewer import ViewerObserver, check_port, require_viser
from mi_nerfpp.training.config import DEFAULT_JOB_MINUTES, TrainConfig
from mi_nerfpp.training.options import add_options, values


def add_parser(sub):
    p = sub.add_parser('optimize', help='fit both volumes to a posed-image dataset',
                       description=__doc__)
    p.add_argument('data', nargs='?', help='dataset folder (NeRF++ layout, transforms.json, '
                   'LLFF or COLMAP), a folder of photos without poses, or a video or folder of '
                   'videos (structure from motion runs first, cached in OUT/sfm; of a video, '
                   'the sharpest frames: docs/data.md, "Video in"); default: synthesize and '
                   'cache the embedded default scene and train it for '
                   f'{DEFAULT_JOB_MINUTES:g} minutes')
    add_frames_option(p)
    p.add_argument('--out', help='run folder (default: runs/<dataset name>)')
    p.add_argument('--resume', action='store_true', help='continue from OUT/model.npz')
    p.add_argument('--overwrite', action='store_true',
                   help='replace the trained run in OUT (model.npz, metrics.json, test/, ...); '
                        'without it, training into a folder that holds a run is refused')
    p.add_argument('--view', action='store_true',
                   help='serve the web viewer while training (python -m mi_nerfpp view: the '
                        'model as it trains, its cameras, the step, rays/s and the held-out '
                        'PSNR, pause/resume); it renders between steps in a bounded share of '
                        "the time. Needs pip install 'mi-nerfpp[viewer]'")
    add_port_options(p, prefix='view-')
    add_options(p, TrainConfig)
    p.set_defaults(func=run)
    return p


def subject(args):
    return f'dataset {args.data}' if args.data else 'the default capture'


def run(args):

    observer = ConsoleObserver()
    if args.view:               # before any work: viser missing, the port taken
        require_viser()
        check_port(args.view_host, args.view_port)
        observer = ViewerObserver(observer, args.view_host, args.view_port,
                                  args.view_max_width)
    try:
        return train(args, observer)
    finally:
        if args.view:
            observer.close()


def train(args, observer):
    options, data = values(args, TrainConfig), args.data
    config = TrainConfig.from_options(**options)    # checks every option (ValueError: the flag)
    plan = budget.plan(config.sizing())             # what they size (memory, Dr.Jit), once
    budget.check(plan)
    if data is None:        # after the checks: the default capture may take minutes to render
        data, options = runs.default_job(options, progress=True)
        config = TrainConfig.from_options(**options)
    # Errors (TrainingError and the others) end the command at its boundary (mi_nerfpp.commands.cli).
    result = runs.optimize(data, config, args.out, resume=args.resume, overwrite=args.overwrite,
                           observer=observer, plan=plan, frames=args.frames)
    if not result.finished:
        print(f'interrupted at iteration {result.trainer.iteration}: checkpoint saved to '
              f'{result.trainer.checkpoint_path}; continue with --resume', file=sys.stderr)
        return _start.interrupted_status()
    lines, warnings = runs.summary(result)
    print('\n' + '\n'.join(lines))
    for warning in warnings:
        print(warning, file=sys.stderr)
    return 0
