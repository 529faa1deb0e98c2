"""Peak memory of ``optimize`` on a real-sized photo set (issue 12: 135 photos of 1200x800).

    python benchmarks/photo_set_memory.py [--views 135] [--res 1200x800] [--out /tmp/photoset]
                                          [-- OPTIMIZE OPTIONS...]

Writes (once) a synthetic posed photo set of that size in the NeRF++ layout, as JPEGs of
smooth random texture on orbiting cameras (every 8th a test view), then runs ``optimize`` on
it in a child process for a few iterations with the default (automatic) resolution - the
photos' own unless they do not fit in memory (issue 34) - and prints the child's peak RSS,
which includes the final evaluation of the test views. Options after ``--`` go to
``optimize`` (e.g. ``--downscale 2``). Results: ``benchmarks/results/photo_set_memory.json``.
"""
import argparse
import os
import shlex
import subprocess
import sys
import time

import numpy as np


def write_photo_set(out, views, width, height):
    from PIL import Image

    from mi_nerfpp.data import Camera
    from mi_nerfpp.data.nerfpp import write_camera
    from mi_nerfpp.data.synth import intrinsics_from_fov, look_at
    if os.path.isdir(os.path.join(out, 'train', 'rgb')):
        return
    rng = np.random.default_rng(0)
    K = intrinsics_from_fov(60.0, width, height)
    coarse = rng.uniform(0, 255, size=(height // 40, width // 40, 3)).astype(np.uint8)
    for i in range(views):
        angle = 2 * np.pi * i / views
        c2w = look_at(3.0 * np.array([np.cos(angle), 0.3, np.sin(angle)]), (0.0, 0.0, 0.0))
        split = os.path.join(out, 'test' if i % 8 == 0 else 'train')
        os.makedirs(os.path.join(split, 'rgb'), exist_ok=True)
        img = Image.fromarray(np.roll(coarse, i, axis=1)).resize((width, height))
        img.save(os.path.join(split, 'rgb', f'{i:06d}.jpg'), quality=90)
        write_camera(split, f'{i:06d}', Camera(K, c2w, width, height))


def main():
    argv = sys.argv[1:]
    extra = argv[argv.index('--') + 1:] if '--' in argv else []
    argv = argv[:argv.index('--')] if '--' in argv else argv
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--views', type=int, default=135)
    p.add_argument('--res', default='1200x800')
    p.add_argument('--out', default='/tmp/mi_nerfpp_photoset')
    p.add_argument('--iterations', type=int, default=5)
    args = p.parse_args(argv)
    width, height = (int(v) for v in args.res.split('x'))
    data = os.path.join(args.out, f'{args.views}x{width}x{height}')
    write_photo_set(data, args.views, width, height)
    cmd = [sys.executable, '-m', 'mi_nerfpp', 'optimize', data, '--out',
           os.path.join(args.out, 'run'), '--iterations', str(args.iterations),
           '--preview-every', '0', '--checkpoint-every', '0', '--eval-at'] + extra
    t = time.perf_counter()
    subprocess.run(cmd, check=True)
    from mi_nerfpp.jobs import bench
    peak, seconds = bench.peak_rss_mib(children=True), time.perf_counter() - t
    print(f'{args.views} photos of {width}x{height}: optimize peak RSS {peak:.0f} MiB, '
          f'{seconds:.0f} s ({" ".join(cmd[3:])})')
    bench.write_results('photo_set_memory', 'Peak memory of optimize on a large photo set', [
        bench.table('optimize in a child process',
                    ['photos', 'size', 'optimize options', 'peak RSS (MiB)', 'wall time (s)'],
                    [[args.views, f'{width}x{height}', shlex.join(extra) or 'defaults', peak,
                      seconds]],
                    note=f'{args.iterations} iterations and the evaluation of the test views; '
                         f'the automatic resolution unless an option sets it.')])


if __name__ == '__main__':
    main()
