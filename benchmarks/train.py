"""Training throughput at the default settings: iterations/s, samples/s, peak RSS.

    python benchmarks/train.py [DATA] [--steps 60] [--warmup 10] [any optimize training option]
    python benchmarks/train.py --alternate freeze [--steps 120] [--block 20]

Without DATA the embedded default capture is used (synthesized and cached on first use).
A step is forward + backward + Adam on one batch of random rays. The first ``--warmup``
steps (kernel compilation, allocator warm-up) are not counted; the median step time of
the rest is reported, and the mean (which includes the periodic occupancy refresh). Every
training option of ``optimize`` is accepted, with the same defaults. Samples are field evaluations: (coarse + fine) per volume per ray.

``--alternate OPTION`` (a yes/no training option, e.g. ``freeze``) compares the option off and
on in one process: two trainers from the same seed take turns, ``--block`` steps at a time
(the order swapped each round), so both see the same machine; it prints the median and mean
step of each (``--steps`` warm steps each). Peak RSS is then that of both together.
"""
import argparse
import dataclasses
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
    ap.add_argument('--alternate', metavar='OPTION',
                    help='compare this yes/no training option off and on, alternating in blocks')
    ap.add_argument('--block', type=int, default=20, help='steps per block with --alternate')
    add_options(ap, TrainConfig)             # every optimize training option, same defaults
    a = ap.parse_args()

    dataset = load_dataset(a.data or default_capture())
    options = dict(values(a, TrainConfig), checkpoint_every=0, preview_every=0, minutes=None,
                   iterations=a.steps + a.warmup)
    cfg = TrainConfig(**options)
    a.model, a.field = cfg.model, cfg.field
    if a.alternate:
        return alternate(dataset, cfg, a)
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


def alternate(dataset, cfg, a):
    name = a.alternate.replace('-', '_')
    if not isinstance(getattr(cfg, name, None), bool):
        raise SystemExit(f'--alternate: {a.alternate!r} is not a yes/no training option')
    trainers = {on: Trainer(dataset, f'{a.out}_{name}_{on}', dataclasses.replace(cfg, **{name: on}))
                for on in (False, True)}
    for tr in trainers.values():
        for _ in range(a.warmup):
            tr.step()
        dr.sync_thread()
    times = {False: [], True: []}
    rounds = -(-a.steps // a.block)
    for r in range(rounds):
        for on in ((False, True) if r % 2 == 0 else (True, False)):
            for _ in range(a.block):
                t0 = time.perf_counter()
                trainers[on].step()
                dr.sync_thread()
                times[on].append(time.perf_counter() - t0)
    for on in (False, True):
        t = times[on]
        print(f'--{"" if on else "no-"}{a.alternate}: median step {statistics.median(t) * 1e3:.1f} ms, '
              f'mean {statistics.mean(t) * 1e3:.1f} ms over {len(t)} warm steps '
              f'({cfg.batch_rays / statistics.mean(t):,.0f} rays/s from the mean)')
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f'{rounds} rounds of {a.block} steps each, alternating; peak RSS of both: {rss:.0f} MiB')


if __name__ == '__main__':
    main()
