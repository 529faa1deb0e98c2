"""Render time of the objects example: the view of ``scenes/insert_objects.xml``
without objects, with the objects, and with the objects and the shadow catcher, each rendered
once cold (kernel compilation) and then ``--repeat`` times warm, the three *alternating* (one of
each per round, so a shared machine's load shifts hit them alike); prints the median warm
seconds per frame of each, the ratio to the view without objects, and the catcher's ratio to
the objects without it (issue 35's target: at most 2x), also per round.

    python benchmarks/objects.py CHECKPOINT [--repeat 1] [-D width=640 -D height=360 -D spp=16 ...]

Results: ``benchmarks/results/objects.json``.
"""
import argparse
import statistics
import time

import mi_nerfpp  # noqa: F401  (libLLVM, variant, plugin registration)
import drjit as dr
import mitsuba as mi
from mi_nerfpp.jobs import bench


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('checkpoint')
    p.add_argument('--repeat', type=int, default=1)
    p.add_argument('-D', '--define', action='append', default=[], metavar='NAME=VALUE')
    args = p.parse_args()
    defines = dict(d.split('=', 1) for d in args.define)
    from mi_nerfpp.data.synth import scene_file
    scenes = list(bench.object_scenes(args.checkpoint, defines,
                                      scene=scene_file('insert_objects.xml')))
    times = {label: [] for label, _ in scenes}
    for round_ in range(1 + args.repeat):          # round 0: cold (kernel compilation)
        for label, scene in scenes:
            t = time.perf_counter()
            dr.eval(mi.render(scene))
            dr.sync_thread()
            times[label].append(time.perf_counter() - t)
        if round_:
            (a, _), (b, _), (c, _) = scenes
            print(f'round {round_}: ' + ', '.join(f'{l} {times[l][-1]:.1f} s' for l, _ in scenes)
                  + f'; catcher / objects {times[c][-1] / times[b][-1]:.2f}x', flush=True)
    base, rows = None, []
    for label, _ in scenes:
        warm = statistics.median(times[label][1:])
        base = base or warm
        print(f'{label}: cold {times[label][0]:.1f} s, warm {warm:.1f} s per frame '
              f'({warm / base:.2f}x)', flush=True)
        rows.append([label, times[label][0], warm, warm / base])
    bench.write_results('objects', 'Render time of the objects example', [
        bench.table('Seconds per frame', ['render', 'cold (s)', 'warm (s)',
                                          'warm, x reconstruction alone'], rows,
                    note=f'Median of {args.repeat} warm render(s) after one cold render, the three '
                         f'alternating.')],
        notes=f'The view of mi_nerfpp/scenes/insert_objects.xml with '
              f'{" ".join(args.define) or "its defaults"}.')


if __name__ == '__main__':
    main()
