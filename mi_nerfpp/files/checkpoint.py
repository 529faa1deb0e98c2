"""The checkpoint file: a NumPy ``.npz`` archive (never pickle).

Keys:

* ``format`` — the string ``mi-nerfpp-checkpoint``; ``version`` — integer (now 4; the config of
  an older file is brought to today's layout by :func:`migrate_config`, one step per version);
* ``config`` — JSON: ``{"fg": <field config>, "bg": <field config or null>,
  "normalization": {"center": [x, y, z], "scale": s}, "color_space": "srgb"|"linear",
  "composite": "linear"|"srgb" (where samples are composited; missing: "srgb", older files),
  "appearance_images": n (per-image colour transforms, ``param/appearance`` of shape (n, 6),
  :mod:`~mi_nerfpp.core.appearance`; missing or 0: none),
  "pose_images": n (per-image camera corrections, ``param/poses`` of shape (n, 6),
  :mod:`~mi_nerfpp.core.poses`; missing or 0: none),
  "embedding_images": n (per-image appearance codes, ``param/embedding`` of shape (n, d), d the
  fields' ``appearance_dims``, :mod:`~mi_nerfpp.core.appearance`; missing: none),
  "sampling": {"fg_samples": n, "bg_samples": n, "fine_samples": n, "near": t} (the samples
  per ray the model is rendered with, :class:`~mi_nerfpp.core.model.RenderSettings`; missing in
  files written before it: those of the training config in ``meta``, else
  :class:`~mi_nerfpp.core.render.Sampling`'s defaults),
  "meta": {...}}``. ``normalization`` is the scene normalization
  ``x_model = (x_world - center)·scale`` (:class:`~mi_nerfpp.core.frame.Normalization`; version 1
  files stored ``center`` and ``scale`` at the top level and are still read);
  ``meta`` holds what training records (:data:`META`: iteration, seconds, dataset, the
  training config as :meth:`~mi_nerfpp.training.config.TrainConfig.to_dict` - flat in older
  files -, …; checked when the file is read, :func:`check_meta`);
* ``param/<name>`` — float32 arrays of the learnable parameters, named as in
  ``NeRFPPModel.parameters()`` (``fg.grid0``, ``bg.color.layers.0.weights``, …);
* ``bricks/<name>`` — the allocated bricks of a sparse grid level (``fg.sparse0``, ...: flat
  brick indices in slot order, :class:`~mi_nerfpp.core.bricks.BrickGrid`; version 4), which
  give its ``param/`` pool its shape;
* ``occupancy/<volume>`` — the occupancy grid of a volume (``fg``/``bg``) when the model
  skips empty space; its configuration is in ``config["occupancy"]``;
* ``coverage/seen``, ``coverage/colour`` — the colour painted where no training view looked
  and the weights it is blended in with (:class:`~mi_nerfpp.core.coverage.CoverageFill`);
  missing in files written before it, which render the background volume everywhere;
* ``state/<name>`` — optional arrays of training state (optimizer moments, RNG)
  that rendering ignores.

Files are written atomically: to a temporary file in the same folder, then renamed.
"""
from __future__ import annotations

import json
import math
import numbers
import os

import numpy as np

from mi_nerfpp.core.arrays import owned
from mi_nerfpp.core.fields import make_field
from mi_nerfpp.core.frame import Normalization
from mi_nerfpp.core.model import NeRFPPModel
from mi_nerfpp.core.occupancy import OccupancyGrid
from mi_nerfpp.core.render import SKIPPING, Sampling
from mi_nerfpp.core.coverage import CoverageFill
from mi_nerfpp.files.atomic import atomic_write_path
from mi_nerfpp.files.readers import FileReadError, decode_json, read_npz
from mi_nerfpp.errors import shown

FORMAT = 'mi-nerfpp-checkpoint'
VERSION = 4


def _v1_to_v2(config: dict) -> dict:
    """version 1 stored the scene normalization as top-level center and scale"""
    if 'normalization' not in config and 'center' in config:
        config['normalization'] = {'center': config.pop('center'), 'scale': config.pop('scale')}
    return config


def _v2_to_v3(config: dict) -> dict:
    """before version 3, grid fields ran their colour MLP at every sample (color 'sample') and
    had no antialiasing"""
    for key in ('fg', 'bg'):
        if config.get(key) and config[key].get('kind', 'grid') == 'grid':
            config[key].setdefault('color', 'sample')
            config[key].setdefault('antialias', False)
    return config


