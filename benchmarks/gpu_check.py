"""The GPU check (issue 51): the same commands on ``cuda_ad_rgb`` as on the CPU, in one run.

    python benchmarks/gpu_check.py [--cpu-only] [--steps 500] [--plaza-minutes 5] [--json FILE]

Run through ``bash benchmarks/gpu_check.sh``, which installs the package first. Each command runs
in a process of its own, choosing its backend with ``--variant`` (a process keeps its variant),
and this script imports neither Mitsuba nor mi_nerfpp: a machine without libLLVM still runs the
CUDA half. In order, each step's figures written to the JSON as soon as it ends:

1. which backends start here (``import mi_nerfpp`` under each variant), and the GPU;
2. the default capture (``synth scenes/gt_garden.xml`` at its defaults, once, on the first
   backend; reused while its ``capture.json`` matches);
3. at once: the backend-agnostic test subset (:data:`TESTS`) on the GPU's variant, the default
   capture trained for ``--steps`` on the CPU (``llvm_ad_rgb``), and on the GPU the same
   training, then the packed-network probe (mitsuba3 issue 1825: a render with
   ``MI_NERFPP_PACKED=1`` in a process of its own, against tensor mode), then the ``gt_plaza``
   capture. The PSNR of the two trainings is compared at equal steps (same capture, seed 0);
   their times are not speed figures (they share the machine);
4. alone: ``gt_plaza`` at ``--plaza-res`` trained for ``--plaza-minutes`` on the GPU (its steps
   are the speed figure);
5. alone: the plaza model (the default capture's with ``--plaza-minutes 0``) rendered at
   ``--render-res`` and 1 spp, one cold and ``--render-runs`` warm frames.

``--cpu-only`` runs the same steps on ``llvm_ad_rgb`` alone (the check's CPU half; pass smaller
sizes on a small machine). Results: ``benchmarks/results/gpu_check.json`` (``--json``; the
schema of ``scripts/benchmarks_page.py``, the GPU named in ``machine``); with ``--cpu-only`` the
default is ``<work>/gpu_check_cpu.json``, not a GPU figure. Work files: ``--work``.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import shlex
import shutil
import statistics
import subprocess
import sys
import time
import xml.etree.ElementTree as ET

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CPU, GPU = 'llvm_ad_rgb', 'cuda_ad_rgb'
# The backend-agnostic subset of the test suite: the integrator, rendering, fields, the variant
# choice, and two trainings (frozen steps against traced ones, PSNR well above untrained).
TESTS = ['tests/test_variant.py', 'tests/integrator/test_integrator.py',
         'tests/core/test_render.py', 'tests/core/test_fields.py', 'tests/commands/test_render.py',
         'tests/training/test_train.py::test_frozen_step_replays_the_traced_step',
         'tests/training/test_train.py::test_training_raises_held_out_psnr_well_above_untrained']


def log(text):
    print(f'[{datetime.datetime.now():%H:%M:%S}] {text}', flush=True)


def cache_dir():
    """Where captures are kept: mi_nerfpp's cache (``$MI_NERFPP_CACHE``, else
    ``$XDG_CACHE_HOME/mi-nerfpp``, else ``~/.cache/mi-nerfpp``), as the package has it."""
    if os.environ.get('MI_NERFPP_CACHE'):
        return os.environ['MI_NERFPP_CACHE']
    base = os.environ.get('XDG_CACHE_HOME') or os.path.join(os.path.expanduser('~'), '.cache')
    return os.path.join(base, 'mi-nerfpp')


def environment(variant=None, **extra):
    env = dict(os.environ)
    env.pop('MI_NERFPP_VARIANT', None)
    env['PYTHONPATH'] = os.pathsep.join(p for p in (ROOT, env.get('PYTHONPATH')) if p)
    env['MI_NERFPP_NO_OIIOTOOL'] = '1'
    if variant:
        env['MI_NERFPP_VARIANT'] = variant
    env.update(extra)
    return env


def start(args, logfile, variant=None, **extra):
    """A child process (``python ARGS`` from the repository root) writing ``logfile``."""
    out = open(logfile, 'w')
    return subprocess.Popen([sys.executable, *args], cwd=ROOT, stdout=out,
                            stderr=subprocess.STDOUT, env=environment(variant, **extra))


def finish(proc, timeout):
    """``(exit status or 'timeout', seconds)`` of a child started by :func:`start`."""
    t0 = time.perf_counter()
    try:
        status = proc.wait(timeout=max(1.0, timeout))
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        status = 'timeout'
    return status, time.perf_counter() - t0


def run(args, logfile, timeout, variant=None, **extra):
    t0 = time.perf_counter()
    status, _ = finish(start(args, logfile, variant, **extra), timeout)
    return status, time.perf_counter() - t0


def tail(path, lines=8):
    try:
        with open(path, errors='replace') as f:
            return ' | '.join(line.strip() for line in f.read().splitlines()[-lines:])
    except OSError:
        return ''


def cli(variant, *args):
    return ['-m', 'mi_nerfpp', '--variant', variant, *args]


# ---------------------------------------------------------------------------------- results

class Results:
    """The JSON of the check, rewritten after every step."""

    def __init__(self, path, options, cpu_only):
        self.path, self.cpu_only = path, cpu_only
        self.tables, self.raw, self.stages = {}, {'options': options}, []
        self.gpu = gpu_name()
        self.started = time.perf_counter()

    def table(self, key, title, columns, rows, note=None):
        t = {'title': title, 'columns': columns, 'rows': rows}
        if note:
            t['note'] = note
        self.tables[key] = t
        self.write()

    def stage(self, name, seconds, status):
        self.stages.append([name, round(seconds, 1), str(status)])
        self.write()

    def write(self):
        tables = list(self.tables.values())
        tables.append({'title': 'Steps of the check', 'columns': ['step', 'seconds', 'result'],
                       'rows': self.stages + [['all', round(time.perf_counter() - self.started,
                                                           1), '']]})
        result = {
            'benchmark': 'gpu_check',
            'title': ('GPU check, CPU half (llvm_ad_rgb only)' if self.cpu_only
                      else 'GPU check: cuda_ad_rgb against llvm_ad_rgb'),
            'command': shlex.join(['bash', 'benchmarks/gpu_check.sh'] + sys.argv[1:]),
            'date': datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'),
            'machine': machine(self.gpu),
            'git': git_revision(),
            'tables': tables,
            'notes': ('Each command ran in its own process. The two default-capture trainings '
                      'and the tests ran at the same time (their times are not speed figures); '
                      'the plaza training and the render ran alone.'),
            'raw': self.raw,
        }
        if self.cpu_only:          # a section of its own, should it ever be kept
            result = {'benchmark': 'gpu_check', 'variant': 'cpu half', **result}
        os.makedirs(os.path.dirname(os.path.abspath(self.path)), exist_ok=True)
        tmp = self.path + '.tmp'
        with open(tmp, 'w') as f:
            json.dump(result, f, indent=2, allow_nan=False)
            f.write('\n')
        os.replace(tmp, self.path)


def gpu_name():
    try:
        out = subprocess.run(['nvidia-smi', '--query-gpu=name,memory.total,driver_version',
                              '--format=csv,noheader'], capture_output=True, text=True,
                             timeout=30).stdout.strip()
        return out.splitlines()[0] if out else None
    except (OSError, subprocess.SubprocessError):
        return None


def machine(gpu):
    """The schema's machine (scripts/benchmarks_page.py), with the GPU."""
    cpu = platform.machine()
    try:
        with open('/proc/cpuinfo') as f:
            names = [line.split(':', 1)[1].strip() for line in f if line.startswith('model name')]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    memory = None
    try:
        memory = round(os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2 ** 30, 1)
    except (ValueError, OSError, AttributeError):
        pass
    versions = {}
    for name in ('mitsuba', 'drjit'):
        try:
            from importlib.metadata import \
                version  # deferred: only here (a script, not the package)
            versions[name] = version(name)
        except Exception:
            versions[name] = None
    os_name = platform.platform()
    try:
        with open('/etc/os-release') as f:
            fields = dict(line.rstrip('\n').split('=', 1) for line in f if '=' in line)
        os_name = fields.get('PRETTY_NAME', '').strip('"') or os_name
    except OSError:
        pass
    out = {'cpu': f'{cpu} ({os.cpu_count()} cores)', 'memory_gib': memory, 'os': os_name,
           'python': platform.python_version(), **versions}
    if gpu:
        out['gpu'] = gpu
    return out


