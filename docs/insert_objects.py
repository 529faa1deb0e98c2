"""The README's picture of objects inside the reconstruction: the view of
scenes/insert_objects.xml rendered three times (the reconstruction alone, with the
objects, with the objects and the shadow catcher), side by side in one PNG.

    .venv/bin/python docs/insert_objects.py runs/default/model.npz docs/results/insert_objects.png \
        [-D width=640 -D height=360 -D spp=16 ...]
"""
import argparse
import os

import numpy as np

import mi_nerfpp  # noqa: F401  (libLLVM, variant, plugin registration)
import mitsuba as mi

from mi_nerfpp.jobs.bench import object_variant_xml
from mi_nerfpp.core.color import to_srgb8
from mi_nerfpp.data.synth import scene_file

SCENE = scene_file('insert_objects.xml')


# The three renders of the comparison: (label, with objects, with the shadow catcher).
VARIANTS = (('reconstruction alone', False, False), ('with objects', True, False),
            ('with objects and catcher', True, True))


def arguments(description, extra=()):
    """Parse ``CHECKPOINT [extra options] [-D NAME=VALUE ...]``; returns ``(args, scenes)`` with
    ``scenes()`` yielding ``(label, mitsuba scene)`` for each of :data:`VARIANTS`."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument('checkpoint')
    for args, kwargs in extra:
        p.add_argument(*args, **kwargs)
    p.add_argument('-D', '--define', action='append', default=[], metavar='NAME=VALUE')
    args = p.parse_args()
    defines = dict(d.split('=', 1) for d in args.define)
    defines['checkpoint'] = os.path.abspath(args.checkpoint)
    with open(SCENE) as f:
        xml = f.read()

    def scenes():
        for label, objects, catchers in VARIANTS:
            yield label, mi.load_string(object_variant_xml(xml, objects, catchers), **defines)
    return args, scenes


def main():
    args, scenes = arguments(__doc__.splitlines()[0], [(('output',), {})])
    panels = []
    for label, scene in scenes():
        img = np.array(mi.render(scene))[..., :3]
        panels.append(to_srgb8(img, 'linear'))
        print(f'{label}: done', flush=True)
    gap = np.full((panels[0].shape[0], 4, 3), 255, np.uint8)
    strip = np.concatenate([panels[0], gap, panels[1], gap, panels[2]], axis=1)
    mi.Bitmap(strip).write(args.output)
    print(f'wrote {args.output}')


if __name__ == '__main__':
    main()
