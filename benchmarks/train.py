"""Training throughput at the default settings: iterations/s, samples/s, peak RSS.

    python benchmarks/train.py [DATA] [--steps 60] [--warmup 10] [--batch-rays 1024]
                               [--samples FG BG FINE] [--model nerfpp|nerf] [--field grid]

Without DATA the embedded default capture is used (synthesized and cached on first use).
A step is forward + backward + Adam on one batch of random rays. The first ``--warmup``
steps (kernel compilation, allocator warm-up) are not counted; the median step time of
the rest is reported. Samples are field evaluations: (coarse + fine) per volume per ray.
"""
import argparse
import resource
import statistics
import time

import mi_nerfpp  # noqa: F401
import drjit as dr

from mi_nerfpp.data import load_dataset
from mi_nerfpp.synth import default_capture
from mi_nerfpp.train import TrainConfig, Trainer


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('data', nargs='?')
    ap.add_argument('--steps', type=int, default=60)
    ap.add_argument('--warmup', type=int, default=10)
    ap.add_argument('--batch-rays', type=int, default=TrainConfig.batch_rays)
    ap.add_argument('--samples', type=int, nargs=3, default=[TrainConfig.fg_samples,
                                                             TrainConfig.bg_samples,
                                                             TrainConfig.fine_samples])
    ap.add_argument('--model', default='nerfpp', choices=['nerfpp', 'nerf'])
    ap.add_argument('--field', default='grid', choices=['grid', 'nerf', 'vanilla'])
    ap.add_argument('--out', default='/tmp/mi_nerfpp_bench_train')
    a = ap.parse_args()

    dataset = load_dataset(a.data or default_capture())
    fg, bg, fine = a.samples
    cfg = TrainConfig(iterations=a.steps + a.warmup, model=a.model, field=a.field,
                      batch_rays=a.batch_rays, fg_samples=fg, bg_samples=bg, fine_samples=fine,
                      checkpoint_every=0, preview_every=0)
    tr = Trainer(dataset, a.out, cfg)
    times = []
    for i in range(a.steps + a.warmup):
        t0 = time.perf_counter()
        tr.step()
        dr.sync_thread()
        if i >= a.warmup:
            times.append(time.perf_counter() - t0)
    t = statistics.median(times)
    n_params = tr.model.n_parameters()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f'dataset {dataset.root}: {tr.rays.size} training rays; model={a.model} field={a.field} '
          f'({n_params / 1e6:.2f} M parameters)')
    print(f'batch {cfg.batch_rays} rays x {cfg.samples_per_ray} samples per ray '
          f'(fg {cfg.sampling.fg_samples}+{cfg.sampling.fine_samples}'
          + ('' if a.model == 'nerf' else f', bg {cfg.sampling.bg_samples}+{cfg.sampling.fine_samples}')
          + ')')
    print(f'median step {t * 1e3:.1f} ms over {len(times)} warm steps '
          f'(p10 {statistics.quantiles(times, n=10)[0] * 1e3:.1f}, '
          f'p90 {statistics.quantiles(times, n=10)[-1] * 1e3:.1f})')
    print(f'iterations/s: {1 / t:.2f}   rays/s: {cfg.batch_rays / t:,.0f}   '
          f'samples/s: {cfg.batch_rays * cfg.samples_per_ray / t / 1e6:.2f} M')
    print(f'peak RSS: {rss:.0f} MiB')


if __name__ == '__main__':
    main()
