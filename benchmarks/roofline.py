"""The training step against the machine's limit: what each stage achieves beside the peaks of
this machine, measured in the same run, and the rays/s with 1 and with 2 threads.

    python benchmarks/roofline.py [--data DATA] [--steps 20] [--warmup 30] [--at 0.6]
                                  [--threads 1 2] [--rounds 5] [--name roofline]
                                  [name=value ...]

**Peaks** (each the best of ``--rounds``, at each thread count):

- *arithmetic*: a Dr.Jit kernel of independent fused multiply-adds (:data:`FMA_CHAINS` chains
  of :data:`FMA_DEPTH` each per element): Dr.Jit IR operations per second, the unit the stages
  are counted in below; and float32 matrix products of NumPy's BLAS (:data:`GEMM_SIZE`², in a
  process of its own per thread count): GFLOP/s;
- *memory*: a Dr.Jit kernel that reads one array of :data:`COPY_ELEMENTS` floats and writes
  another: GB/s, read plus written.

**Stages.** A training step at the defaults (the default capture without ``DATA``;
``name=value`` sets training options), at fraction ``--at`` of a run as
``benchmarks/profile.py`` takes it: ``--steps`` steps traced without ``drjit.freeze`` under a
:class:`~mi_nerfpp.core.profiling.KernelProfile` after ``--warmup`` steps. Per stage and kind of
kernel: milliseconds a step, the share of the kernels' time, and from Dr.Jit's kernel history
(:meth:`~mi_nerfpp.core.profiling.KernelProfile.by_stage_work`) the IR operations per second
and the streaming traffic (GB/s) achieved, each beside its peak. The traffic counts the arrays a
kernel reads or writes whole and leaves out the parts that gathers and scatters touch, so it
is a lower bound; IR operations include integer and address arithmetic, so for a kernel of
gathers it overstates the arithmetic. A stage far below both peaks is bound by neither: by
latency (gathers, atomic scatters), by launches or by threads waiting.

**Threads.** Frozen steps (how training runs), timed at each ``--threads`` count, each count
in a process of its own (``drjit.set_thread_count`` before any kernel) that also measures the
peaks: the median step and the rays/s, and the scaling from the first count to the last.

Prints tables; writes ``benchmarks/results/<--name>.json`` for the benchmarks page.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import mi_nerfpp  # noqa: F401  (libLLVM, variant, plugin registration)
import drjit as dr
import mitsuba as mi

from mi_nerfpp.jobs import bench

# The arithmetic peak's kernel: independent chains of fused multiply-adds per element.
FMA_CHAINS, FMA_DEPTH, FMA_ELEMENTS = 8, 64, 1 << 22
# The memory peak's kernel: a copy of this many float32 (256 MiB read, 256 MiB written).
COPY_ELEMENTS = 1 << 26
# The matrix products' peak: float32 square matrices of this side.
GEMM_SIZE = 1536
# The kinds of kernel that issue 61 asks to shrink (Adam, gradient sums, memsets).
OPTIMISER_KINDS = ('gradient scatter', 'memset')
OPTIMISER_STAGES = ('adam',)

GEMM = '''
import sys, time
import numpy as np
n, rounds = int(sys.argv[1]), int(sys.argv[2])
a = np.random.default_rng(0).random((n, n), dtype=np.float32)
b = np.random.default_rng(1).random((n, n), dtype=np.float32)
a @ b
times = []
for _ in range(rounds):
    t0 = time.perf_counter()
    a @ b
    times.append(time.perf_counter() - t0)
print(2 * n ** 3 / min(times) / 1e9)
'''


def _kernel_ms(fn):
    """``(milliseconds, elements x IR operations)`` of the kernels ``fn`` launches."""
    dr.sync_thread()
    flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history_clear()
    try:
        fn()
        dr.sync_thread()
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, flag)
    return (sum(float(k.get('execution_time', 0.0)) for k in history),
            sum(int(k.get('size', 0)) * int(k.get('operation_count', 0)) for k in history))


def fma_peak(rounds):
    """Dr.Jit IR operations per second of an FMA-bound kernel (best of ``rounds``)."""
    def run():
        x = dr.arange(mi.Float, FMA_ELEMENTS) * dr.opaque(mi.Float, 1e-7)
        chains = [x + dr.opaque(mi.Float, float(i)) for i in range(FMA_CHAINS)]
        a, b = dr.opaque(mi.Float, 0.999), dr.opaque(mi.Float, 1e-3)
        for _ in range(FMA_DEPTH):
            chains = [dr.fma(c, a, b) for c in chains]
        dr.eval(sum(chains[1:], chains[0]))
    run()
    best = max((ops / (ms * 1e-3) for ms, ops in (_kernel_ms(run) for _ in range(rounds))
                if ms > 0), default=0.0)
    return best / 1e9


def copy_peak(rounds):
    """GB/s (read plus written) of a Dr.Jit kernel that copies one float32 array to another."""
    source = dr.arange(mi.Float, COPY_ELEMENTS)
    dr.eval(source)
    scale = dr.opaque(mi.Float, 1.0)

    def run():
        dr.eval(source * scale)
    run()
    best = min(ms for ms, _ in (_kernel_ms(run) for _ in range(rounds)))
    return 2 * 4 * COPY_ELEMENTS / (best * 1e-3) / 1e9


def gemm_peak(threads, rounds):
    """GFLOP/s of NumPy's float32 matrix product on ``threads`` BLAS threads."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS=str(threads), OMP_NUM_THREADS=str(threads),
               MKL_NUM_THREADS=str(threads))
    out = subprocess.run([sys.executable, '-c', GEMM, str(GEMM_SIZE), str(rounds)], env=env,
                         check=True, stdout=subprocess.PIPE, text=True).stdout
    return float(out.strip().splitlines()[-1])


