"""Where a training step's and a render's time goes: kernels by stage and kind, launches, cores.

    python benchmarks/profile.py [--data DATA] [--steps 20] [--warmup 20] [--run RUN]
                                 [--width 1280 --height 720] [-- name=value ...]

Training (the default capture without DATA, default options; ``name=value`` sets options of the
training config): after ``--warmup`` steps, ``--steps`` steps are traced without
``drjit.freeze`` under a :class:`mi_nerfpp.profiling.KernelProfile`, which attributes every
kernel to the stage that launched it (occupancy refresh and sampling, field evaluations,
deferred colour, losses and the reverse pass, Adam) and tells the reverse pass's kernels apart by
kind (gradient scatters into the grids, memsets, block reductions, matrix products). Then the
same number of frozen steps (how training runs) are timed: wall time, kernel launches and
kernel time per step, and the cores busy (process CPU time over wall time; 2 = both cores of
this machine). With ``--run RUN`` one frame of the run's ``render.xml`` at ``--width x
--height`` (1 spp) is profiled the same way. Prints tables; writes
``benchmarks/results/profile.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import mi_nerfpp  # noqa: F401
import drjit as dr
import mitsuba as mi

from mi_nerfpp.profiling import KernelProfile

def cores_busy(fn):
    """``(wall seconds, cores busy)`` of ``fn()``."""
    c0, t0 = time.process_time(), time.perf_counter()
    fn()
    dr.sync_thread()
    wall = time.perf_counter() - t0
    return wall, (time.process_time() - c0) / wall


def stage_rows(profile, per):
    """Table rows ``[stage, kind, ms per unit, launches per unit]``, largest first."""
    rows = []
    for name, kinds in profile.by_stage().items():
        for kind, (ms, n) in kinds.items():
            rows.append([name, kind, round(ms / per, 2), round(n / per, 1)])
    return sorted(rows, key=lambda r: -r[2])


def print_table(title, columns, rows):
    print(f'\n{title}')
    print('  ' + ' | '.join(columns))
    for r in rows:
        print('  ' + ' | '.join(str(v) for v in r))


def profile_training(dataset, options, steps, warmup):
    from mi_nerfpp.config import TrainConfig
    from mi_nerfpp.train import Trainer
    out = {}
    for freeze in (False, True):
        cfg = TrainConfig.from_options(iterations=10 ** 9, checkpoint_every=0, preview_every=0,
                                       **dict(options, freeze=freeze))
        trainer = Trainer(dataset, f'/tmp/mi_nerfpp_profile_{freeze}', cfg)
        for _ in range(warmup):
            trainer.step()
        dr.sync_thread()
        if not freeze:
            with KernelProfile() as profile:
                wall, busy = cores_busy(lambda: [trainer.step() for _ in range(steps)])
            out['stages'] = stage_rows(profile, steps)
            out['traced'] = {'step_ms': 1e3 * wall / steps, 'cores_busy': busy,
                             'launches': profile.launches() / steps}
        else:
            times = []
            with KernelProfile() as profile:
                c0, t0 = time.process_time(), time.perf_counter()
                for _ in range(steps):
                    s = time.perf_counter()
                    trainer.step()
                    dr.sync_thread()
                    times.append(time.perf_counter() - s)
                wall = time.perf_counter() - t0
                busy = (time.process_time() - c0) / wall
            kernel_ms = sum(ms for _, _, ms in profile.records) / steps
            out['frozen'] = {'step_ms': 1e3 * statistics.median(times),
                             'mean_step_ms': 1e3 * statistics.mean(times),
                             'kernel_ms': kernel_ms, 'cores_busy': busy,
                             'launches': profile.launches() / steps,
                             'rays_per_second': cfg.schedule.batch_rays / statistics.mean(times),
                             'batch_rays': cfg.schedule.batch_rays}
    return out


def render_scene(run, width, height):
    import re
    with open(os.path.join(run, 'render.xml')) as f:
        xml = f.read()
    for name, value in (('width', width), ('height', height), ('sample_count', 1)):
        xml = re.sub(rf'(<integer name="{name}" value=")\d+', rf'\g<1>{value}', xml)
    path = os.path.join(run, 'render_profile.xml')
    with open(path, 'w') as f:
        f.write(xml)
    return mi.load_file(path)


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--data', help='dataset folder (default: the embedded default capture)')
    ap.add_argument('--steps', type=int, default=20)
    ap.add_argument('--warmup', type=int, default=20)
    ap.add_argument('--run', help='also profile a render of this run folder')
    ap.add_argument('--width', type=int, default=1280)
    ap.add_argument('--height', type=int, default=720)
    ap.add_argument('options', nargs='*', help='training options as name=value')
    a = ap.parse_intermixed_args()
    from mi_nerfpp.data import load_dataset
    from mi_nerfpp.synth import default_capture
    options = {k: json.loads(v) for k, v in (o.split('=', 1) for o in a.options)}
    dataset = load_dataset(a.data or default_capture(progress=False))
    train = profile_training(dataset, options, a.steps, a.warmup)
    f, t = train['frozen'], train['traced']
    print(f"training step ({f['batch_rays']} rays): frozen {f['step_ms']:.1f} ms median "
          f"({f['rays_per_second']:,.0f} rays/s from the mean), {f['launches']:.0f} kernel "
          f"launches, {f['kernel_ms']:.1f} ms of kernels, {f['cores_busy']:.2f} cores busy; "
          f"traced in Python {t['step_ms']:.1f} ms, {t['launches']:.0f} launches, "
          f"{t['cores_busy']:.2f} cores busy")
    columns = ['stage', 'kind', 'ms per step', 'launches per step']
    print_table('kernels of a traced training step', columns, train['stages'])
    tables = [{'title': 'Training step: kernels by stage and kind (traced, per step)',
               'columns': columns, 'rows': train['stages']},
              {'title': 'Training step', 'columns': ['', 'step (ms)', 'launches', 'kernel ms',
                                                     'cores busy', 'rays/s'],
               'rows': [['frozen (as trained)', round(f['step_ms'], 1), round(f['launches']),
                         round(f['kernel_ms'], 1), round(f['cores_busy'], 2),
                         round(f['rays_per_second'])],
                        ['traced in Python', round(t['step_ms'], 1), round(t['launches']),
                         '', round(t['cores_busy'], 2), '']]}]
    raw = {'training': train}
    if a.run:
        scene = render_scene(a.run, a.width, a.height)
        mi.render(scene)            # compile
        dr.sync_thread()
        with KernelProfile() as profile:
            wall, busy = cores_busy(lambda: dr.eval(mi.render(scene)))
        rows = stage_rows(profile, 1)
        print(f'\nrender {a.width}x{a.height}, 1 spp, {a.run}: {wall:.2f} s, '
              f'{profile.launches()} launches, {busy:.2f} cores busy')
        columns = ['stage', 'kind', 'ms per frame', 'launches per frame']
        print_table('kernels of a render', columns, rows)
        tables.append({'title': f'Render {a.width}x{a.height}, 1 spp: kernels by stage and kind',
                       'columns': columns, 'rows': rows,
                       'note': f'{wall:.2f} s per frame, {profile.launches()} launches, '
                               f'{busy:.2f} cores busy'})
        raw['render'] = {'seconds': wall, 'launches': profile.launches(), 'cores_busy': busy}
    from mi_nerfpp.bench import write_results
    write_results('profile', 'Where the time goes', tables, raw=raw,
                  notes='Kernels attributed to the stage that launched them (Dr.Jit evaluates '
                        'lazily, so a stage holds the kernels it evaluates); the reverse pass '
                        'by kind. Cores busy: process CPU time over wall time.')


if __name__ == '__main__':
    main()