def git_revision():
    try:
        def git(*args):
            return subprocess.run(['git', '-C', ROOT, *args], capture_output=True, text=True,
                                  check=True).stdout.strip()
        return git('rev-parse', '--short', 'HEAD') + \
            ('-dirty' if git('status', '--porcelain', '--untracked-files=no') else '')
    except (OSError, subprocess.CalledProcessError):
        return None


# ---------------------------------------------------------------------------------- steps

def backends(results, wanted, work):
    """The wanted variants that start here (``import mi_nerfpp`` in a child process)."""
    rows, ready = [], []
    code = 'import mi_nerfpp, mitsuba as mi, drjit as dr; print(mi.variant(), dr.__version__)'
    for variant in wanted:
        logfile = os.path.join(work, f'import_{variant}.log')
        status, seconds = run(['-c', code], logfile, 120, variant)
        if status == 0:
            ready.append(variant)
        what = (results.gpu or 'no nvidia-smi') if variant == GPU else 'the CPU'
        rows.append([variant, 'yes' if status == 0 else 'no',
                     what if status == 0 else tail(logfile, 1), round(seconds, 1)])
        results.stage(f'import mi_nerfpp ({variant})', seconds, status)
    results.table('backends', 'Backends', ['variant', 'starts', 'device / why not',
                                           'import (s)'], rows)
    return ready