def _v3_to_v4(config: dict) -> dict:
    """version 4 added sparse grid levels (``bricks/``), which older files do not have"""
    return config


# The step that brings the config of a version-n file to version n + 1, for every version
# before VERSION (a new version appends its step: MIGRATIONS[4] = _v4_to_v5).
MIGRATIONS = {1: _v1_to_v2, 2: _v2_to_v3, 3: _v3_to_v4}
READABLE_VERSIONS = (*MIGRATIONS, VERSION)


def migrate_config(config: dict, version: int) -> dict:
    """The config of a version-``version`` file in the layout of :data:`VERSION` (a copy):
    every step of :data:`MIGRATIONS` from ``version`` on, in order."""
    config = json.loads(json.dumps(config))
    for step in range(version, VERSION):
        config = MIGRATIONS[step](config)
    return config


def migration_notes(version: int) -> list[str]:
    """What changed since files of ``version`` were written (for messages about their
    models): the first line of each migration step's docstring, oldest first."""
    return [' '.join(MIGRATIONS[step].__doc__.split()) for step in range(version, VERSION)]


class CheckpointError(ValueError):
    """A checkpoint file is missing, malformed or does not match its config."""


class NonFiniteStateError(ValueError):
    """A model or training state to be saved holds NaN or infinite values (nothing is
    written)."""


def _non_finite(arrays: dict) -> list[str]:
    """The names of the float arrays that hold NaN or inf."""
    return [k for k, v in arrays.items()
            if np.asarray(v).dtype.kind == 'f' and not np.all(np.isfinite(v))]


def save_checkpoint(path, model, meta=None, state=None):
    """Write ``model`` (and optional training ``state``: name -> array) to ``path`` atomically.

    Only finite state is written: parameters, occupancy grids or state arrays holding NaN or
    inf raise :class:`NonFiniteStateError` (naming them) before the file is touched, so a
    diverged run never replaces a good checkpoint."""
    path = os.fspath(path)
    config = dict(model.config, meta=meta or {})
    arrays = {'format': np.array(FORMAT), 'version': np.array(VERSION),
              'config': np.array(json.dumps(config))}
    for k, v in model.parameters().items():
        arrays[f'param/{k}'] = np.asarray(v.numpy(), dtype=np.float32)
    for k, grid in model.occupancy.items():
        arrays[f'occupancy/{k}'] = grid.numpy()
    for k, v in model.allocated_bricks().items():
        arrays[f'bricks/{k}'] = np.asarray(v, dtype=np.int64)
    if model.coverage is not None:
        for k, v in model.coverage.arrays().items():
            arrays[f'coverage/{k}'] = v
    for k, v in (state or {}).items():
        arrays[f'state/{k}'] = np.asarray(v)
    bad = _non_finite(arrays)
    if bad:
        names = ', '.join(bad[:4]) + (f' and {len(bad) - 4} more' if len(bad) > 4 else '')
        raise NonFiniteStateError(f'{names} hold NaN or infinite values')
    with atomic_write_path(path) as tmp, open(tmp, 'wb') as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())


# What to do about a checkpoint that cannot be read.
REMEDY = 'restore it from a copy, or train the model again'


def _read(path, keys=None):
    """``{name: array}`` of the checkpoint ``path`` (those of ``keys`` only, when given);
    :class:`CheckpointError` for a file that is missing, empty or not an ``.npz`` archive."""
    if not os.path.isfile(path):
        raise CheckpointError(f'{path}: checkpoint not found')
    if os.path.getsize(path) == 0:
        raise CheckpointError(f'{path}: not a mi-nerfpp checkpoint: the file is empty (0 bytes)')
    try:
        return read_npz(path, what='checkpoint', keys=keys)
    except FileReadError as e:
        raise CheckpointError(f'{path}: not a mi-nerfpp checkpoint (.npz archive): {e.detail}: '
                              f'{REMEDY}') from None


def _config(z, path) -> dict:
    """The config stored in the checkpoint ``path`` (its arrays ``z``), decoded."""
    if 'config' not in z:
        raise CheckpointError(f"{path}: not a mi-nerfpp checkpoint (no 'config' entry)")
    return decode_json(str(z['config']), path, what='checkpoint config', remedy=REMEDY,
                       error=CheckpointError)


def _count(v):
    return isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= 0


def _seconds(v):
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) \
        and v >= 0


