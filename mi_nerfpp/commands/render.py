"""``python -m mi_nerfpp render SCENE.xml``: a scene to a multi-layer EXR (and a PNG preview).

``--camera FILE [--frame N]`` renders through one frame of a tracked camera (USD, Nuke ``.chan``,
nerfstudio's ``camera_path.json``: :mod:`mi_nerfpp.output.tracked_camera`) in place of the
scene's sensor, placed in the frame of ``export``'s files; the scene's film gives its width (and
height, where the file gives no aspect) and its sampler the samples per pixel.
"""
from __future__ import annotations

import os
import time

import mitsuba as mi

from mi_nerfpp.core.frame import SCENE_NEAR_CLIP
from mi_nerfpp.data import mitsuba_sensor_dict
from mi_nerfpp.files.atomic import check_writable_folder, readable_path
from mi_nerfpp.files.preview import write_linear_png
from mi_nerfpp.integrator import NeRFPPIntegrator
from mi_nerfpp.output.camera_path import DEFAULT_RESOLUTION
from mi_nerfpp.output.deep import render_deep_to_file
from mi_nerfpp.output.tracked_camera import (capture_normalizations,
                                             read_shot)
from mi_nerfpp.output.views import render_to_files


def add_parser(sub):
    p = sub.add_parser('render', help='render a scene XML (nerfpp integrator) to a multi-layer EXR')
    p.add_argument('scene', help='Mitsuba scene XML')
    p.add_argument('-o', '--output', default='render.exr', help='EXR to write (default: render.exr)')
    p.add_argument('--spp', type=int, default=0, help="samples per pixel (default: the scene's)")
    p.add_argument('--preview', help='also write an sRGB PNG preview here')
    p.add_argument('--deep', action='store_true',
                   help='write a deep EXR (R G B A Z ZBack samples along each pixel) instead '
                        'of the flat layers: docs/compositing.md')
    p.add_argument('--seed', type=int, default=0, help='sampler seed')
    p.add_argument('-D', '--define', action='append', metavar='NAME=VALUE',
                   help='set a <default> parameter of the scene (repeatable)')
    p.add_argument('--camera', metavar='FILE',
                   help="render through a tracked camera in place of the scene's sensor: USD "
                        "(.usd/.usda/.usdc/.usdz), Nuke .chan or nerfstudio's camera_path.json, "
                        "in the frame of export's files (the scene's film gives the width)")
    p.add_argument('--frame', type=int, metavar='N',
                   help="with --camera: the file's frame N (default: its first)")
    p.add_argument('--camera-name', metavar='NAME',
                   help='with --camera FILE.usd: the camera to render, of several (its prim name, '
                        "its parent's, as Blender names the object, or its path)")
    p.set_defaults(func=run)
    return p


def _defines(pairs):
    out = {}
    for pair in pairs or []:
        if '=' not in pair:
            raise ValueError(f"-D expects name=value, got '{pair}'")
        k, v = pair.split('=', 1)
        out[k] = v
    return out


def run(args):



    if not os.path.isfile(args.scene):
        raise ValueError(f'{args.scene}: scene file not found')
    if args.spp < 0:
        raise ValueError(f'--spp must be 0 (the scene\'s sampler) or more, got {args.spp}')
    for path in filter(None, (args.output, args.preview)):
        if os.path.isdir(path):
            raise ValueError(f'{path} is a folder: give a file name to write')
    check_arguments(args)
    for path in filter(None, (args.output, args.preview)):
        check_writable_folder(os.path.dirname(os.path.abspath(path)), 'output folder')
    t0 = time.perf_counter()
    with readable_path(args.scene) as readable:      # Mitsuba takes UTF-8 names only
        scene = mi.load_file(readable, **_defines(args.define))
    if args.camera:
        sensor = tracked_sensor(scene, args)
    else:
        check_sensor(scene, args.scene)
        sensor = None
    if args.deep:
        _, _, beauty = render_deep_to_file(scene, args.output, spp=args.spp, seed=args.seed,
                                           sensor=sensor)
        if args.preview:
            write_linear_png(args.preview, beauty)
    else:
        render_to_files(scene, args.output, spp=args.spp, preview=args.preview, seed=args.seed,
                        sensor=sensor)
    print(f'wrote {args.output}' + (f' and {args.preview}' if args.preview else '')
          + f' in {time.perf_counter() - t0:.1f} s')


