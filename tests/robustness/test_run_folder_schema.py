"""Run folders whose checkpoint config was damaged (issue 63, item 2): a property test.

A real run folder is trained once. Then every entry of its checkpoint's config - the model's
(``fg``, ``bg``, ``normalization``, ...) and the training record in ``meta`` (iteration,
seconds, dataset, history, random state and each stored training option) - is deleted,
retyped or given an odd value, :data:`CORRUPTIONS` times per entry, seeded. Each damaged
config is read as the commands read a run folder (:func:`~mi_nerfpp.files.checkpoint.from_arrays`
on the file's arrays, then :func:`~mi_nerfpp.training.config.stored_config` and
:meth:`~mi_nerfpp.training.config.TrainConfig.from_stored`): it opens, or it is refused with a
:class:`~mi_nerfpp.files.checkpoint.CheckpointError` naming the file in one line of the project's
own (no message of Python, NumPy or Dr.Jit passed on) - never another exception.

Then end to end, through the command line on a real file: per entry, the first damage that is
refused and the first that opens go through ``evaluate`` (and, for the training record,
``optimize --resume`` too); each ends with one clear line naming the checkpoint, or succeeds -
never "a bug", never a traceback.
"""
import collections
import json
import math
import os
import random
import re
import shutil

import numpy as np
import pytest

from mi_nerfpp.files.checkpoint import CheckpointError, from_arrays
from mi_nerfpp.training.config import TrainConfig, stored_config
from tests.robustness.common import TINY, run_cli

CORRUPTIONS = 200       # per entry (issue 63: at least 200 per run-folder field)
# End to end, a damaged config that opens renders with kernels of its own (seconds each): so
# many entries' (drawn, seeded) go through evaluate; every entry's refusal does.
OPENED_END_TO_END = 8
# What Python's, NumPy's and Dr.Jit's own messages say, which a refusal must not pass on.
LIBRARY_TEXT = re.compile(r'NoneType|object is not|has no attribute|jit_|drjit|nanobind|'
                          r'__init__\(\)|unhashable|not supported between|positional argument|'
                          r'Invoked with|cannot convert|index-sized')
# The entries of the training record that only a resumed run reads.
RESUMED = [('meta', key) for key in ('iteration', 'elapsed', 'rng', 'history', 'data')]
# The run folder: small grids, and the parts a model may have besides its volumes (per-photo
# colour transforms and codes, pose corrections, a sparse level, the error map's state). A
# resumed run takes the same options but --error-rays (its own is read back): RUN[:-2].
RUN = TINY + ['--appearance', '--refine-poses', '--appearance-embedding', '2',
              '--occupancy-res', '8', '--grid-sparse', '16', '--sparse-at', '0.1',
              '--error-rays', '0.5']


@pytest.fixture(scope='module')
def run_folder(capture, tmp_path_factory):
    from mi_nerfpp.commands.cli import main
    out = tmp_path_factory.mktemp('schema') / 'run'
    assert main(['optimize', capture, '--out', str(out), *RUN]) == 0
    with np.load(out / 'model.npz') as z:
        arrays = {k: z[k] for k in z.files}
    return out, arrays, json.loads(str(arrays['config']))


def _entries(tree, prefix=()):
    """The path of every entry of a JSON object, depth first (lists are values)."""
    for key, value in tree.items():
        yield prefix + (key,)
        if isinstance(value, dict):
            yield from _entries(value, prefix + (key,))


def _scalar(rng):
    kind = rng.randrange(6)
    if kind == 0:
        return rng.choice([None, True, False])
    if kind == 1:
        if rng.random() < 0.5:
            return rng.choice([0, -1, 1, 2 ** 31, 2 ** 63, 2 ** 64, -(2 ** 40)])
        return rng.randint(-10 ** rng.randint(0, 20), 10 ** rng.randint(0, 20))
    if kind == 2:
        return rng.choice([math.nan, math.inf, -math.inf, -0.0, 1e-300, 1e300]) \
            if rng.random() < 0.4 else rng.uniform(-1, 1) * 10 ** rng.randint(-10, 30)
    if kind == 3:
        return rng.choice(['', 'x', '3', 'nan', '\0', 'é', 'grid', 'nerfpp', '/nonexistent',
                           'a' * 300])
    if kind == 4:
        return [_scalar(rng) for _ in range(rng.randrange(4))]
    return {rng.choice(['a', 'kind', 'state', '0']): _scalar(rng)}


