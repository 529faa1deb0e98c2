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

Results: ``benchmarks/results/train.json`` (``train_alternate_<option>.json`` with
``--alternate``).
"""
import argparse
import statistics
import time

import mi_nerfpp  # noqa: F401
import drjit as dr

from mi_nerfpp.jobs import bench, run
from mi_nerfpp.training.config import TrainConfig
from mi_nerfpp.training.options import add_options, values
from mi_nerfpp.data.synth import default_capture

# Set by this benchmark for every run (not a setting it measures).
RUN_OPTIONS = ('checkpoint_every', 'preview_every', 'iterations', 'minutes', 'eval_at',
               'downscale')


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

    options = dict(values(a, TrainConfig), checkpoint_every=0, preview_every=0, minutes=None,
                   iterations=a.steps + a.warmup, eval_at=())
    inputs = run.prepare(a.data or default_capture(), TrainConfig.from_options(**options),
                         a.out, overwrite=True)
    dataset, cfg = inputs.dataset, inputs.config
    a.model, a.field = cfg.model.kind, cfg.model.field
    if a.alternate:
        return alternate(inputs, a)
    tr = run.start(inputs)
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
    rss = bench.peak_rss_mib()
    batch, per_ray, s = cfg.schedule.batch_rays, cfg.samples_per_ray, tr.model.sampling
    p10, p90 = statistics.quantiles(times, n=10)[0], statistics.quantiles(times, n=10)[-1]
    print(f'dataset {dataset.root}: {tr.rays.size} training rays; model={a.model} field={a.field} '
          f'({n_params / 1e6:.2f} M parameters)')
    print(f'batch {batch} rays x {per_ray} samples per ray '
          f'(fg {s.fg_samples}+{s.fine_samples}'
          + ('' if a.model == 'nerf' else f', bg {s.bg_samples}+{s.fine_samples}') + ')')
    print(f'median step {t * 1e3:.1f} ms over {len(times)} warm steps '
          f'(p10 {p10 * 1e3:.1f}, p90 {p90 * 1e3:.1f})')
    print(f'mean step {mean * 1e3:.1f} ms (includes the occupancy refresh every '
          f'{cfg.sampling.occupancy_every} steps when on)')
    print(f'from the mean: iterations/s: {1 / mean:.2f}   rays/s: {batch / mean:,.0f}   '
          f'samples/s: {batch * per_ray / mean / 1e6:.2f} M')
    print(f'peak RSS: {rss:.0f} MiB')
    setting = bench.changed_options(cfg, ignore=RUN_OPTIONS)
    bench.write_results('train', 'Training throughput', [bench.table(
        'Training step', ['setting', 'median step (ms)', 'p10 (ms)', 'p90 (ms)', 'mean step (ms)',
                          'iterations/s', 'rays/s', 'M samples/s', 'peak RSS (MiB)'],
        [[setting, 1e3 * t, 1e3 * p10, 1e3 * p90, 1e3 * mean, 1 / mean, batch / mean,
          batch * per_ray / mean / 1e6, rss]],
        note=f'{len(times)} warm steps after {a.warmup} not counted; the mean includes the '
             f'occupancy refresh every {cfg.sampling.occupancy_every} steps.')],
        notes=f'Dataset {dataset.root}: {tr.rays.size} training rays; model={a.model} '
              f'field={a.field} ({n_params / 1e6:.2f} M parameters); batch {batch} rays x '
              f'{per_ray} samples per ray (field evaluations: coarse + fine per volume).')


def alternate(inputs, a):
    cfg = inputs.config
    name = a.alternate.replace('-', '_')
    if not isinstance(cfg.options().get(name), bool):
        raise SystemExit(f'--alternate: {a.alternate!r} is not a yes/no training option')
    trainers = {}
    for on in (False, True):
        folder = f'{a.out}_{name}_{on}'
        run.check_run_folder(folder, resume=False, overwrite=True)
        trainers[on] = run.start(run.RunInputs(inputs.data, inputs.dataset,
                                               cfg.replace(**{name: on}), folder))
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
    rows = []
    for on in (False, True):
        t = times[on]
        label = f'--{"" if on else "no-"}{a.alternate}'
        rays = cfg.schedule.batch_rays / statistics.mean(t)
        print(f'{label}: median step {statistics.median(t) * 1e3:.1f} ms, '
              f'mean {statistics.mean(t) * 1e3:.1f} ms over {len(t)} warm steps '
              f'({rays:,.0f} rays/s from the mean)')
        rows.append([label, 1e3 * statistics.median(t), 1e3 * statistics.mean(t), rays])
    rss = bench.peak_rss_mib()
    print(f'{rounds} rounds of {a.block} steps each, alternating; peak RSS of both: {rss:.0f} MiB')
    bench.write_results(f'train_alternate_{name}',
                        f'Training step with --{a.alternate} off and on', [
        bench.table('Training step, alternating',
                    ['setting', 'median step (ms)', 'mean step (ms)', 'rays/s'], rows,
                    note=f'{rounds} rounds of {a.block} steps each, the order swapped each round; '
                         f'{len(times[True])} warm steps each; peak RSS of both {rss:.0f} MiB.')])


if __name__ == '__main__':
    main()