def _number(v):
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _rng_state(v):
    """the state of the NumPy generator training draws its rays with (``default_rng``)"""
    try:
        np.random.default_rng().bit_generator.state = v
    except (ValueError, TypeError, KeyError, OverflowError):
        return False
    return True


def _data(v):
    """what training recorded of its data (``Trainer.data_summary``)"""
    return isinstance(v, dict) and all(
        (key not in v or ok(v[key])) for key, ok in (
            ('dataset', lambda p: isinstance(p, str)), ('train_views', _count),
            ('training_rays', _count)))


def _history_row(row):
    """(iteration, seconds, loss, PSNR of the batch[, {loss term: value}])"""
    return (isinstance(row, list) and len(row) in (4, 5) and _count(row[0])
            and _seconds(row[1]) and all(_number(v) for v in row[2:4])
            and (len(row) == 4 or (isinstance(row[4], dict)
                                   and all(_number(v) for v in row[4].values()))))


# What training records in a checkpoint's ``meta`` (``training`` writes it; every reader of a
# checkpoint reads it through :func:`check_meta`): entry -> (check, what it must be). A model
# saved by other code, or by an older version, may lack any of them (:func:`progress`).
META = {
    'iteration': (_count, 'a whole number >= 0'),
    'elapsed': (_seconds, 'a finite number of seconds >= 0'),
    'dataset': (lambda v: v is None or (isinstance(v, str) and v and '\0' not in v),
                'the path of a dataset'),
    'config': (lambda v: v is None or isinstance(v, dict), 'an object (the training options)'),
    'data': (_data, 'an object (the dataset path, the numbers of training views and rays)'),
    'rng': (_rng_state, "the state of NumPy's PCG64 generator"),
    'history': (lambda v: isinstance(v, list) and all(map(_history_row, v)),
                'a list of [iteration, seconds, loss, PSNR, {terms}] rows'),
}


def _occupancy(v):
    """{volume: {domain, resolution, threshold}}"""
    return isinstance(v, dict) and set(v) <= {'fg', 'bg'} and all(
        isinstance(c, dict) and set(c) <= {'domain', 'resolution', 'threshold'}
        and c.get('domain') == {'fg': 'ball', 'bg': 'inverted_sphere'}[k]
        and _count(c.get('resolution', 64)) and 4 <= c.get('resolution', 64) <= 4096
        and _seconds(c.get('threshold', 0.0)) for k, c in v.items())


# What the model's entries of a checkpoint's config must be besides its fields' (which
# :func:`~mi_nerfpp.core.fields.check_field_config` checks) and its normalization: checked
# before anything is built from them.
def _normalization(v):
    """{center: [x, y, z], scale: s}"""
    center, scale = (v.get('center'), v.get('scale')) if isinstance(v, dict) else (None, None)
    return (isinstance(center, list) and len(center) == 3
            and all(_number(c) and math.isfinite(c) for c in center)
            and _seconds(scale) and scale > 0)


def _sample_counts(v):
    """{fg_samples, bg_samples, fine_samples, near}"""
    counts = ('fg_samples', 'bg_samples', 'fine_samples')
    return isinstance(v, dict) and set(v) <= {*counts, 'near'} and all(
        _count(v[k]) and v[k] <= 1 << 16 for k in counts if k in v) and (
        _seconds(v['near']) if 'near' in v else True)


MODEL = {
    'fg': (lambda v: isinstance(v, dict), 'an object (the foreground field)'),
    'bg': (lambda v: v is None or isinstance(v, dict), 'an object (the background field) or '
           'null'),
    'normalization': (_normalization, 'an object of a center (three finite numbers) and a '
                      'scale > 0'),
    'sampling': (_sample_counts, 'an object of fg_samples, bg_samples and fine_samples (whole '
                 'numbers >= 0) and near (a distance >= 0)'),
    'appearance_images': (lambda v: _count(v) and v < 2 ** 31, 'a whole number >= 0'),
    'pose_images': (lambda v: _count(v) and v < 2 ** 31, 'a whole number >= 0'),
    'embedding_images': (lambda v: _count(v) and v < 2 ** 31, 'a whole number >= 0'),
    'occupancy': (_occupancy, 'an object of the grids fg (domain ball) and bg (domain '
                  'inverted_sphere), each with a resolution from 4 to 4096 and a threshold '
                  '>= 0'),
    'color_space': (lambda v: v in ('srgb', 'linear'), "'srgb' or 'linear'"),
    'composite': (lambda v: v in ('srgb', 'linear'), "'srgb' or 'linear'"),
}


