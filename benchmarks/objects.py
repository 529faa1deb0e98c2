"""Render time of the objects example (issue 13): the view of
``scenes/insert_objects.xml`` without objects, with the objects, and with the objects
and the shadow catcher, each rendered once cold (kernel compilation) and ``--repeat`` times warm;
prints the median warm seconds per frame of each and the ratio to the view without objects.

    python benchmarks/objects.py CHECKPOINT [--repeat 1] [-D width=640 -D height=360 -D spp=16 ...]
"""
import os
import statistics
import sys
import time

import mi_nerfpp  # noqa: F401  (libLLVM, variant, plugin registration)
import drjit as dr
import mitsuba as mi

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', 'docs'))
from insert_objects import arguments  # noqa: E402


def main():
    args, scenes = arguments(__doc__.splitlines()[0],
                             [(('--repeat',), dict(type=int, default=1))])
    base = None
    for label, scene in scenes():
        times = []
        for i in range(1 + args.repeat):
            t = time.perf_counter()
            dr.eval(mi.render(scene))
            dr.sync_thread()
            times.append(time.perf_counter() - t)
        warm = statistics.median(times[1:])
        base = base or warm
        print(f'{label}: cold {times[0]:.1f} s, warm {warm:.1f} s per frame ({warm / base:.2f}x)',
              flush=True)


if __name__ == '__main__':
    main()