def peaks(threads, rounds):
    """``{'fma': Gop/s, 'copy': GB/s, 'gemm': GFLOP/s}`` on this process's threads."""
    return {'fma': fma_peak(rounds), 'copy': copy_peak(rounds),
            'gemm': gemm_peak(threads, rounds)}


def trainer_of(data, options, freeze, at):
    from mi_nerfpp.data import load_dataset
    from mi_nerfpp.data.synth import default_capture
    from mi_nerfpp.training.config import TrainConfig
    from mi_nerfpp.training.train import Trainer
    dataset = load_dataset(data or default_capture(progress=False))
    cfg = TrainConfig.from_options(iterations=10 ** 9, checkpoint_every=0, preview_every=0,
                                   **dict(options, freeze=freeze))
    trainer = Trainer(dataset, tempfile.mkdtemp(prefix='mi_nerfpp_roofline_'), cfg)
    trainer.iteration = int(at * 10 ** 9)      # the phase of the run (see --at)
    return trainer, cfg.schedule.batch_rays


def stages(data, options, steps, warmup, at):
    """``(rows by (stage, kind): [ms, launches, ops, bytes] per step, traced step ms)``."""
    from mi_nerfpp.core.profiling import KernelProfile
    trainer, _ = trainer_of(data, options, False, at)
    for _ in range(warmup):
        trainer.step()
    dr.sync_thread()
    with KernelProfile() as profile:
        t0 = time.perf_counter()
        for _ in range(steps):
            trainer.step()
        dr.sync_thread()
        wall = time.perf_counter() - t0
    work = {key: [None if v is None else v / steps for v in values]
            for key, values in profile.by_stage_work().items()}
    return work, 1e3 * wall / steps


def rays_per_second(data, options, steps, warmup, at):
    """``(median step ms, rays/s)`` of frozen steps on this process's threads."""
    trainer, batch = trainer_of(data, options, True, at)
    for _ in range(warmup):
        trainer.step()
    dr.sync_thread()
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        trainer.step()
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
    step = statistics.median(times)
    return 1e3 * step, batch / step


def worker(job):
    """One thread count in a process of its own (Dr.Jit's thread pool is sized before any
    kernel runs, as the cluster's workers size it): its peaks and its frozen steps, as JSON."""
    dr.set_thread_count(job['threads'])
    out = {'peaks': peaks(job['threads'], job['rounds'])}
    out['step_ms'], out['rays_per_second'] = rays_per_second(
        job['data'], job['options'], job['steps'], job['warmup'], job['at'])
    print(json.dumps(out))


