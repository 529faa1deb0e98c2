"""What the scripts in ``benchmarks/`` share: their results files and common measurements.

Every benchmark that measures something writes its results with :func:`write_results`:
``benchmarks/results/<name>.json`` in the schema the generated benchmarks page reads (the
benchmark, a title, the command that reproduces it, the date, the machine, the git revision,
tables, optional figures copied next to it, notes and raw data). The measurements two or more
benchmarks take are here too, so that no benchmark imports another: the training options of
``optimize`` given on a benchmark's command line (:func:`training_options`), a run with an
option off and on (:func:`without_and_with`), ray distances to camera z
(:func:`ray_distance_to_z`), a ground-truth view rendered as a capture encodes it
(:func:`render_encoded`), the objects example's three scenes (:func:`object_scenes`) and
peak memory (:func:`peak_rss_mib`).
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import resource
import shlex
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET

import drjit
import imageio.v3 as iio
import mitsuba
import mitsuba as mi
import numpy as np

from mi_nerfpp.core.color import to_srgb8
from mi_nerfpp.core.frame import MITSUBA_NEAR_CLIP
from mi_nerfpp.data import mitsuba_sensor_dict
from mi_nerfpp.data.synth.capture import scenes_dir
from mi_nerfpp.jobs import run
from mi_nerfpp.training.config import TrainConfig
from mi_nerfpp.training.evaluate import evaluate_split
from mi_nerfpp.training.options import add_options, flag, values

# ---------------------------------------------------------------------------------- results

def table(title: str, columns: list, rows: list, note: str | None = None) -> dict:
    """One table of a results file: ``rows`` of plain numbers or strings, one per column."""
    out = {'title': title, 'columns': list(columns), 'rows': [list(r) for r in rows]}
    if note:
        out['note'] = note
    return out


def write_results(name: str, title: str, tables: list, figures=(), notes: str | None = None,
                  raw=None, command: str | None = None, folder: str | None = None,
                  variant: str | None = None) -> str:
    """Write ``<folder>/<name>.json`` (default folder: ``results/`` next to the running
    benchmark script) and return its path. ``figures``: PNG files to show with the tables,
    copied into the folder as ``<name>_<file name>``; ``command``: what reproduces the
    results (default: this process's command line, from the repository root); the date, the
    machine and the git revision are filled in. ``variant``: what this file measures when one
    benchmark measures different things (the benchmarks page shows the latest file of each)."""
    script = os.path.abspath(sys.argv[0])
    folder = folder or os.path.join(os.path.dirname(script), 'results')
    os.makedirs(folder, exist_ok=True)
    shown = []
    for figure in figures:
        target = f'{name}_{os.path.basename(figure)}'
        if os.path.abspath(figure) != os.path.abspath(os.path.join(folder, target)):
            shutil.copyfile(figure, os.path.join(folder, target))
        shown.append(target)
    results = {
        'benchmark': os.path.splitext(os.path.basename(script))[0],
        **({'variant': variant} if variant else {}),
        'title': title,
        'command': command or this_command(),
        'date': datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'),
        'machine': machine(),
        'git': git_revision(os.path.dirname(script)),
        'tables': tables,
    }
    if shown:
        results['figures'] = shown
    if notes:
        results['notes'] = notes
    if raw is not None:
        results['raw'] = raw
    path = os.path.join(folder, f'{name}.json')
    tmp = path + '.tmp'
    with open(tmp, 'w') as f:
        json.dump(_plain(results), f, indent=2, allow_nan=False)
        f.write('\n')
    os.replace(tmp, path)
    return path


def write_image_row(path: str, images, scale: int = 2, gap: int = 4) -> str:
    """Write ``images`` (float (H, W, 3) in [0, 1], encoded for display, one height) side by
    side, each enlarged ``scale`` times by pixel repetition, ``gap`` white pixels apart, as an
    8-bit PNG at ``path`` (a benchmark's figure); returns ``path``."""
    tiles = [np.repeat(np.repeat(np.asarray(t, np.float64)[..., :3], scale, 0), scale, 1)
             for t in images]
    space = np.ones((tiles[0].shape[0], gap, 3))
    row = np.concatenate(sum(([t, space] for t in tiles), [])[:-1], axis=1)
    iio.imwrite(path, (np.clip(row, 0, 1) * 255).round().astype(np.uint8))
    return path


def _plain(value):
    """``value`` with NumPy numbers and arrays as Python numbers and lists, tuples as lists
    and non-finite numbers (NaN: nothing to measure) as None, so that it is valid JSON."""
    if hasattr(value, 'tolist'):
        value = value.tolist()
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def this_command() -> str:
    """``python <script> <arguments>`` as run, the script relative to the repository root
    (the folder above ``benchmarks/``)."""
    script = os.path.abspath(sys.argv[0])
    root = os.path.dirname(os.path.dirname(script))
    return shlex.join(['python', os.path.relpath(script, root)] + sys.argv[1:])


def add_train_command(commands, func, minutes: float, cases=None):
    """The ``train`` command of a benchmark that trains its cases one after the other: ``work``
    (the folder of the cases), ``--minutes``, ``--seed`` and, with ``cases`` (their names),
    ``--cases`` and ``--options LABEL=ARGS`` (more runs with other options)."""
    p = commands.add_parser('train', help='train the cases one after the other')
    p.add_argument('work')
    p.add_argument('--minutes', type=float, default=minutes)
    if cases is not None:
        p.add_argument('--cases', nargs='*', choices=list(cases), default=list(cases))
        p.add_argument('--options', nargs='*', default=[], metavar='LABEL=ARGS')
    p.add_argument('--seed', type=int, default=0)
    p.set_defaults(func=func)
    return p


def add_score_command(commands, func, name: str):
    """The ``score`` command of a benchmark that scores the finished runs of ``work``: the
    results file ``--name`` (default ``name``) and its ``--note``."""
    p = commands.add_parser('score', help='score the finished runs')
    p.add_argument('work')
    p.add_argument('--name', default=name)
    p.add_argument('--note', default=None)
    p.set_defaults(func=func)
    return p


def machine() -> dict:
    """The machine the numbers were measured on: CPU model and cores, memory, OS, Python,
    Mitsuba and Dr.Jit versions."""
    cpu = platform.processor() or platform.machine()
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
    return {'cpu': f'{cpu} ({os.cpu_count()} cores)', 'memory_gib': memory, 'os': _os_name(),
            'python': platform.python_version(), 'mitsuba': mitsuba.__version__,
            'drjit': drjit.__version__}


def _os_name():
    try:
        with open('/etc/os-release') as f:
            fields = dict(line.rstrip('\n').split('=', 1) for line in f if '=' in line)
        return fields.get('PRETTY_NAME', '').strip('"') or platform.platform()
    except OSError:
        return platform.platform()


def git_revision(where: str) -> str | None:
    """The short git revision of the code at ``where``, ``-dirty`` when tracked files are
    modified; None outside a git checkout."""
    def git(*args):
        return subprocess.run(['git', '-C', where, *args], capture_output=True, text=True,
                              check=True).stdout.strip()
    try:
        rev = git('rev-parse', '--short', 'HEAD')
        dirty = git('status', '--porcelain', '--untracked-files=no')
    except (OSError, subprocess.CalledProcessError):
        return None
    return rev + ('-dirty' if dirty else '')


def peak_rss_mib(children: bool = False) -> float:
    """Peak resident memory of this process (or of its finished child processes), MiB."""
    who = resource.RUSAGE_CHILDREN if children else resource.RUSAGE_SELF
    return resource.getrusage(who).ru_maxrss / 1024


# ---------------------------------------------------------------------------------- training

def training_options(argv) -> dict:
    """The training options of ``optimize`` in ``argv`` (a list of command-line words, e.g.
    what follows ``--``), by option name; options not given take their defaults."""

    parser = argparse.ArgumentParser(prog='optimize options', add_help=False)
    add_options(parser, TrainConfig)
    return values(parser.parse_args(list(argv)), TrainConfig)


def changed_options(cfg, ignore=()) -> str:
    """The options in which ``cfg`` (a :class:`~mi_nerfpp.training.config.TrainConfig`) differs from
    the defaults, as command-line flags (``--batch-rays 256 --samples 8 8 8``), leaving out
    the option names in ``ignore``; ``'defaults'`` when none differs."""
    now, default = cfg.options(), TrainConfig().options()
    words, done = [], set()
    for name, value in now.items():
        if name in ignore or value == default[name]:
            continue
        spelled = flag(TrainConfig, name)
        if spelled in done:
            continue
        done.add(spelled)
        if spelled == '--samples':
            words += [spelled] + [str(now[k]) for k in ('fg_samples', 'bg_samples',
                                                         'fine_samples')]
        elif isinstance(value, bool):
            words.append(spelled if value else '--no-' + spelled[2:])
        elif isinstance(value, tuple):
            words += [spelled] + [str(v) for v in value]
        else:
            words += [spelled, str(value)]
    return shlex.join(words) or 'defaults'


def without_and_with(dataset, cfg, out, option, fit_appearance=None, observer=None):
    """Train ``cfg`` (a :class:`~mi_nerfpp.training.config.TrainConfig`) with the yes/no ``option``
    (an option name, e.g. ``'appearance'``) off, then on, each from scratch in
    ``out/<last word of option>_<on>``, and score each on the held-out views; yields ``(on,
    config, trainer, held-out result)``. ``fit_appearance`` (default: the run's
    ``appearance``) scores NeRF-W style."""
    for on in (False, True):
        config = cfg.replace(**{option: on})
        folder = os.path.join(out, f'{option.split("_")[-1]}_{on}')
        run.check_run_folder(folder, resume=False, overwrite=True)
        trainer = run.start(run.RunInputs(dataset.root, dataset, config, folder),
                            observer=observer)
        run.train(trainer, observer)
        fit = config.model.per_photo_appearance if fit_appearance is None else fit_appearance
        yield on, config, trainer, evaluate_split(trainer.model, trainer.test,
                                                  os.path.join(folder, 'test'),
                                                  fit_appearance=fit)


# ---------------------------------------------------------------------------------- cameras, scenes

def ray_distance_to_z(distance, camera):
    """Distances along the pixel-centre rays of a pinhole camera -> camera-space z."""
    h, w = distance.shape
    v, u = np.mgrid[0:h, 0:w] + 0.5
    x, y, _ = np.linalg.inv(camera.K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    return distance / np.sqrt(x * x + y * y + 1.0).reshape(h, w)


def render_encoded(scene, world_camera, spp, seed):
    """The ground-truth scene seen by ``world_camera`` at ``spp``, in a capture's 8-bit sRGB
    encoding (as floats in [0, 1]), with the sensor ``synth`` renders through."""

    desc = mitsuba_sensor_dict(world_camera, spp=spp, pixel_format='rgb')
    desc['near_clip'] = MITSUBA_NEAR_CLIP
    image = np.array(mi.render(scene, sensor=mi.load_dict(desc), spp=spp, seed=seed))
    return to_srgb8(image[..., :3]).astype(np.float64) / 255.0


# The objects example's renders: (label, with the objects, with the shadow catcher).
OBJECT_VARIANTS = (('reconstruction alone', False, False), ('with objects', True, False),
                   ('with objects and catcher', True, True))


def object_scenes(checkpoint, defines=None, scene=None):
    """``(label, Mitsuba scene)`` of each of :data:`OBJECT_VARIANTS` of the objects example
    (``scenes/insert_objects.xml`` of the package, or ``scene``) rendering ``checkpoint``;
    ``defines``: values of the scene's ``<default>`` parameters."""
    scene = scene or os.path.join(scenes_dir(), 'insert_objects.xml')
    with open(scene) as f:
        xml = f.read()
    defines = dict(defines or {}, checkpoint=os.path.abspath(checkpoint))
    for label, objects, catchers in OBJECT_VARIANTS:
        yield label, mi.load_string(object_variant_xml(xml, objects, catchers), **defines)


def object_variant_xml(xml: str, objects: bool, catchers: bool) -> str:
    """The objects example's scene XML without its shapes (``objects`` False) and/or without
    its shadow catchers (``catchers`` False)."""
    root = ET.fromstring(xml)
    for shape in root.findall('shape'):
        if not objects:
            root.remove(shape)
    if not objects:             # no shapes left for the integrator's proxies to name
        for proxies in root.iter('string'):
            if proxies.get('name') == 'proxies':
                proxies.set('value', '')
    if not catchers or not objects:
        for default in root.findall('default'):
            if default.get('name') == 'catchers':
                default.set('value', '')
    return ET.tostring(root, encoding='unicode')
