"""Two versions of mi-nerfpp side by side: training steps or renders, alternating, one machine.

    python benchmarks/versus.py train  --base c93a164 [--rounds 8 --block 16] [--data DATA]
                                       [--resume RUN --base-resume RUN] [-- NEW OPTIONS]
    python benchmarks/versus.py render --base c93a164 --base-run RUN_A --run RUN_B
                                       [--width 1280 --height 720 --rounds 5]

Writes ``benchmarks/results/versus_train.json`` / ``versus_render.json`` (``--name``).

The base revision is exported from git (``git archive``) into a temporary folder; this checkout
is the new version. Each version runs in a worker process of its own (its own package on
``PYTHONPATH``, its own defaults), and the workers take turns: ``--rounds`` rounds, each running
``--block`` training steps (or one render) in each worker, the order swapped every round, so both
see the same machine - its fast and slow modes, whatever else runs. Each worker makes its
trainer as its version's ``optimize.py`` does (``benchmarks/stepping.py``: what the options
leave to the capture chosen by the version's own ``jobs.run.prepare``), on the embedded default
capture or ``--data``; ``--resume`` / ``--base-resume`` continue trained runs of each version
(on a fresh model a sparse level holds every brick). Reported per version: the
median and mean step (or frame) time of the warm blocks, training rays/s from the mean (the
mean includes the periodic occupancy refresh when ``--block`` is a multiple of its period), the
worker's peak RSS, and the ratio new/base. ``train`` uses each version's default training
options (``-- OPTIONS`` are keyword options of the new
version's config, as ``name=value``, e.g. ``batch_rays=2048``); both versions take their steps
at fraction ``--at`` of a run (0.6: past the phases of the schedule, where most of a run's steps
are). ``render`` renders each run's ``render.xml`` (its model, its sample counts) with the film
resized, like ``benchmarks/render.py --run``.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

TRAIN_WORKER = r'''
import json, resource, sys, time
sys.path.insert(0, sys.argv[2])         # this checkout's benchmarks/ (stepping.py)
import mi_nerfpp, drjit as dr
from stepping import make_trainer
args = json.loads(sys.argv[1])
trainer, batch = make_trainer(args['data'], args['options'], args['at'], args['resume'])
for _ in range(args['warmup']):
    trainer.step()
dr.sync_thread()
print(json.dumps({'batch': batch}), flush=True)
for line in sys.stdin:
    n = int(line)
    if n == 0:
        break
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        trainer.step()
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
    print(json.dumps({'times': times}), flush=True)
print(json.dumps({'rss_mib': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}), flush=True)
'''

RENDER_WORKER = r'''
import json, os, re, resource, sys, tempfile, time
import mi_nerfpp, drjit as dr, mitsuba as mi
args = json.loads(sys.argv[1])
with open(os.path.join(args['run'], 'render.xml')) as f:
    xml = f.read()
for name in ('width', 'height', 'sample_count'):
    xml = re.sub(rf'(<integer name="{name}" value=")\d+', rf'\g<1>{args[name]}', xml)
path = os.path.join(args['run'], 'render_versus.xml')
with open(path, 'w') as f:
    f.write(xml)
scene = mi.load_file(path)
def frame():
    t0 = time.perf_counter()
    image = mi.render(scene, seed=0)
    dr.eval(image)
    dr.sync_thread()
    return time.perf_counter() - t0
frame()
print(json.dumps({'batch': args['width'] * args['height'] * args['sample_count']}), flush=True)
for line in sys.stdin:
    n = int(line)
    if n == 0:
        break
    print(json.dumps({'times': [frame() for _ in range(n)]}), flush=True)
print(json.dumps({'rss_mib': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}), flush=True)
'''


def export(rev, folder):
    """The tree of ``rev`` in ``folder`` (``git archive``)."""
    os.makedirs(folder, exist_ok=True)
    archive = subprocess.run(['git', '-C', ROOT, 'archive', rev], check=True,
                             stdout=subprocess.PIPE).stdout
    subprocess.run(['tar', '-x', '-C', folder], input=archive, check=True)
    return folder


class Worker:
    def __init__(self, name, tree, code, args):
        env = dict(os.environ, PYTHONPATH=tree, PYTHONUNBUFFERED='1')
        self.name = name
        self.proc = subprocess.Popen([sys.executable, '-c', code, json.dumps(args),
                                      os.path.join(ROOT, 'benchmarks')], cwd=tree,
                                     env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True)
        self.batch = self._read()['batch']
        self.times = []

    def _read(self):
        while True:
            line = self.proc.stdout.readline()
            if not line:
                raise SystemExit(f'{self.name}: the worker stopped (see its error output above)')
            if line.startswith('{'):
                return json.loads(line)
            print(f'{self.name}: {line}', end='', file=sys.stderr)   # the run's announcements

    def run(self, n):
        self.proc.stdin.write(f'{n}\n')
        self.proc.stdin.flush()
        self.times += self._read()['times']

    def close(self):
        self.proc.stdin.write('0\n')
        self.proc.stdin.flush()
        self.rss = self._read()['rss_mib']
        self.proc.wait()


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('mode', choices=['train', 'render'])
    ap.add_argument('--base', required=True, help='git revision of the base version')
    ap.add_argument('--rounds', type=int, default=8)
    ap.add_argument('--block', type=int, default=16, help='training steps per turn')
    ap.add_argument('--warmup', type=int, default=20, help='training steps before timing')
    ap.add_argument('--at', type=float, default=0.6,
                    help='train: the fraction of a run at which the steps are taken (what the '
                         'schedule has switched on by then: the image pyramid at full size '
                         'from 0.3, the background\'s sparsity prior from 0.5)')
    ap.add_argument('--data', help='train: dataset folder (default: the embedded default capture)')
    ap.add_argument('--resume', metavar='RUN',
                    help="train: this version's steps from this trained run's checkpoint (its "
                         "bricks as trained; a fresh model holds every brick)")
    ap.add_argument('--base-resume', metavar='RUN', help='train: --resume for the base version')
    ap.add_argument('--base-run', help='render: the base version\'s run folder')
    ap.add_argument('--run', help='render: this version\'s run folder')
    ap.add_argument('--width', type=int, default=1280)
    ap.add_argument('--height', type=int, default=720)
    ap.add_argument('--spp', type=int, default=1)
    ap.add_argument('--name', help='write benchmarks/results/<name>.json (default: versus_<mode>)')
    ap.add_argument('options', nargs='*', help='train: name=value options of the new version')
    a = ap.parse_intermixed_args()

    tmp = tempfile.mkdtemp(prefix='mi_nerfpp_versus_')
    base_tree = export(a.base, os.path.join(tmp, 'base'))
    trees = {'base': base_tree, 'new': ROOT}
    workers = {}
    for name in ('base', 'new'):
        if a.mode == 'train':
            options = {}
            if name == 'new':
                for item in a.options:
                    key, value = item.split('=', 1)
                    options[key] = json.loads(value)
            resume = a.base_resume if name == 'base' else a.resume
            args = {'options': options, 'warmup': a.warmup, 'at': a.at,
                    'data': a.data and os.path.abspath(a.data),
                    'resume': resume and os.path.abspath(resume)}
            workers[name] = Worker(name, trees[name], TRAIN_WORKER, args)
        else:
            run = a.base_run if name == 'base' else a.run
            if not run:
                raise SystemExit('render needs --base-run and --run')
            args = {'run': os.path.abspath(run), 'width': a.width, 'height': a.height,
                    'sample_count': a.spp}
            workers[name] = Worker(name, trees[name], RENDER_WORKER, args)
    block = a.block if a.mode == 'train' else 1
    order = ['base', 'new']
    for r in range(a.rounds):
        for name in (order if r % 2 == 0 else order[::-1]):
            workers[name].run(block)
    result = {'mode': a.mode, 'base': a.base, 'rounds': a.rounds, 'block': block}
    for name, w in workers.items():
        w.close()
        mean = statistics.mean(w.times)
        result[name] = {'median_s': statistics.median(w.times), 'mean_s': mean,
                        'per_second': w.batch / mean, 'batch': w.batch, 'rss_mib': w.rss,
                        'n': len(w.times)}
        what = 'rays/s (training)' if a.mode == 'train' else 'rays/s (render)'
        print(f'{name:5s}: median {1e3 * result[name]["median_s"]:.1f} ms, mean '
              f'{1e3 * mean:.1f} ms over {len(w.times)} ({w.batch} rays each): '
              f'{w.batch / mean:,.0f} {what}; peak RSS {w.rss:.0f} MiB')
    ratio = result['new']['per_second'] / result['base']['per_second']
    result['ratio'] = ratio
    print(f'new / base: {ratio:.2f}x')
    from mi_nerfpp.jobs.bench import table, write_results
    unit = 'rays/s (training)' if a.mode == 'train' else 'rays/s (render)'
    what = 'step' if a.mode == 'train' else 'frame'
    rows = [[f'{name} ({a.base if name == "base" else "this checkout"})',
             round(1e3 * result[name]['median_s'], 1), round(1e3 * result[name]['mean_s'], 1),
             round(result[name]['per_second']), result[name]['batch'],
             round(result[name]['rss_mib'])] for name in ('base', 'new')]
    title = ('Training throughput against ' if a.mode == 'train' else 'Render time against ') \
        + a.base
    write_results(a.name or f'versus_{a.mode}', title,
                  [table(f'{what.capitalize()} time, side by side', ['version', f'median {what} (ms)',
                                                                     f'mean {what} (ms)', unit,
                                                                     'rays per ' + what,
                                                                     'peak RSS (MiB)'],
                         rows, note=f'new / base: {ratio:.2f}x; {a.rounds} rounds, the order '
                                    f'swapped every round')],
                  raw=result)


if __name__ == '__main__':
    main()
