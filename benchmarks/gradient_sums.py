"""How a training step sums its gradients into the grids: atomic adds against Dr.Jit's "expand"
mode (a copy of each large grid per thread, added up after the kernel), late in a run.

    python benchmarks/gradient_sums.py RUN [--at 0.9] [--rounds 8] [--block 32]

Two trainers resume the run ``RUN`` (a finished ``optimize`` run on the embedded default
capture or its own dataset) with a budget that puts them at fraction ``--at`` of it: the image
pyramid at full size and the priors of that phase on, the occupancy grids as trained (samples
concentrated on the surfaces, unlike the first steps of a run that ``benchmarks/train.py``
measures). One sums by atomics, the other in expand mode; they take turns, ``--block`` steps at a
time for ``--rounds`` rounds (the order swapped each round; the first round is not counted), so
both see the same machine. Prints and writes ``benchmarks/results/gradient_sums.json``.
"""
import argparse
import shutil
import statistics
import tempfile
import time

import mi_nerfpp  # noqa: F401
import drjit as dr

import mi_nerfpp.training.train as T
from mi_nerfpp.jobs import bench
from mi_nerfpp.files.checkpoint import load_checkpoint
from mi_nerfpp.training.config import TrainConfig
from mi_nerfpp.data import load_dataset

MODES = {'atomic adds': 1 << 62, 'expand (a copy per thread)': 0}   # EXPAND_MIN_SAMPLES


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('run')
    ap.add_argument('--at', type=float, default=0.9, help='fraction of the run to resume at')
    ap.add_argument('--rounds', type=int, default=8)
    ap.add_argument('--block', type=int, default=32)
    a = ap.parse_args()

    _, meta, _ = load_checkpoint(f'{a.run}/model.npz')
    options = TrainConfig.stored_options(meta['config'])
    # A time budget that puts the run's elapsed time at fraction --at of it.
    options.update(iterations=None, minutes=float(meta['elapsed']) / 60.0 / a.at,
                   checkpoint_every=0, preview_every=0)
    cfg = TrainConfig.from_options(**options)
    dataset = load_dataset(meta['dataset'])
    work = tempfile.mkdtemp(prefix='gradient_sums_')
    trainers = {}
    for i, mode in enumerate(MODES):
        folder = f'{work}/{i}'
        shutil.copytree(a.run, folder)
        trainers[mode] = T.Trainer(dataset, folder, cfg, resume=True)
    times = {mode: [] for mode in MODES}
    for r in range(a.rounds):
        for mode in (list(MODES) if r % 2 == 0 else list(MODES)[::-1]):
            T.EXPAND_MIN_SAMPLES = MODES[mode]
            tr = trainers[mode]
            for _ in range(a.block):
                t0 = time.perf_counter()
                tr.step()
                dr.sync_thread()
                if r > 0:
                    times[mode].append(time.perf_counter() - t0)
    shutil.rmtree(work, ignore_errors=True)
    rows = []
    for mode, t in times.items():
        median, mean = 1e3 * statistics.median(t), 1e3 * statistics.mean(t)
        print(f'{mode}: median step {median:.1f} ms, mean {mean:.1f} ms over {len(t)} steps')
        rows.append([mode, median, mean, cfg.schedule.batch_rays / statistics.mean(t)])
    occupied = {k: g.fraction() for k, g in next(iter(trainers.values())).model.occupancy.items()}
    bench.write_results('gradient_sums', 'Gradient sums late in a run: atomics against expand', [
        bench.table('Training step, alternating', ['gradient sums', 'median step (ms)',
                                                   'mean step (ms)', 'rays/s'], rows,
                    note=f'{a.rounds - 1} counted rounds of {a.block} steps each, the order '
                         f'swapped each round; resumed at {a.at:.0%} of the run (iteration '
                         f"{meta['iteration']}); occupied cells: "
                         + ', '.join(f'{k} {v:.1%}' for k, v in occupied.items()) + '.')],
        notes=f"{cfg.schedule.batch_rays} rays x {cfg.samples_per_ray} samples per step; "
              f"dataset {meta['dataset']}.")


if __name__ == '__main__':
    main()