def measure_threads(job):
    out = subprocess.run([sys.executable, os.path.abspath(__file__), '--worker',
                          json.dumps(job)], check=True, stdout=subprocess.PIPE,
                         text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('options', nargs='*', metavar='name=value')
    parser.add_argument('--data', help='a capture (default: the embedded default capture)')
    parser.add_argument('--steps', type=int, default=20)
    parser.add_argument('--warmup', type=int, default=30)
    parser.add_argument('--at', type=float, default=0.6)
    parser.add_argument('--threads', type=int, nargs='+', default=None,
                        help='thread counts (default: 1 and all of this machine\'s)')
    parser.add_argument('--rounds', type=int, default=5)
    parser.add_argument('--name', default='roofline')
    parser.add_argument('--worker', help=argparse.SUPPRESS)
    args = parser.parse_intermixed_args()
    if args.worker:
        return worker(json.loads(args.worker))
    options = {k: json.loads(v) for k, v in (o.split('=', 1) for o in args.options)}
    counts = args.threads or sorted({1, os.cpu_count() or 1})
    most = max(counts)

    job = {'data': args.data and os.path.abspath(args.data), 'options': options,
           'steps': args.steps, 'warmup': args.warmup, 'at': args.at, 'rounds': args.rounds}
    threads = {t: measure_threads(dict(job, threads=t)) for t in counts}
    peak = {t: v['peaks'] for t, v in threads.items()}
    speeds = {t: (v['step_ms'], v['rays_per_second']) for t, v in threads.items()}
    dr.set_thread_count(most)
    work, traced_ms = stages(args.data, options, args.steps, args.warmup, args.at)

    peak_rows = [[t, round(p['fma'], 2), round(p['copy'], 2), round(p['gemm'], 2)]
                 for t, p in peak.items()]
    total = sum(v[0] for v in work.values()) or 1.0
    top = peak[most]
    stage_rows = []
    for (path, kind), (ms, launches, ops, nbytes) in sorted(work.items(), key=lambda kv: -kv[1][0]):
        rates = []
        for amount, peak_rate in ((ops, top['fma']), (nbytes, top['copy'])):
            if amount is None or ms <= 0:
                rates += ['', '']          # not estimated (matrix products, copies)
                continue
            rate = amount / (ms * 1e-3) / 1e9
            rates += [round(rate, 2), round(100 * rate / peak_rate, 1) if peak_rate else '']
        stage_rows.append([path, kind, round(ms, 2), round(100 * ms / total, 1),
                           round(launches, 1), *rates])
    optimiser = sum(ms for (path, kind), (ms, *_) in work.items()
                    if kind in OPTIMISER_KINDS or path.split(' / ')[0] in OPTIMISER_STAGES)
    first, last = min(counts), max(counts)
    speed_rows = [[t, round(ms, 2), round(rays), round(speeds[t][1] / speeds[first][1], 2)]
                  for t, (ms, rays) in speeds.items()]

    tables = [
        bench.table('Peaks of this machine, measured in the same run',
                    ['threads', 'FMA kernel (G IR ops/s)', 'copy kernel (GB/s, read + written)',
                     'float32 matrix product, NumPy BLAS (GFLOP/s)'], peak_rows),
        bench.table(f'A training step by stage and kind of kernel, {most} threads (traced '
                    f'steps, {traced_ms:.1f} ms a step with the tracing)',
                    ['stage', 'kind', 'ms a step', 'share of kernel time (%)', 'launches',
                     'G IR ops/s', '% of the FMA peak', 'GB/s streamed (lower bound)',
                     '% of the copy peak'], stage_rows,
                    note=f'Adam, gradient scatters and memsets: {100 * optimiser / total:.1f} % '
                         f'of the kernel time ({optimiser:.2f} of {total:.2f} ms a step).'),
        bench.table('Frozen training steps by thread count',
                    ['threads', 'median step (ms)', 'rays/s', f'rays/s against {first} thread'],
                    speed_rows),
    ]
    for table in tables:
        print(f"\n{table['title']}")
        print('  ' + ' | '.join(table['columns']))
        for row in table['rows']:
            print('  ' + ' | '.join(str(v) for v in row))
        if table.get('note'):
            print('  ' + table['note'])
    raw = {'peaks': {str(k): v for k, v in peak.items()},
           'stages': [[p, k, *v] for (p, k), v in work.items()],
           'threads': {str(k): v for k, v in speeds.items()}, 'options': options,
           'optimiser_share': optimiser / total, 'scaling': speeds[last][1] / speeds[first][1]}
    path = bench.write_results(args.name, 'The training step against the machine\'s limit',
                               tables, raw=raw, notes=(
                                   'Peaks and steps measured in one run (a process per '
                                   'thread count), alone on the machine; IR operations and streamed bytes from Dr.Jit\'s '
                                   'kernel history (benchmarks/roofline.py explains both '
                                   'estimates).'))
    print(f'\nwrote {path}')


if __name__ == '__main__':
    main()