def synthesize(results, variant, scene, out, work, name, timeout, *options):
    logfile = os.path.join(work, f'synth_{name}.log')
    status, seconds = run(cli(variant, 'synth', os.path.join(ROOT, 'scenes', scene), '--out', out,
                              *options), logfile, timeout)
    results.stage(f'synth {name} ({variant})', seconds, status)
    if status != 0:
        raise SystemExit(f'error: gpu_check: synth {name} failed ({status}): {tail(logfile)}')


def train_args(variant, data, out, *options):
    return cli(variant, 'optimize', data, '--out', out, '--overwrite', '--seed', '0',
               '--checkpoint-every', '0', '--preview-every', '0', *options)


def metrics_row(variant, run_dir, status, seconds):
    try:
        with open(os.path.join(run_dir, 'metrics.json')) as f:
            m = json.load(f)
        steps = m['iterations']
        return [variant, steps, round(m['test']['psnr'], 2), round(m['test']['ssim'], 3),
                round(m['train_seconds'], 1), round(steps / m['train_seconds'], 1)
                if m['train_seconds'] else None, round(seconds, 1)], m
    except (OSError, KeyError, ValueError):
        return [variant, None, None, None, None, None, round(seconds, 1)], {'status': status}


def test_counts(junit):
    """``(passed, failed, errors, skipped, failed test names)`` from pytest's JUnit XML."""
    root = ET.parse(junit).getroot()
    suites = [root] if root.tag == 'testsuite' else list(root)
    total = sum(int(s.get('tests', 0)) for s in suites)
    failed = sum(int(s.get('failures', 0)) for s in suites)
    errors = sum(int(s.get('errors', 0)) for s in suites)
    skipped = sum(int(s.get('skipped', 0)) for s in suites)
    names = [f"{case.get('classname')}::{case.get('name')}"
             for s in suites for case in s.iter('testcase')
             if case.find('failure') is not None or case.find('error') is not None]
    return total - failed - errors - skipped, failed, errors, skipped, names