# ----------------------------------------------------------------------------- checks
# What the render command writes, by file extension: -o is a multi-layer OpenEXR file,
# --preview an 8-bit sRGB PNG; any other extension is refused rather than written in the
# wrong format under its name.
OUTPUT_EXTENSIONS = {'output': ('-o', '.exr', 'a multi-layer OpenEXR file'),
                     'preview': ('--preview', '.png', 'an sRGB PNG')}
# Sensors whose camera the EXR header describes (views.camera_attributes): the projective
# cameras with a pinhole model. Mitsuba's class name -> plugin name.
CAMERA_SENSORS = {'PerspectiveCamera': 'perspective', 'ThinLensCamera': 'thinlens'}
MAX_SEED = 2 ** 32 - 1       # mi.render takes a 32-bit seed


def subject(args):
    return f'scene {args.scene}'


def check_arguments(args):
    """Refuse output names whose extension is not the format written, and a seed that
    Mitsuba's 32-bit seed cannot hold, before the scene is loaded (ValueError)."""
    for name, (flag, ext, what) in OUTPUT_EXTENSIONS.items():
        path = getattr(args, name)
        if path and os.path.splitext(path)[1].lower() != ext:
            hint = ' (a PNG preview: --preview NAME.png)' if name == 'output' else ''
            raise ValueError(f'{flag} {path}: the render writes {what} here: give a name '
                             f'ending in {ext}{hint}')
    if not 0 <= args.seed <= MAX_SEED:
        raise ValueError(f'--seed must be a whole number from 0 to {MAX_SEED}, got {args.seed}')
    if not args.camera:
        for flag, value in (('--frame', args.frame), ('--camera-name', args.camera_name)):
            if value is not None:
                raise ValueError(f'{flag} picks from a tracked camera: give it with --camera FILE')
    elif not os.path.isfile(args.camera):
        raise ValueError(f'--camera {args.camera}: camera file not found')


def tracked_sensor(scene, args):
    """The sensor of frame ``--frame`` (default: the first) of the tracked camera ``--camera``
    (module docs), in the scene's world: the dataset's frame of the integrator's model."""
    integrator = scene.integrator()
    if not isinstance(integrator, NeRFPPIntegrator):
        raise ValueError(f"{args.scene}: the scene's integrator is not 'nerfpp': --camera "
                         f"places the camera through a model's normalization")
    shot = read_shot(args.camera, args.camera_name)
    number = shot.frames[0].number if args.frame is None else shot.frame(args.frame).number
    sensors = scene.sensors()
    film = tuple(sensors[0].film().crop_size()) if sensors else DEFAULT_RESOLUTION
    frame = shot.within((number, number))       # its own film: the aspect may change
    width, height = frame.image_size(*film)
    camera = frame.cameras(width, height,
                           capture_normalizations(integrator.meta.get('dataset')))[number]
    spp = sensors[0].sampler().sample_count() if sensors else 1
    desc = mitsuba_sensor_dict(camera, spp=spp)
    desc['near_clip'] = integrator.model.normalization.to_world_distance(SCENE_NEAR_CLIP)
    return mi.load_dict(desc)


def check_sensor(scene, path):
    """Refuse a scene without a sensor, or whose first sensor is not a camera with a film
    image (``perspective`` or ``thinlens``), naming the scene file (ValueError)."""
    sensors = scene.sensors()
    if not sensors:
        raise ValueError(f'{path}: the scene has no sensor: add a <sensor type="perspective"> '
                         f'with a film (see scenes/render_random.xml)')
    kind = str(sensors[0]).split('[', 1)[0].strip()
    if kind not in CAMERA_SENSORS:
        name = kind.removesuffix('Camera').lower() or 'unknown'
        raise ValueError(f"{path}: the scene's sensor is '{name}': render takes a "
                         f"{' or '.join(CAMERA_SENSORS.values())} sensor (a camera with a film "
                         f"image, which the EXR header describes)")
