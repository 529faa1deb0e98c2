"""Render throughput of the nerfpp integrator (forward only), warm, median of several runs.

    python benchmarks/render.py [--width 1280 --height 720] [--runs 3] [--field grid]
                                [--fg-samples 64 --bg-samples 64 --fine-samples 128]
    python benchmarks/render.py --run runs/default [--width 1280 --height 720]

Without ``--run``, seeded random fields (no occupancy grid, nothing opaque) are rendered
from a fixed camera with the given sample counts. With ``--run DIR``, the trained model
of a run is rendered through its ``DIR/render.xml`` (its first held-out camera, its
sample counts, its occupancy grids), with the film resized to ``--width x --height``.

Prints seconds per frame, rays/s, samples/s (field evaluations: (coarse + fine) per
volume per ray) and the process's peak RSS. The first (cold) run compiles kernels
and is reported separately. Results: ``benchmarks/results/render.json`` (``render_run.json``
with ``--run``).
"""
import argparse
import statistics
import time

import mi_nerfpp  # noqa: F401
import drjit as dr
import mitsuba as mi
from mi_nerfpp.jobs import bench
from mi_nerfpp.core.render import Sampling


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--width', type=int, default=1280)
    ap.add_argument('--height', type=int, default=720)
    ap.add_argument('--runs', type=int, default=3, help='warm runs (after one cold run)')
    ap.add_argument('--field', default='grid', choices=['grid', 'nerf', 'vanilla'])
    ap.add_argument('--fg-samples', type=int, default=Sampling().fg_samples)
    ap.add_argument('--bg-samples', type=int, default=Sampling().bg_samples)
    ap.add_argument('--fine-samples', type=int, default=Sampling().fine_samples)
    ap.add_argument('--chunk-rays', type=int, default=1 << 15)
    ap.add_argument('--spp', type=int, default=1, help='rays per pixel (a frame = 1)')
    ap.add_argument('--run', help='a run folder: render its render.xml (trained model)')
    a = ap.parse_args()

    if a.run:
        scene = run_scene(a.run, a.width, a.height, a.spp)
        integrator = scene.integrator()
        a.fg_samples, a.bg_samples = integrator.sampling.fg_samples, integrator.sampling.bg_samples
        a.fine_samples = integrator.sampling.fine_samples
        a.field = integrator.model.fg.kind
    else:
        scene = random_scene(a)
    rays = a.width * a.height * a.spp
    samples = rays * (a.fg_samples + a.bg_samples + 2 * a.fine_samples)
    measure(scene, a, rays, samples)


def run_scene(run, width, height, spp):
    """The run's render.xml with its film resized (and ``spp`` samples per pixel)."""
    import os
    import re
    path = os.path.join(run, 'render.xml')
    with open(path) as f:
        xml = f.read()
    xml = re.sub(r'(<integer name="width" value=")\d+', rf'\g<1>{width}', xml)
    xml = re.sub(r'(<integer name="height" value=")\d+', rf'\g<1>{height}', xml)
    xml = re.sub(r'(<integer name="sample_count" value=")\d+', rf'\g<1>{spp}', xml)
    resized = os.path.join(run, 'render_benchmark.xml')
    with open(resized, 'w') as f:
        f.write(xml)
    return mi.load_file(resized)


def random_scene(a):
    return mi.load_dict({
        'type': 'scene',
        'integrator': {'type': 'nerfpp', 'field': a.field, 'fg_samples': a.fg_samples,
                       'bg_samples': a.bg_samples, 'fine_samples': a.fine_samples,
                       'chunk_rays': a.chunk_rays},
        'sensor': {'type': 'perspective', 'fov': 60,
                   'to_world': mi.ScalarTransform4f().look_at([0, 0.2, 0.8], [0, 0, 0], [0, 1, 0]),
                   'sampler': {'type': 'independent', 'sample_count': a.spp},
                   'film': {'type': 'hdrfilm', 'width': a.width, 'height': a.height,
                            'rfilter': {'type': 'box'}, 'pixel_format': 'rgba'}}})


def measure(scene, a, rays, samples):
    def run():
        t0 = time.perf_counter()
        img = mi.render(scene, seed=0)
        dr.eval(img)
        dr.sync_thread()
        return time.perf_counter() - t0

    cold = run()
    times = [run() for _ in range(a.runs)]
    t = statistics.median(times)
    rss = bench.peak_rss_mib()
    n_params = scene.integrator().model.n_parameters()
    print(f'frame {a.width}x{a.height} at {a.spp} spp, field={a.field} ({n_params / 1e6:.2f} M parameters), '
          f'samples per ray: fg {a.fg_samples}+{a.fine_samples}, bg {a.bg_samples}+{a.fine_samples}'
          + (f' (trained model of {a.run}; samples/s counts the full budget, before skipping)' if a.run else ''))
    print(f'cold run (kernel compilation included): {cold:.2f} s')
    print(f'warm runs: {", ".join(f"{x:.2f}" for x in times)} s -> median {t:.2f} s per frame')
    print(f'rays/s: {rays / t / 1e6:.3f} M   samples/s: {samples / t / 1e6:.2f} M')
    print(f'peak RSS: {rss:.0f} MiB')
    what = f'trained model of {a.run}' if a.run else f'random {a.field} fields'
    bench.write_results('render_run' if a.run else 'render', 'Render throughput', [
        bench.table(f'{a.width}x{a.height} at {a.spp} spp, {what}',
                    ['samples per ray (fg, bg, fine)', 'cold (s)', 'median warm (s)',
                     'M rays/s', 'M samples/s', 'peak RSS (MiB)'],
                    [[f'{a.fg_samples} {a.bg_samples} {a.fine_samples}', cold, t,
                      rays / t / 1e6, samples / t / 1e6, rss]],
                    note=f'Median of {a.runs} warm runs after one cold run (kernel compilation); '
                         f'samples/s counts the full budget'
                         + (', before skipping empty space.' if a.run else '.'))],
        notes=f'{n_params / 1e6:.2f} M parameters.')


if __name__ == '__main__':
    main()