def render_worker(a):
    """In a child process of one variant: render ``a.run``'s render.xml at ``a.width x
    a.height`` and 1 spp, once cold and ``a.runs`` times warm; print one JSON line."""
    import mi_nerfpp  # noqa: F401  deferred: the variant comes from MI_NERFPP_VARIANT
    import drjit as dr  # deferred: after mi_nerfpp chose the variant
    import mitsuba as mi  # deferred: after mi_nerfpp chose the variant
    import numpy as np  # deferred: the worker only
    with open(os.path.join(a.run, 'render.xml')) as f:
        xml = f.read()
    for name, value in (('width', a.width), ('height', a.height), ('sample_count', 1)):
        xml = re.sub(rf'(<integer name="{name}" value=")\d+', rf'\g<1>{value}', xml)
    path = os.path.join(a.run, f'render_{a.width}x{a.height}.xml')
    with open(path, 'w') as f:
        f.write(xml)
    scene = mi.load_file(path)

    def frame():
        t0 = time.perf_counter()
        img = mi.render(scene, seed=0)
        dr.eval(img)
        dr.sync_thread()
        return time.perf_counter() - t0, img
    cold, img = frame()
    warm = [frame()[0] for _ in range(a.runs)]
    image = np.array(img)
    if a.save:
        np.save(a.save, image)
    print(json.dumps({'variant': mi.variant(), 'cold': cold, 'warm': warm,
                      'finite': bool(np.all(np.isfinite(image))), 'mean': float(image.mean())}))


