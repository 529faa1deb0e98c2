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
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    try:
        return args.func(args) or 0
    except KeyboardInterrupt:
        print('interrupted', file=sys.stderr)
        return 130
