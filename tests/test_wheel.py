"""The installed package: a wheel of the project, installed into a fresh virtual environment,
runs ``python -m mi_nerfpp`` from outside the repository with its own scenes and modules.

Slow-ish (building the wheel, a venv, a tiny capture and a 0.2-minute training: about a minute
on 2 cores). The wheel is built by ``pip wheel``: offline where the running interpreter has
what setuptools needs to build one (the ``wheel`` package, or setuptools >= 70.1), else in
pip's isolated build environment, which fetches setuptools from the package index.
"""
from __future__ import annotations

import glob
import importlib.util
import json
import os
import re
import shutil
import site
import subprocess
import sys
import sysconfig
import zipfile

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# What the checkout holds that a build must not see (ignored by git too).
NOT_SOURCES = shutil.ignore_patterns('.git', '.venv', 'build', 'dist', 'runs', 'out',
                                     'data_cache', '*.egg-info', '__pycache__', '.pytest_cache')


def _run(cmd, cwd, env=None, timeout=600):
    result = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True,
                            timeout=timeout)
    assert result.returncode == 0, (f"{' '.join(map(str, cmd))} failed ({result.returncode}):\n"
                                    f'{result.stdout[-3000:]}\n{result.stderr[-3000:]}')
    return result.stdout


def _builds_offline():
    """Whether this interpreter's setuptools can build a wheel without downloading anything."""
    return (importlib.util.find_spec('wheel') is not None
            or importlib.util.find_spec('setuptools.command.bdist_wheel') is not None)


@pytest.fixture(scope='module')
def wheel(tmp_path_factory):
    """A wheel built from a copy of the working tree (the build writes build/ and *.egg-info)."""
    tmp = tmp_path_factory.mktemp('wheel')
    source = tmp / 'source'
    shutil.copytree(ROOT, source, ignore=NOT_SOURCES)
    cmd = [sys.executable, '-m', 'pip', 'wheel', '--no-deps', '--disable-pip-version-check',
           '-w', str(tmp / 'dist'), str(source)]
    if _builds_offline():
        cmd.insert(4, '--no-build-isolation')
    _run(cmd, cwd=tmp)
    (path,) = glob.glob(str(tmp / 'dist' / 'mi_nerfpp-*.whl'))
    return path


@pytest.fixture(scope='module')
def venv(wheel, tmp_path_factory):
    """A fresh venv with the wheel installed (no dependencies); it finds mitsuba, drjit, ... in
    this interpreter's site-packages through a .pth file (``python -m venv
    --system-site-packages`` would give the base interpreter's, not this venv's), whose own
    .pth files - an editable install of the checkout - are not run."""
    path = tmp_path_factory.mktemp('venv') / 'env'
    _run([sys.executable, '-m', 'venv', str(path)], cwd=path.parent)
    python = str(path / 'bin' / 'python')
    purelib = _run([python, '-c', 'import sysconfig; print(sysconfig.get_paths()["purelib"])'],
                   cwd=path.parent).strip()
    ours = list(dict.fromkeys(site.getsitepackages() + [sysconfig.get_paths()['purelib'],
                                                        sysconfig.get_paths()['platlib']]))
    with open(os.path.join(purelib, 'mi_nerfpp_test_dependencies.pth'), 'w') as f:
        f.write('\n'.join(ours) + '\n')
    _run([python, '-m', 'pip', 'install', '--no-deps', '--no-index',
          '--disable-pip-version-check', wheel], cwd=path.parent)
    return python, purelib


def _env(cache):
    """The environment of a user's shell: no PYTHONPATH pointing at the checkout (and captures
    cached in ``cache``, not in the user's cache)."""
    env = {k: v for k, v in os.environ.items() if k not in ('PYTHONPATH', 'PYTHONHOME')}
    env['MI_NERFPP_CACHE'] = str(cache)
    return env


def test_wheel_holds_every_module_and_the_scenes_files(wheel):
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
    package = os.path.join(ROOT, 'mi_nerfpp')
    modules = {os.path.relpath(p, ROOT).replace(os.sep, '/')
               for p in glob.glob(os.path.join(package, '**', '*.py'), recursive=True)}
    assert modules and modules <= names, sorted(modules - names)
    scenes = glob.glob(os.path.join(ROOT, 'scenes', '*.xml'))
    assert {'gt_garden.xml', 'gt_plaza.xml', 'gt_bounded.xml', 'insert_objects.xml',
            'render_random.xml'} <= {os.path.basename(p) for p in scenes}
    for xml in scenes:
        assert f'mi_nerfpp/scenes/{os.path.basename(xml)}' in names
        # Every file a scene loads (textures, environment maps) is in the wheel too.
        with open(xml) as f:
            for ref in re.findall(r'name="filename"\s+value="([^"$]+)"', f.read()):
                assert f'mi_nerfpp/scenes/{ref}' in names, (xml, ref)
    for name in ('train_cam_dict_norm.json', 'LICENSE-nerfplusplus-BSD-2'):
        assert f'mi_nerfpp/trajectories/{name}' in names


def test_installed_wheel_synthesizes_and_optimizes_outside_the_repository(venv, tmp_path):
    python, purelib = venv
    work = tmp_path / 'user'         # a folder outside the repository
    work.mkdir()
    env = _env(tmp_path / 'cache')
    where = json.loads(_run([python, '-c', (
        'import json, mi_nerfpp, mi_nerfpp.data.synth as s; '
        'print(json.dumps([mi_nerfpp.__file__, s.scene_file(s.DEFAULT_SCENE)]))')],
        cwd=work, env=env).strip().splitlines()[-1])
    installed = os.path.realpath(os.path.join(purelib, 'mi_nerfpp'))
    # The wheel's copy is imported, and the default scene is the one it carries.
    assert os.path.realpath(where[0]) == os.path.join(installed, '__init__.py')
    assert os.path.realpath(where[1]) == os.path.join(installed, 'scenes', 'gt_garden.xml')
    assert os.path.isfile(where[1])
    # Mitsuba loads the packaged default scene (with its environment map) and renders a capture.
    _run([python, '-m', 'mi_nerfpp', 'synth', where[1], '--out', 'capture', '--views', '6',
          '--res', '16x12', '--spp', '2'], cwd=work, env=env)
    assert json.loads((work / 'capture' / 'capture.json').read_text())['complete']
    _run([python, '-m', 'mi_nerfpp', 'optimize', 'capture', '--minutes', '0.2', '--out', 'run'],
         cwd=work, env=env)
    metrics = json.loads((work / 'run' / 'metrics.json').read_text())
    assert (work / 'run' / 'model.npz').is_file()
    assert metrics['test']['psnr'] > 0 and len(metrics['test']['views']) == 1