def _check(config, schema, where, path):
    """:class:`CheckpointError` naming the first entry of ``config`` that ``schema`` (entry ->
    (check, what it must be)) refuses."""
    for key, (ok, need) in schema.items():
        if key in config and not ok(config[key]):
            raise CheckpointError(f'{path}: {where}: {key} must be {need}, got '
                                  f'{shown(config[key])}: {REMEDY}')


def check_meta(meta, path) -> dict:
    """``meta`` when it has :data:`META`'s layout (entries it does not name are kept), else
    :class:`CheckpointError` naming the file and the entry."""
    if not isinstance(meta, dict):
        raise CheckpointError(f'{path}: invalid config: its "meta" is not an object: {REMEDY}')
    _check(meta, META, 'its training record (meta) is damaged', path)
    return meta


def progress(meta, path) -> tuple[int, float]:
    """``(iteration, seconds)`` of training that the checked ``meta`` of checkpoint ``path``
    records; :class:`CheckpointError` for one that does not (what continues or reports a run
    needs them)."""
    missing = [f'meta.{key}' for key in ('iteration', 'elapsed') if key not in meta]
    if missing:
        raise CheckpointError(f'{path}: its training record has no {" and no ".join(missing)} '
                              f'(not saved by optimize, or damaged): {REMEDY}')
    return int(meta['iteration']), float(meta['elapsed'])


def read_meta(path) -> dict:
    """The ``meta`` a checkpoint was saved with (its training config, iteration, ...), read
    without building its model and checked (:func:`check_meta`); errors as
    :func:`load_checkpoint`'s."""
    path = os.fspath(path)
    return check_meta(_config(_read(path, keys=('config',)), path).get('meta', {}), path)


def _set_bricks(model, z, path) -> None:
    """Allocate the sparse levels' bricks stored in ``z`` (``bricks/<volume>.sparse<i>``):
    each a list of whole, distinct brick indices within its level, as many as its parameter's
    pool holds; anything else (a damaged file) is a :class:`CheckpointError` naming the entry
    (a float or text list was read as indices, issue 63)."""
    for key in [k for k in z if k.startswith('bricks/')]:
        name, bricks = key[len('bricks/'):], np.asarray(z[key])
        if bricks.ndim != 1 or bricks.dtype.kind not in 'iu':
            raise CheckpointError(f'{path}: {key} is not a list of whole brick indices (shape '
                                  f'{bricks.shape}, {bricks.dtype}): {REMEDY}')
        pool = z.get(f'param/{name}') if hasattr(z, 'get') else None
        if pool is not None and np.ndim(pool) >= 1 and \
                np.shape(pool)[0] != max(bricks.size, 1):
            raise CheckpointError(f'{path}: {key} lists {bricks.size} bricks, its parameter '
                                  f'param/{name} holds {np.shape(pool)[0]}: {REMEDY}')
        try:
            model.set_bricks({name: bricks})
        except ValueError as e:
            raise CheckpointError(f'{path}: {key}: {e}: {REMEDY}') from None


def load_checkpoint(path, seed=0):
    """Read a checkpoint. Returns ``(model, meta, state)``; errors name the path and the problem."""
    path = os.fspath(path)
    return from_arrays(_read(path), path, seed)


