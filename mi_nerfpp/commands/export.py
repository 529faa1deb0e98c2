"""``python -m mi_nerfpp export RUN --out DIR``: cameras and proxy geometry of a run for USD,
Nuke and Blender (:mod:`mi_nerfpp.jobs.export`)."""
from __future__ import annotations

from mi_nerfpp.commands.arguments import at_least, positive_float
from mi_nerfpp.core import budget
from mi_nerfpp.jobs.export import (DEFAULT_TEXTURE_SIZE, MIN_RESOLUTION, export_run,
                                   largest_resolution)
from mi_nerfpp.jobs.run import open_run
from mi_nerfpp.output.proxy_texture import MIN_TEXTURE_SIZE, largest_texture_size


def add_parser(sub):
    p = sub.add_parser('export', help='export a run\'s cameras (USD, Nuke .chan) and a '
                                      'textured proxy mesh of its foreground (USD, OBJ, PLY) '
                                      'for DCC tools')
    p.add_argument('run', help='run folder written by optimize (holds model.npz)')
    p.add_argument('--out', required=True, metavar='DIR', help='folder to write into')
    p.add_argument('--resolution', type=at_least(MIN_RESOLUTION), default=128,
                   help=f'marching-cubes grid over the unit sphere (default 128, at least '
                        f'{MIN_RESOLUTION})')
    p.add_argument('--density', type=positive_float,
                   help='density of the proxy surface (default: opacity 1/2 over one grid '
                        'step)')
    p.add_argument('--texture-size', type=at_least(MIN_TEXTURE_SIZE),
                   default=DEFAULT_TEXTURE_SIZE, metavar='N',
                   help=f'texels a side of the proxy\'s texture, proxy_texture.png (default '
                        f'{DEFAULT_TEXTURE_SIZE}, at least {MIN_TEXTURE_SIZE})')
    p.set_defaults(func=run)
    return p


def subject(args):
    return f'run folder {args.run}'


def run(args):
    for module, package in (('pxr', 'usd-core'), ('xatlas', 'xatlas')):
        try:
            __import__(module)  # deferred: usd-core and xatlas are the optional extra [export]
        except ImportError:
            raise RuntimeError(f"{package} is not installed: pip install -e '.[export]' "
                               "(scripts/setup.sh --test installs it)") from None
    largest = largest_resolution()
    if args.resolution > largest:
        raise ValueError(f'--resolution {args.resolution} is too large: its grid of '
                         f'{args.resolution ** 3:,} points takes more than this machine\'s '
                         f'{budget.memory_text()}; the largest that fits is {largest}')
    largest = largest_texture_size(budget.memory_bytes())
    if args.texture_size > largest:
        raise ValueError(f'--texture-size {args.texture_size} is too large: its '
                         f'{args.texture_size ** 2:,} texels take more than this machine\'s '
                         f'{budget.memory_text()}; the largest that fits is {largest}')
    opened = open_run(args.run)                # errors: reported by mi_nerfpp.commands.cli
    written = export_run(args.run, args.out, args.resolution, args.density, opened=opened,
                         texture_size=args.texture_size)
    for path in written:
        print(f'wrote {path}')
