"""``python -m mi_nerfpp synth SCENE.xml --out DATA``: a synthetic capture (:mod:`mi_nerfpp.data.synth`)."""
from __future__ import annotations

import argparse
import os

from mi_nerfpp.commands.arguments import (float_between, positive_float, positive_int,
                                          resolution, whole_between)
from mi_nerfpp.data.synth import (DEFAULT_FOV, DEFAULT_RADIUS, DEFAULT_RES,
                                  DEFAULT_SEED, DEFAULT_SPP,
                                  DEFAULT_TRAJECTORY, DEFAULT_VIEWS,
                                  TRAJECTORIES, synthesize)
from mi_nerfpp.data.synth.capture import write_object_masks
from mi_nerfpp.data.synth.realistic import CLEAN_FOLDER, PHONE_RES, Realism, realistic_copy
from mi_nerfpp.files.atomic import check_not_a_file


def run(args) -> None:
    check_not_a_file(args.out)
    # Errors end the command at its boundary (mi_nerfpp.commands.cli).
    clean = os.path.join(args.out, CLEAN_FOLDER) if args.realistic else args.out
    synthesize(args.scene, clean, views=args.views, res=args.res, spp=args.spp,
               trajectory=args.trajectory, seed=args.seed, fov=args.fov, radius=args.radius)
    if args.object_masks:
        count = write_object_masks(clean)
        print(f'wrote {count} object masks to {clean}/{{train,validation,test}}/mask/ '
              f'(train with --masks object)')
    if args.realistic:
        realism = Realism.in_the_wild() if args.realistic == 'wild' else Realism()
        realistic_copy(clean, args.out, realism, seed=args.seed)
        print(f'wrote the realistic stand-in to {args.out} (transforms_*.json; the clean '
              f'capture it was made from in {clean})')


def subject(args):
    return f'scene {args.scene}'


def add_parser(sub) -> argparse.ArgumentParser:
    """Register ``synth`` on the sub-command parsers of ``python -m mi_nerfpp``."""
    p = sub.add_parser(
        'synth', help='render a synthetic NeRF++ capture (images, poses, ground truth) of a '
                      'Mitsuba scene',
        description='Render posed views of a Mitsuba scene XML into the NeRF++ dataset layout, '
                    'with ground-truth depth and foreground masks (DATA/{split}/gt/*.exr) and '
                    'DATA/capture.json. An identical earlier capture in DATA is reused.')
    p.add_argument('scene', help='Mitsuba scene XML (e.g. scenes/gt_garden.xml)')
    p.add_argument('--out', required=True, metavar='DATA', help='output folder')
    p.add_argument('--views', type=positive_int, default=DEFAULT_VIEWS,
                   help=f'number of views over all splits (default {DEFAULT_VIEWS}; 80/10/10 '
                        f'train/validation/test)')
    p.add_argument('--res', type=resolution, default=DEFAULT_RES, metavar='WxH',
                   help='image size (default %dx%d)' % DEFAULT_RES)
    p.add_argument('--spp', type=positive_int, default=DEFAULT_SPP,
                   help=f'samples per pixel (default {DEFAULT_SPP})')
    p.add_argument('--trajectory', choices=TRAJECTORIES, default=DEFAULT_TRAJECTORY,
                   help='orbit: jittered ring around the origin; truck: the Tanks and Temples '
                        'Truck camera poses; hemisphere: random views on the upper hemisphere '
                        '(elevation 5-75 deg); arc: DTU-like arc in front (train within +-50 '
                        'deg azimuth; validation = interpolated views, test = extrapolated '
                        'views at 65-90 deg; needs >= 3 views) (default %(default)s)')
    p.add_argument('--seed', type=whole_between(0, 2 ** 31 - 1), default=DEFAULT_SEED,
                   help='seed of cameras, splits and sampler (default %(default)s)')
    p.add_argument('--fov', type=float_between(0, 180, ' degrees'), default=DEFAULT_FOV,
                   help=f'horizontal field of view in degrees, ignored by truck '
                        f'(default {DEFAULT_FOV:g})')
    p.add_argument('--radius', type=positive_float, default=DEFAULT_RADIUS,
                   help=f'camera distance from the origin in world units (default '
                        f'{DEFAULT_RADIUS:g})')
    p.add_argument('--object-masks', action='store_true',
                   help='also write each view\'s object silhouette as its mask '
                        '(DATA/{split}/mask/*.png, white where the first surface seen lies in '
                        'the foreground sphere: the ground truth\'s fg.A), for --masks object')
    p.add_argument('--realistic', nargs='?', const='phone', choices=('phone', 'wild'),
                   help='a stand-in of a phone capture: the clean capture goes to '
                        f'DATA/{CLEAN_FOLDER}/, and DATA gets its training photos with lens '
                        'distortion, auto-exposure, sensor noise, JPEG, motion blur on some, '
                        'a transient object on a few and small pose errors '
                        '(transforms_*.json; held-out views stay clean). A phone photo is '
                        f'{PHONE_RES[0]}x{PHONE_RES[1]}: --res {PHONE_RES[0] // 4}x'
                        f'{PHONE_RES[1] // 4} is a quarter of it. --realistic wild: a photo '
                        'collection of many people over years instead (wider exposure, the sky '
                        'and the haze changing from photo to photo, passers-by in a third)')
    p.set_defaults(func=run)
    return p
