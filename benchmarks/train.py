"""Training throughput at the default settings: iterations/s, samples/s, peak RSS.

    python benchmarks/train.py [DATA] [--steps 60] [--warmup 10] [any optimize training option]

Without DATA the embedded default capture is used (synthesized and cached on first use).
A step is forward + backward + Adam on one batch of random rays. The first ``--warmup``
steps (kernel compilation, allocator warm-up) are not counted; the median step time of
the rest is reported, and the mean (which includes the periodic occupancy refresh). Every
training option of ``optimize`` is accepted, with the same defaults. Samples are field evaluations: (coarse + fine) per volume per ray.
"""
import argparse
import resource
import statistics
import time

import mi_nerfpp  # noqa: F401
import drjit as dr

from mi_nerfpp.data import load_dataset
from mi_nerfpp.synth import default_capture
from mi_nerfpp.options import add_options, values
from mi_nerfpp.train import TrainConfig, Trainer


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('data', nargs='?')
    ap.add_argument('--steps', type=int, default=60)
    ap.add_argument('--warmup', type=int, default=10)
    ap.add_argument('--out', default='/tmp/mi_nerfpp_bench_train')
    add_options(ap, TrainConfig)             # every optimize training option, same defaults
    a = ap.parse_args()

    dataset = load_dataset(a.data or default_capture())
    options = dict(values(a, TrainConfig), checkpoint_every=0, preview_every=0, minutes=None,
                   iterations=a.steps + a.warmup)
    cfg = TrainConfig(**options)
    a.model, a.field = cfg.model, cfg.field
    tr = Trainer(dataset, a.out, cfg)
    times = []
    for i in range(a.steps + a.warmup):
        t0 = time.perf_counter()
        tr.step()
        dr.sync_thread()
        if i >= a.warmup:
            times.append(time.perf_counter() - t0)
    t = statistics.median(times)
    mean = statistics.mean(times)
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
    print(f'mean step {mean * 1e3:.1f} ms (includes the occupancy refresh every '
          f'{cfg.occupancy_every} steps when on)')
    print(f'from the mean: iterations/s: {1 / mean:.2f}   rays/s: {cfg.batch_rays / mean:,.0f}   '
          f'samples/s: {cfg.batch_rays * cfg.samples_per_ray / mean / 1e6:.2f} M')
    print(f'peak RSS: {rss:.0f} MiB')


if __name__ == '__main__':
    main()