def render(results, variant, run_dir, width, height, runs, work, name, timeout, **extra):
    logfile = os.path.join(work, f'render_{name}.log')
    save = os.path.join(work, f'render_{name}.npy')
    status, seconds = run([os.path.abspath(__file__), 'render', run_dir, '--width', str(width),
                           '--height', str(height), '--runs', str(runs), '--save', save],
                          logfile, timeout, variant, **extra)
    results.stage(f'render {name} ({variant})', seconds, status)
    out = None
    if status == 0:
        with open(logfile) as f:
            lines = [line for line in f.read().splitlines() if line.startswith('{')]
        out = json.loads(lines[-1]) if lines else None
    return status, out, save, logfile


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--cpu-only', action='store_true', help='llvm_ad_rgb alone: the CPU half')
    p.add_argument('--steps', type=int, default=500,
                   help='training steps on the default capture, each backend (default 500)')
    p.add_argument('--plaza-minutes', type=float, default=5.0,
                   help='minutes of gt_plaza training (default 5; 0: none)')
    p.add_argument('--plaza-res', default='512x384', help='gt_plaza capture size (default 512x384)')
    p.add_argument('--plaza-views', type=int, default=60)
    p.add_argument('--plaza-spp', type=int, default=64)
    p.add_argument('--render-res', default='1280x720', help='render size (default 1280x720)')
    p.add_argument('--render-runs', type=int, default=2, help='warm frames (default 2)')
    p.add_argument('--tests-timeout', type=float, default=90.0,
                   help='seconds for the test subset (default 90)')
    p.add_argument('--no-tests', action='store_true', help='skip the test subset')
    p.add_argument('--work', default=os.path.join(os.path.expanduser('~'), 'gpu_check'),
                   help='work folder: run folders and logs (default ~/gpu_check)')
    p.add_argument('--json', help='results file (default benchmarks/results/gpu_check.json; '
                                  'with --cpu-only WORK/gpu_check_cpu.json)')
    a = p.parse_args(argv)
    work = os.path.abspath(a.work)
    os.makedirs(work, exist_ok=True)
    path = a.json or (os.path.join(work, 'gpu_check_cpu.json') if a.cpu_only
                      else os.path.join(ROOT, 'benchmarks', 'results', 'gpu_check.json'))
    results = Results(os.path.abspath(path), vars(a), a.cpu_only)
    log(f'gpu_check: results in {results.path}, work files in {work}')

    ready = backends(results, [CPU] if a.cpu_only else [CPU, GPU], work)
    log(f'backends that start: {", ".join(ready) or "none"}')
    gpu = GPU if GPU in ready else None
    cpu = CPU if CPU in ready else None
    if not ready or (not a.cpu_only and gpu is None):
        raise SystemExit('error: gpu_check: ' + ('no backend starts' if not ready else
                         f'{GPU} does not start here: {tail(os.path.join(work, "import_" + GPU + ".log"), 2)}'))
    main_backend = gpu or cpu

    # The default capture, once, on the first backend (reused while it matches).
    default = os.path.join(cache_dir(), 'default')
    log(f'default capture: {default}')
    synthesize(results, main_backend, 'gt_garden.xml', default, work, 'default', 600)

    # At once: the tests on the GPU's variant, the CPU's training, the GPU's chain.
    t0 = time.perf_counter()
    children = {}
    if not a.no_tests:
        junit = os.path.join(work, 'tests.xml')
        if os.path.exists(junit):
            os.remove(junit)
        children['tests'] = start(['-m', 'pytest', *TESTS, '-q', '-p', 'no:cacheprovider',
                                   f'--junitxml={junit}'], os.path.join(work, 'tests.log'),
                                  main_backend)
    runs = {}
    if cpu:
        runs[cpu] = os.path.join(work, f'default_{cpu}')
        children['cpu'] = start(train_args(cpu, default, runs[cpu], '--iterations',
                                           str(a.steps)),
                                os.path.join(work, f'train_default_{cpu}.log'))
    probe_rows = []
    if gpu:
        runs[gpu] = os.path.join(work, f'default_{gpu}')
        status, seconds = run(train_args(gpu, default, runs[gpu], '--iterations', str(a.steps)),
                              os.path.join(work, f'train_default_{gpu}.log'), 900)
        results.stage(f'train default capture ({gpu})', seconds, status)
        rows = [metrics_row(gpu, runs[gpu], status, seconds)[0]]
        results.table('default', f'Default capture, {a.steps} steps, seed 0: held-out PSNR at '
                      f'equal steps', ['variant', 'steps', 'PSNR (dB)', 'SSIM', 'training (s)',
                                       'steps/s', 'command (s)'], rows)
        if status == 0:       # drjit.nn's packed networks on CUDA (mitsuba3 issue 1825)
            tensor = render(results, gpu, runs[gpu], 128, 96, 0, work, 'probe_tensor', 120,
                            MI_NERFPP_PACKED='0')
            packed = render(results, gpu, runs[gpu], 128, 96, 0, work, 'probe_packed', 120,
                            MI_NERFPP_PACKED='1')
            diff = None
            if tensor[0] == 0 and packed[0] == 0:
                import numpy as np  # deferred: only for the probe's comparison
                diff = float(np.abs(np.load(packed[2]) - np.load(tensor[2])).max())
            probe_rows = [['tensor mode (the default on CUDA)', str(tensor[0]),
                           tail(tensor[3], 1) if tensor[0] != 0 else 'renders', None],
                          ['packed (MI_NERFPP_PACKED=1)', str(packed[0]),
                           tail(packed[3], 2) if packed[0] != 0 else 'renders', diff]]
            results.table('packed', 'Packed networks on CUDA (mitsuba3 issue 1825), 128x96',
                          ['networks', 'exit status', 'result', 'max |packed - tensor|'],
                          probe_rows)
    plaza = None
    if a.plaza_minutes > 0:
        plaza = os.path.join(cache_dir(), f'gt_plaza_{a.plaza_res}_{a.plaza_views}v_'
                                          f'{a.plaza_spp}spp')
        synthesize(results, main_backend, 'gt_plaza.xml', plaza, work, 'plaza', 900,
                   '--res', a.plaza_res, '--views', str(a.plaza_views), '--spp',
                   str(a.plaza_spp))
    rows = []
    if 'cpu' in children:
        status, _ = finish(children['cpu'], 1800 - (time.perf_counter() - t0))
        seconds = time.perf_counter() - t0
        results.stage(f'train default capture ({cpu})', seconds, status)
        rows.append(metrics_row(cpu, runs[cpu], status, seconds)[0])
    if gpu:
        rows.append(metrics_row(gpu, runs[gpu], 0, 0)[0])
    results.table('default', f'Default capture, {a.steps} steps, seed 0: held-out PSNR at equal '
                  f'steps', ['variant', 'steps', 'PSNR (dB)', 'SSIM', 'training (s)', 'steps/s',
                             'command (s)'], rows,
                  note='The same capture and seed on each backend; trained at the same time as '
                       'the tests, so the times are not speed figures.')
    if 'tests' in children:
        status, _ = finish(children['tests'], a.tests_timeout - (time.perf_counter() - t0))
        seconds = time.perf_counter() - t0
        results.stage(f'tests ({main_backend})', seconds, status)
        junit = os.path.join(work, 'tests.xml')
        if os.path.exists(junit):
            passed, failed, errors, skipped, names = test_counts(junit)
            results.raw['failed_tests'] = names
            row = [main_backend, passed, failed, errors, skipped, round(seconds, 1), str(status)]
        else:
            row = [main_backend, None, None, None, None, round(seconds, 1), str(status)]
            results.raw['tests_log'] = tail(os.path.join(work, 'tests.log'), 20)
        results.table('tests', 'Test subset (backend-agnostic)', ['variant', 'passed', 'failed',
                      'errors', 'skipped', 'seconds', 'exit status'], [row],
                      note='pytest ' + ' '.join(TESTS))

    # Alone: the plaza training on the main backend, then the render.
    model = runs.get(main_backend)
    if plaza:
        out = os.path.join(work, f'plaza_{main_backend}')
        status, seconds = run(train_args(main_backend, plaza, out, '--minutes',
                                         str(a.plaza_minutes)),
                              os.path.join(work, f'train_plaza_{main_backend}.log'),
                              a.plaza_minutes * 60 + 600)
        results.stage(f'train gt_plaza {a.plaza_res} ({main_backend})', seconds, status)
        row, m = metrics_row(main_backend, out, status, seconds)
        results.table('plaza', f'gt_plaza {a.plaza_res} ({a.plaza_views} views, {a.plaza_spp} '
                      f'spp), {a.plaza_minutes:g} minutes', ['variant', 'steps', 'PSNR (dB)',
                      'SSIM', 'training (s)', 'steps/s', 'command (s)'], [row],
                      note='After the steps that run at once had ended; default options, '
                           'seed 0.')
        if status == 0:
            model = out
    if model:
        width, height = (int(x) for x in a.render_res.lower().split('x'))
        status, out, _, logfile = render(results, main_backend, model, width, height,
                                         a.render_runs, work, 'frame', 900)
        if out:
            t = statistics.median(out['warm']) if out['warm'] else out['cold']
            row = [main_backend, os.path.basename(model), round(out['cold'], 2), round(t, 3),
                   round(width * height / t / 1e6, 2), out['finite']]
        else:
            row = [main_backend, os.path.basename(model), None, None, None, tail(logfile, 2)]
        results.table('render', f'Render {width}x{height} at 1 spp', ['variant', 'model',
                      'cold (s)', 'median warm (s)', 'M rays/s', 'finite'], [row],
                      note=f'One cold frame (kernels compiled) and {a.render_runs} warm ones, '
                           f'after the training.')
    log(f'gpu_check: done in {time.perf_counter() - results.started:.0f} s: {results.path}')
    print(json.dumps({k: v['rows'] for k, v in results.tables.items()}, indent=1))
    return 0


if __name__ == '__main__':
    if len(sys.argv) > 1 and sys.argv[1] == 'render':
        ap = argparse.ArgumentParser()
        ap.add_argument('command')
        ap.add_argument('run')
        ap.add_argument('--width', type=int, required=True)
        ap.add_argument('--height', type=int, required=True)
        ap.add_argument('--runs', type=int, default=2)
        ap.add_argument('--save')
        render_worker(ap.parse_args())
    else:
        sys.exit(main())
