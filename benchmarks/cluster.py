"""Frames per minute of ``video`` in one process and on a local Ray cluster (scaling, overhead).

    python benchmarks/cluster.py [--run runs/default] [--frames 60] [--res 320x180]

Renders the same orbit (``--frames`` frames at ``--res``, PNG + multi-layer EXR each) with the
``video`` command, each configuration into a fresh folder so no frame is skipped:

* ``single process``: ``video`` without ``--ray`` (Dr.Jit threads = all CPUs),
* ``ray 1 x 1 CPU`` and ``ray 2 x 1 CPU``: ``--ray`` with one / two workers of one CPU each,
* ``ray 1 x N CPUs``: one worker with all CPUs, the single process's resources.

One local Ray cluster (``ray.init`` here, all CPUs) serves every configuration, and an untimed
two-frame job of each kind first fills the kernel cache (``DRJIT_CACHE_DIR``), so each timing
is a whole command with warm kernels: loading the run and the checkpoint, starting the
workers, rendering, writing, assembling the MP4. Prints frames per minute, the scaling
efficiency of 2 workers against 1 (fpm(2 x 1) / (2 fpm(1 x 1))) and the overhead per frame of
Ray against the single process with the same CPUs ((t(ray 1 x N) - t(single)) / frames).
Run it on an otherwise idle machine with at least two cores. Results:
``benchmarks/results/cluster.json``.
"""
import argparse
import os
import tempfile
import time

import mi_nerfpp  # noqa: F401
from mi_nerfpp.jobs import bench
from mi_nerfpp.commands.cli import main as cli


def video(run, frames, res, out, extra):
    argv = ['video', run, '--frames', str(frames), '--res', res, '--exr', '-o', out] + extra
    start = time.perf_counter()
    if cli(argv) != 0:
        raise SystemExit(f'failed: python -m mi_nerfpp {" ".join(argv)}')
    return time.perf_counter() - start


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--run', default='runs/default', help='a run folder (python optimize.py)')
    ap.add_argument('--frames', type=int, default=60)
    ap.add_argument('--res', default='320x180')
    a = ap.parse_args()
    import ray
    cpus = os.cpu_count()
    ray.init(num_cpus=cpus, include_dashboard=False, configure_logging=False)
    configs = [('single process', []),
               ('ray 1 x 1 CPU', ['--ray', '--workers', '1', '--worker-cpus', '1']),
               ('ray 2 x 1 CPU', ['--ray', '--workers', '2', '--worker-cpus', '1']),
               (f'ray 1 x {cpus} CPUs', ['--ray', '--workers', '1', '--worker-cpus', str(cpus)])]
    seconds = {}
    with tempfile.TemporaryDirectory() as tmp:
        for i, (_, extra) in enumerate(configs):          # warm the kernel cache, untimed
            video(a.run, 2, a.res, os.path.join(tmp, f'warm{i}.mp4'), extra)
        for i, (label, extra) in enumerate(configs):
            seconds[label] = video(a.run, a.frames, a.res, os.path.join(tmp, f'{i}.mp4'), extra)
    ray.shutdown()

    fpm = {label: 60 * a.frames / s for label, s in seconds.items()}
    print(f'\n{a.frames} frames at {a.res} of {a.run}, {cpus} CPUs')
    print(f'{"configuration":<18} {"seconds":>8} {"frames/min":>11}')
    for label in seconds:
        print(f'{label:<18} {seconds[label]:8.1f} {fpm[label]:11.1f}')
    efficiency = fpm['ray 2 x 1 CPU'] / (2 * fpm['ray 1 x 1 CPU'])
    overhead = (seconds[configs[3][0]] - seconds['single process']) / a.frames
    print(f'scaling efficiency, 2 workers against 1: {100 * efficiency:.0f} %')
    print(f'overhead of Ray per frame against the single process ({cpus} CPUs each): '
          f'{1000 * overhead:+.0f} ms')
    bench.write_results('cluster', 'Video frames in one process and on a local Ray cluster', [
        bench.table(f'{a.frames} frames at {a.res} (PNG + multi-layer EXR each)',
                    ['configuration', 'seconds', 'frames/min'],
                    [[label, seconds[label], fpm[label]] for label in seconds]),
        bench.table('Scaling', ['2 workers against 1: efficiency (%)',
                                f'Ray overhead per frame, {cpus} CPUs (ms)'],
                    [[100 * efficiency, 1000 * overhead]])],
        notes=f'Run {a.run}; each timing is a whole video command with warm kernels.')


if __name__ == '__main__':
    main()