def _damage(value, rng):
    """A damaged stand-in for ``value``: a random value of any type, or one of its own kind
    gone wrong (a list with an element changed, cut or grown; a number scaled or negated)."""
    if rng.random() < 0.5:
        return _scalar(rng)
    if isinstance(value, list) and value:
        out = list(value)
        how = rng.randrange(3)
        if how == 0:
            out[rng.randrange(len(out))] = _scalar(rng)
        elif how == 1:
            out = out[:rng.randrange(len(out))]
        else:
            out.append(_scalar(rng))
        return out
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return value * rng.choice([-1, 0, 0.5, 1.5, 10 ** rng.randint(1, 30)])
    if isinstance(value, str):
        return rng.choice([value + 'x', value.upper(), value[:1]])
    if isinstance(value, dict):
        return {k: _scalar(rng) for k in value}
    return _scalar(rng)


def _damaged(config, entry, rng, first):
    """A copy of ``config`` with ``entry`` deleted (the first case) or damaged; and how."""
    c = json.loads(json.dumps(config))
    parent = c
    for key in entry[:-1]:
        parent = parent[key]
    if first:
        del parent[entry[-1]]
        return c, 'deleted'
    parent[entry[-1]] = _damage(parent[entry[-1]], rng)
    return c, repr(parent[entry[-1]])[:80]


def _open(arrays, config, path):
    """Read a damaged config as the commands read a run folder."""
    z = dict(arrays, config=np.array(json.dumps(config)))
    model, meta, _ = from_arrays(z, path)
    TrainConfig.from_stored(stored_config(meta, path, model.config), weights=model.config)


def test_every_damaged_entry_opens_or_is_refused_naming_the_file(run_folder):
    out, arrays, config = run_folder
    path = str(out / 'model.npz')
    rng = random.Random(63)
    entries = list(_entries(config))
    assert len(entries) > 100 and ('meta', 'config', 'schedule', 'batch_rays') in entries
    outcomes = collections.Counter()
    for entry in entries:
        for k in range(CORRUPTIONS):
            damaged, how = _damaged(config, entry, rng, first=k == 0)
            try:
                _open(arrays, damaged, path)
                outcomes['opened'] += 1
            except CheckpointError as e:
                outcomes['refused'] += 1
                text = str(e)
                assert text.startswith(f'{path}: ') and '\n' not in text, (entry, how, text)
                assert not LIBRARY_TEXT.search(text), (entry, how, text)
            except Exception as e:     # noqa: BLE001 - anything else is what this test finds
                pytest.fail(f'{".".join(entry)} = {how}: {type(e).__name__}: {e}')
    assert sum(outcomes.values()) == len(entries) * CORRUPTIONS
    assert outcomes['refused'] > 0 and outcomes['opened'] > 0
    print(f'{len(entries)} entries x {CORRUPTIONS}: {dict(outcomes)}')


def _clear(status, err, path):
    """A command that failed said so in one line naming the checkpoint (or its folder)."""
    assert 'Traceback' not in err and 'a bug' not in err, err
    if status == 0:
        return 'ok'
    errors = [line for line in err.splitlines() if line.startswith('error:')]
    assert status == 1 and len(errors) == 1, err
    return 'clear'


@pytest.mark.parametrize('part', ['model', 'meta'])
def test_commands_end_clearly_on_a_damaged_run_folder(run_folder, capture, capsys, tmp_path,
                                                      part):
    """Per entry, the first damage that is refused (of seeded draws as above) goes through
    ``evaluate`` on a real file, and for :data:`OPENED_END_TO_END` entries (and those only a
    resumed run reads) the first that opens; the training record's entries that only a resumed
    run reads also through ``optimize --resume``."""
    out, arrays, config = run_folder
    rng = random.Random(6300)
    entries = [e for e in _entries(config) if (e[0] == 'meta') == (part == 'meta')]
    opened = set(random.Random(part).sample(range(len(entries)), OPENED_END_TO_END))
    seen = collections.Counter()
    for i, entry in enumerate(entries):
        tried = set() if i in opened or entry[:2] in RESUMED else {'opened'}
        for k in range(CORRUPTIONS):
            damaged, how = _damaged(config, entry, rng, first=k == 0)
            folder = tmp_path / 'case'
            path = str(folder / 'model.npz')
            try:
                _open(arrays, damaged, path)
                kind = 'opened'
            except CheckpointError:
                kind = 'refused'
            if kind in tried:
                continue
            tried.add(kind)
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            np.savez(path, **dict(arrays, config=np.array(json.dumps(damaged))))
            status, _, err = run_cli(capsys, 'evaluate', folder)
            result = _clear(status, err, path)
            if kind == 'refused':
                assert result == 'clear' and f'{path}: ' in err, (entry, how, err)
            seen[(kind, result)] += 1
            if entry[:2] in RESUMED:
                status, _, err = run_cli(capsys, 'optimize', capture, '--out', folder,
                                         '--resume', *RUN[:-2], '--iterations', '3')
                seen[('resume', _clear(status, err, path))] += 1
            if len(tried) == 2:
                break
    assert seen[('opened', 'ok')] > 0
    assert seen[('refused', 'clear')] > 0
    if part == 'meta':
        assert seen[('resume', 'ok')] > 0
    print(part, dict(seen))