def from_arrays(z: dict, path, seed=0):
    """:func:`load_checkpoint` of the arrays ``z`` read from checkpoint ``path``: the model,
    its checked ``meta`` and its state, or :class:`CheckpointError` naming ``path``."""
    if 'format' not in z or str(z['format']) != FORMAT:
        raise CheckpointError(f"{path}: not a mi-nerfpp checkpoint (no 'format' = '{FORMAT}' entry)")
    try:
        version = int(z['version'])
    except (KeyError, TypeError, ValueError):
        raise CheckpointError(f"{path}: not a mi-nerfpp checkpoint (no integer 'version' "
                              f"entry)") from None
    if version not in READABLE_VERSIONS:
        raise CheckpointError(f'{path}: checkpoint version {version}, this mi-nerfpp reads '
                              f'{", ".join(map(str, READABLE_VERSIONS))}')
    config = _config(z, path)
    meta = check_meta(config.get('meta', {}), path)
    try:
        config = migrate_config(config, version)
        _check(config, MODEL, 'its model config is damaged', path)
        fg = make_field(config['fg'], seed=seed)
        bg = make_field(config['bg'], seed=seed + 1) if config.get('bg') else None
        occupancy = {k: OccupancyGrid(density=z[f'occupancy/{k}'], **c)
                     for k, c in config.get('occupancy', {}).items()}
        model = NeRFPPModel(fg, bg, normalization=Normalization.from_config(config),
                            color_space=config.get('color_space', 'srgb'), occupancy=occupancy,
                            # written before issue 11: sRGB models composited encoded colour
                            composite=config.get('composite', 'srgb'),
                            appearance_images=int(config.get('appearance_images', 0)),
                            pose_images=int(config.get('pose_images', 0)),
                            embedding_images=int(config.get('embedding_images', 0)),
                            sampling=_sampling(config))
        _set_bricks(model, z, path)
        fill = {k[len('coverage/'):]: v for k, v in z.items() if k.startswith('coverage/')}
        if fill:
            model.coverage = CoverageFill.from_arrays(fill)
    except CheckpointError:
        raise
    except (KeyError, ValueError, TypeError, AttributeError, OverflowError, ZeroDivisionError,
            RuntimeError, MemoryError) as e:     # what a damaged config meets as it is built
        text = ' '.join(str(e).split())     # a library's message may span lines
        if isinstance(e, KeyError):         # a missing key, or a message of our own
            key = str(e.args[0]) if e.args else ''
            text = key if ' ' in key else f'it has no entry {key!r}'
        raise CheckpointError(f'{path}: invalid config: {text}: {REMEDY}') from None

    expected = model.parameters()
    stored = {k[len('param/'):]: v for k, v in z.items() if k.startswith('param/')}
    missing = sorted(set(expected) - set(stored))
    extra = sorted(set(stored) - set(expected))
    if missing or extra:
        raise CheckpointError(f'{path}: parameters do not match the config '
                              f'(missing {missing}, unexpected {extra})')
    values = {}
    for k, v in stored.items():
        if tuple(v.shape) != tuple(expected[k].shape):
            raise CheckpointError(f"{path}: parameter '{k}' has shape {tuple(v.shape)}, "
                                  f'the config needs {tuple(expected[k].shape)}')
        if not np.all(np.isfinite(v)):
            raise CheckpointError(f"{path}: parameter '{k}' contains NaN or inf")
        values[k] = owned(v)
    model.set_parameters(values)
    state = {k[len('state/'):]: v for k, v in z.items() if k.startswith('state/')}
    return model, meta, state


def read_version(path) -> int:
    """The format version a checkpoint was written with (1 when it does not say); errors as
    :func:`read_meta`'s."""
    path = os.fspath(path)
    z = _read(path, keys=('version',))
    try:
        return int(z['version']) if 'version' in z else 1
    except (TypeError, ValueError):
        raise CheckpointError(f"{path}: not a mi-nerfpp checkpoint (no integer 'version' "
                              f"entry)") from None


def _sampling(config):
    """The samples per ray a checkpoint's model renders with: stored with the model, or in a
    file written before that, those it was trained with (:func:`_legacy_sampling`); None (the
    model's default) for a file that says neither."""
    if 'sampling' in config:
        return Sampling(**config['sampling'])
    trained = config.get('meta', {}).get('config')
    return _legacy_sampling(trained) if trained else None


# ----------------------------------------------------------------------------- legacy reader
# Files written before the model stored its samples per ray (before ff06f22: version 2 and
# older) have them only in the training config of their ``meta``. The reader below is the one
# place this layer reads a training config: the layout those files have, frozen (one flat dict
# of options by name, or the option groups ``sampling`` and ``model``), which the training
# layer's config need not keep.

def _legacy_sampling(stored: dict) -> Sampling:
    """Legacy reader: the samples per ray of a model from the training config an older file
    stored in its ``meta`` (see above); counts it does not store take training's defaults
    (:data:`~mi_nerfpp.core.render.SKIPPING`)."""
    grouped = isinstance(stored.get('model'), dict)
    sampling = stored.get('sampling', {}) if grouped else stored
    kind = stored['model'].get('kind') if grouped else stored.get('model')   # flat: --model
    counts = [sampling.get(name, getattr(SKIPPING, name))
              for name in ('fg_samples', 'bg_samples', 'fine_samples')]
    return Sampling.of_model(kind or 'nerfpp', *counts)
