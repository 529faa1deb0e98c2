"""Where a training step's and a render's time goes: kernels by stage and kind, launches, cores.

    python benchmarks/profile.py [--data DATA] [--steps 20] [--warmup 20] [--run RUN]
                                 [--resume RUN] [--width 1280 --height 720]
                                 [--base REV --base-run RUN --base-resume RUN] [name=value ...]

Training (the default capture without DATA, default options with what ``optimize.py`` chooses
from the capture; ``name=value`` sets options of the training config; ``--resume RUN``: from
that trained run's checkpoint, whose sparse levels hold the bricks training left them, where a
fresh model holds every brick), at fraction ``--at`` of a run (0.6: past the schedule's phases, as
``benchmarks/versus.py train``): after ``--warmup`` steps, ``--steps`` steps are traced without
``drjit.freeze`` under a :class:`mi_nerfpp.core.profiling.KernelProfile`, which attributes every
kernel to the stage that launched it (occupancy refresh and sampling, field evaluations, the
merge of coarse and fine samples, quadrature, deferred colour, losses and the reverse pass,
Adam) and tells kernels apart by kind (gradient scatters, memsets, block reductions, matrix
products). Then the same number of frozen steps (how training runs) are timed: wall time and
the cores busy (process CPU time over wall time; 2 = both cores of this machine); and as many
again profiled: kernel launches and kernel time per step. With ``--run RUN`` one frame of the run's ``render.xml`` at
``--width x --height`` (1 spp) is profiled the same way.

``--base REV`` measures the same for git revision ``REV`` too (exported with ``git archive``,
run in its own process with this checkout's :mod:`mi_nerfpp.core.profiling` copied in; code without
stage marks shows its kernels by kind only), one version after the other; ``--base-run`` is the
base version's run to render. Prints tables; writes ``benchmarks/results/profile.json``
(``--name NAME``: ``NAME.json``).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


# ----------------------------------------------------------------------------- one version

def cores_busy(fn):
    """``(wall seconds, cores busy)`` of ``fn()``."""
    import drjit as dr
    c0, t0 = time.process_time(), time.perf_counter()
    fn()
    dr.sync_thread()
    wall = time.perf_counter() - t0
    return wall, (time.process_time() - c0) / wall


def stage_rows(profile, per):
    """Rows ``[stage, kind, ms per unit, launches per unit]``, largest first."""
    rows = []
    for name, kinds in profile.by_stage().items():
        for kind, (ms, n) in kinds.items():
            rows.append([name, kind, round(ms / per, 2), round(n / per, 1)])
    return sorted(rows, key=lambda r: -r[2])


def profile_training(data, options, steps, warmup, at, resume=None):
    import drjit as dr
    from mi_nerfpp.core.profiling import KernelProfile
    from stepping import make_trainer
    out = {}
    for freeze in (False, True):
        trainer, batch = make_trainer(data, options, at, resume, freeze)
        for _ in range(warmup):
            trainer.step()
        dr.sync_thread()
        if not freeze:
            with KernelProfile() as profile:
                wall, busy = cores_busy(lambda: [trainer.step() for _ in range(steps)])
            out['stages'] = stage_rows(profile, steps)
            out['traced'] = {'step_ms': 1e3 * wall / steps, 'cores_busy': busy,
                             'launches': profile.launches() / steps}
            continue
        # Timed without the profile (under it, the first occupancy refresh compiles its kernels
        # again: one step of ~0.4 s in the mean), then the same steps profiled for the kernels.
        times = []
        c0, t0 = time.process_time(), time.perf_counter()
        for _ in range(steps):
            s = time.perf_counter()
            trainer.step()
            dr.sync_thread()
            times.append(time.perf_counter() - s)
        busy = (time.process_time() - c0) / (time.perf_counter() - t0)
        with KernelProfile() as profile:
            for _ in range(steps):
                trainer.step()
            dr.sync_thread()
        out['frozen'] = {'step_ms': 1e3 * statistics.median(times),
                         'mean_step_ms': 1e3 * statistics.mean(times),
                         'kernel_ms': sum(ms for _, _, ms in profile.records) / steps,
                         'cores_busy': busy, 'launches': profile.launches() / steps,
                         'rays_per_second': batch / statistics.mean(times), 'batch_rays': batch}
    return out


def profile_render(run, width, height):
    import re

    import drjit as dr
    import mitsuba as mi
    from mi_nerfpp.core.profiling import KernelProfile
    with open(os.path.join(run, 'render.xml')) as f:
        xml = f.read()
    for name, value in (('width', width), ('height', height), ('sample_count', 1)):
        xml = re.sub(rf'(<integer name="{name}" value=")\d+', rf'\g<1>{value}', xml)
    path = os.path.join(run, 'render_profile.xml')
    with open(path, 'w') as f:
        f.write(xml)
    scene = mi.load_file(path)
    dr.eval(mi.render(scene))            # compile
    dr.sync_thread()
    with KernelProfile() as profile:
        wall, busy = cores_busy(lambda: dr.eval(mi.render(scene)))
    return {'seconds': wall, 'launches': profile.launches(), 'cores_busy': busy,
            'kernel_ms': sum(ms for _, _, ms in profile.records),
            'stages': stage_rows(profile, 1)}


def worker(args):
    """Measure the version this process imports; print the result as JSON."""
    import mi_nerfpp  # noqa: F401  (libLLVM, variant, plugin registration)
    result = {'training': profile_training(args['data'], args['options'], args['steps'],
                                           args['warmup'], args.get('at', 0.0),
                                           args.get('resume'))}
    if args.get('run'):
        result['render'] = profile_render(args['run'], args['width'], args['height'])
    print(json.dumps(result))


def measure(tree, args):
    """Run :func:`worker` on the package in ``tree`` in a process of its own."""
    env = dict(os.environ, PYTHONPATH=tree, PYTHONUNBUFFERED='1')
    out = subprocess.run([sys.executable, os.path.abspath(__file__), '--worker',
                          json.dumps(args)], cwd=tree, env=env, check=True,
                         stdout=subprocess.PIPE, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- report

def print_table(title, columns, rows):
    print(f'\n{title}')
    print('  ' + ' | '.join(columns))
    for r in rows:
        print('  ' + ' | '.join(str(v) for v in r))


def main():
    if len(sys.argv) == 3 and sys.argv[1] == '--worker':
        return worker(json.loads(sys.argv[2]))
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--data', help='dataset folder (default: the embedded default capture)')
    ap.add_argument('--steps', type=int, default=20)
    ap.add_argument('--warmup', type=int, default=20)
    ap.add_argument('--at', type=float, default=0.6,
                    help='the fraction of a run at which the steps are taken (as '
                         'benchmarks/versus.py train --at)')
    ap.add_argument('--run', help='also profile a render of this run folder')
    ap.add_argument('--resume', metavar='RUN',
                    help="take the steps from this trained run's checkpoint (its bricks as "
                         "trained; a fresh model holds every brick)")
    ap.add_argument('--base-resume', metavar='RUN', help='--resume for the base revision')
    ap.add_argument('--width', type=int, default=1280)
    ap.add_argument('--height', type=int, default=720)
    ap.add_argument('--base', help='also measure this git revision')
    ap.add_argument('--base-run', help="the base revision's run folder to render")
    ap.add_argument('--name', default='profile',
                    help='results file name (benchmarks/results/NAME.json)')
    ap.add_argument('options', nargs='*', help='training options as name=value (this version)')
    a = ap.parse_intermixed_args()
    common = {'data': a.data and os.path.abspath(a.data), 'steps': a.steps,
              'warmup': a.warmup, 'width': a.width, 'height': a.height, 'at': a.at}
    versions = {'this checkout': measure(ROOT, dict(
        common, options={k: json.loads(v) for k, v in (o.split('=', 1) for o in a.options)},
        run=a.run and os.path.abspath(a.run), resume=a.resume and os.path.abspath(a.resume)))}
    if a.base:
        tmp = tempfile.mkdtemp(prefix='mi_nerfpp_profile_base_')
        archive = subprocess.run(['git', '-C', ROOT, 'archive', a.base], check=True,
                                 stdout=subprocess.PIPE).stdout
        subprocess.run(['tar', '-x', '-C', tmp], input=archive, check=True)
        os.makedirs(os.path.join(tmp, 'mi_nerfpp', 'core'), exist_ok=True)
        shutil.copy(os.path.join(ROOT, 'mi_nerfpp', 'core', 'profiling.py'),
                    os.path.join(tmp, 'mi_nerfpp', 'core', 'profiling.py'))
        versions[a.base] = measure(tmp, dict(common, options={},
                                             run=a.base_run and os.path.abspath(a.base_run),
                                             resume=a.base_resume and os.path.abspath(
                                                 a.base_resume)))

    columns = ['version', 'step (ms, median)', 'rays per step', 'rays/s', 'kernel launches',
               'kernel ms', 'cores busy']
    rows = []
    for name, v in versions.items():
        f = v['training']['frozen']
        rows.append([name, round(f['step_ms'], 1), f['batch_rays'], round(f['rays_per_second']),
                     round(f['launches']), round(f['kernel_ms'], 1), round(f['cores_busy'], 2)])
    print_table('Training step, frozen (as trained)', columns, rows)
    tables = [{'title': 'Training step, frozen (as trained)', 'columns': columns, 'rows': rows}]
    stage_columns = ['stage', 'kind', 'ms per step', 'launches per step']
    for name, v in versions.items():
        t = v['training']['traced']
        title = (f'{name}: kernels of a training step traced in Python by stage and kind '
                 f"({t['step_ms']:.1f} ms, {t['launches']:.0f} launches, "
                 f"{t['cores_busy']:.2f} cores busy)")
        print_table(title, stage_columns, v['training']['stages'])
        tables.append({'title': title, 'columns': stage_columns,
                       'rows': v['training']['stages']})
    if any('render' in v for v in versions.values()):
        columns = ['version', 'seconds', 'kernel launches', 'kernel ms', 'cores busy']
        rows = [[name, round(v['render']['seconds'], 2), v['render']['launches'],
                 round(v['render']['kernel_ms']), round(v['render']['cores_busy'], 2)]
                for name, v in versions.items() if 'render' in v]
        title = f'Render of a trained model, {a.width}x{a.height}, 1 spp'
        print_table(title, columns, rows)
        tables.append({'title': title, 'columns': columns, 'rows': rows})
        for name, v in versions.items():
            if 'render' in v:
                title = f'{name}: kernels of a render by stage and kind'
                print_table(title, ['stage', 'kind', 'ms', 'launches'], v['render']['stages'])
                tables.append({'title': title, 'columns': ['stage', 'kind', 'ms', 'launches'],
                               'rows': v['render']['stages']})
    from mi_nerfpp.jobs.bench import write_results
    title = 'Where the time goes' + (f" ({', '.join(a.options)})" if a.options else '')
    write_results(a.name, title, tables, raw=versions,
                  notes='Kernels are attributed to the stage that launched them (Dr.Jit '
                        'evaluates lazily; while profiling, stages evaluate their outputs '
                        'before they end). Cores busy: process CPU time over wall time. '
                        'Versions are measured one after the other, each in its own process.')


if __name__ == '__main__':
    main()
