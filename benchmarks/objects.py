"""Render time of the objects example: the view of ``scenes/insert_objects.xml``
without objects, with the objects, and with the objects and the shadow catcher, each rendered
once cold (kernel compilation) and ``--repeat`` times warm; prints the median warm seconds per
frame of each and the ratio to the view without objects.

    python benchmarks/objects.py CHECKPOINT [--repeat 1] [-D width=640 -D height=360 -D spp=16 ...]

Results: ``benchmarks/results/objects.json``.
"""
import argparse
import statistics
import time

import mi_nerfpp  # noqa: F401  (libLLVM, variant, plugin registration)
import drjit as dr
import mitsuba as mi
from mi_nerfpp import bench


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('checkpoint')
    p.add_argument('--repeat', type=int, default=1)
    p.add_argument('-D', '--define', action='append', default=[], metavar='NAME=VALUE')
    args = p.parse_args()
    defines = dict(d.split('=', 1) for d in args.define)
    base, rows = None, []
    for label, scene in bench.object_scenes(args.checkpoint, defines):
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
        rows.append([label, times[0], warm, warm / base])
    bench.write_results('objects', 'Render time of the objects example', [
        bench.table('Seconds per frame', ['render', 'cold (s)', 'warm (s)',
                                          'warm, x reconstruction alone'], rows,
                    note=f'Median of {args.repeat} warm render(s) after one cold render.')],
        notes=f'The view of mi_nerfpp/scenes/insert_objects.xml with '
              f'{" ".join(args.define) or "its defaults"}.')


if __name__ == '__main__':
    main()
