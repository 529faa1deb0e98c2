"""One reader per kind of file (:mod:`mi_nerfpp.files.readers`): every JSON and NumPy read of the
package goes through it, and a damaged file of any kind ends with the reader's one-line error
that names the file, or reads.

* The source scan (``ast``, nothing imported) fails on a direct ``json.load``, a ``json.loads``
  of anything but ``json.dumps(...)`` (a deep copy), ``np.load``, an ``OpenEXR.File`` that reads
  (one argument: a path; writes pass a header and the pixels), an ``imread`` or a Pillow
  ``Image.open`` outside the modules that read that kind of file. Reads not yet behind one
  reader would be listed in :data:`SCATTERED`, each one named; a listed site that is gone must
  leave the list.
* The property tests damage one file :data:`CASES` times per kind, seeded (the same cases every
  run): cut short at a random byte, random bytes flipped, random bytes (not UTF-8) in its place,
  bytes that are not UTF-8 put inside it, a JSON value of another type in its place, a value
  inside it swapped for another JSON value, an edge number in place of one of its numbers, an
  empty file, a folder, a symbolic link to itself (unreadable: ELOOP) or to nothing. Each case
  reads, or ends with the reader's error class and one line that names the file and holds no
  traceback and no "a bug" - never another exception.
"""
import ast
import json
import re
import shutil
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from mi_nerfpp.commands.cli import describe
from mi_nerfpp.files.readers import (FileReadError, read_exr, read_image, read_json,
                                     read_npy, read_npz)

ROOT = Path(__file__).resolve().parent.parent.parent
PACKAGE = ROOT / 'mi_nerfpp'
CASES = 210                       # damaged files per kind of file (at least 200)

# Where each kind of read may be written directly: the readers of that kind of file.
READERS = {
    'json.load': {'files/readers.py'},
    'json.loads': {'files/readers.py'},
    'np.load': {'files/readers.py'},
    'OpenEXR.File': {'files/readers.py', 'files/exr.py', 'data/images.py'},
    'imread': {'files/readers.py', 'data/images.py'},
    'Image.open': {'files/readers.py', 'data/images.py'},
}
# Reads not yet behind their kind's reader (issue 63, item 1: to move behind one).
SCATTERED = set()

def _dotted(node) -> str:
    """``a.b.c`` of a call's function (Name / Attribute chain), '' for anything else."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if isinstance(node, ast.Name):
        parts.append(node.id)
        return '.'.join(reversed(parts))
    return ''


def _kind(call: ast.Call) -> str | None:
    """The kind of file read of ``call`` (a key of :data:`READERS`), or None."""
    name = _dotted(call.func)
    if name == 'json.load':
        return name
    if name == 'json.loads':
        arg = call.args[0] if call.args else None
        copy = isinstance(arg, ast.Call) and _dotted(arg.func) == 'json.dumps'
        return None if copy else name
    if name in ('np.load', 'numpy.load'):
        return 'np.load'
    if name == 'OpenEXR.File':      # OpenEXR.File(path[, flags]) reads, (header, pixels) writes
        return name if len(call.args) == 1 else None
    if name.split('.')[-1] == 'imread':
        return 'imread'
    if name in ('Image.open', 'PIL.Image.open'):
        return 'Image.open'
    return None


def direct_reads() -> set[tuple[str, str, int]]:
    """``{(kind, module path under mi_nerfpp/, line)}`` of every direct read in the package."""
    found = set()
    for path in sorted(PACKAGE.rglob('*.py')):
        tree = ast.parse(path.read_text(encoding='utf-8'), str(path))
        module = path.relative_to(PACKAGE).as_posix()
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and _kind(node):
                found.add((_kind(node), module, node.lineno))
    return found


def test_every_read_goes_through_its_reader():
    reads = direct_reads()
    stray = sorted(f'mi_nerfpp/{module}:{line}: {kind}' for kind, module, line in reads
                   if module not in READERS[kind] and (kind, module) not in SCATTERED)
    assert not stray, ('read these files through mi_nerfpp.files.readers (JSON, NumPy), '
                       'files.exr (EXR) or data.images (images):\n' + '\n'.join(stray))
    gone = sorted(SCATTERED - {(kind, module) for kind, module, _ in reads})
    assert not gone, f'no longer scattered, take them off SCATTERED: {gone}'


def test_the_scan_finds_what_it_looks_for(tmp_path):
    source = ('import json, numpy as np, OpenEXR, imageio.v3 as iio\n'
              'json.load(f); json.loads(text); json.loads(json.dumps(x)); np.load(p)\n'
              'OpenEXR.File(p); OpenEXR.File(header, pixels); iio.imread(p); Image.open(p)\n')
    calls = [n for n in ast.walk(ast.parse(source)) if isinstance(n, ast.Call)]
    kinds = [k for k in map(_kind, calls) if k]
    assert sorted(kinds) == ['Image.open', 'OpenEXR.File', 'imread', 'json.load', 'json.loads',
                             'np.load']


# ------------------------------------------------------------------------------ damage

EDGE_NUMBERS = ['0', '-1', '-0.0', '1e-45', '3', '2147483648', '1e30', '1e308', '-1e308',
                'NaN', 'Infinity', '-Infinity', '18446744073709551616', '1' * 5000, '1e999']
OTHER_VALUES = [None, True, False, 0, -1, 1.5, 1e308, float('nan'), '', 'x', [], [1, 2], {},
                {'a': 1}, [[0.0] * 4] * 4]
JSON_DAMAGE = ('cut short', 'flipped bytes', 'random bytes', 'not UTF-8 inside',
               'other top-level type', 'value swapped', 'edge number', 'empty', 'folder',
               'link to itself', 'dangling link')
BINARY_DAMAGE = ('cut short', 'flipped bytes', 'random bytes', 'empty', 'folder',
                 'link to itself', 'dangling link')


def _paths(value, at=()):
    """Every path (tuple of keys and indices) into a JSON value."""
    yield at
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _paths(v, at + (k,))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _paths(v, at + (i,))


def _swapped(value, rng):
    """``value`` (decoded JSON) with one value inside it replaced by another."""
    paths = list(_paths(value))[1:]
    if not paths:
        return OTHER_VALUES[rng.integers(len(OTHER_VALUES))]
    at = paths[rng.integers(len(paths))]
    value = json.loads(json.dumps(value))
    parent = value
    for key in at[:-1]:
        parent = parent[key]
    parent[at[-1]] = OTHER_VALUES[rng.integers(len(OTHER_VALUES))]
    return value


def damage(path: Path, how: str, rng) -> None:
    """Damage the file ``path`` in place (see the module docstring)."""
    data = path.read_bytes()
    if how in ('empty', 'folder', 'link to itself', 'dangling link'):
        path.unlink()
        if how == 'empty':
            path.write_bytes(b'')
        elif how == 'folder':
            path.mkdir()
            (path / 'inside.json').write_text('{}')
        elif how == 'link to itself':
            path.symlink_to(path.name)
        else:
            path.symlink_to(path.name + '.missing')
        return
    if how == 'cut short':
        data = data[:rng.integers(len(data))]
    elif how == 'flipped bytes':
        data = bytearray(data)
        for _ in range(rng.integers(1, 9)):
            data[rng.integers(len(data))] = rng.integers(256)
        data = bytes(data)
    elif how == 'random bytes':
        data = bytes(rng.integers(0, 256, rng.integers(1, 300)).astype(np.uint8))
        data += b'\xff'                               # never UTF-8
    elif how == 'not UTF-8 inside':
        at = rng.integers(len(data) + 1)
        bad = [b'\xff', b'\xc3', b'\xe2\x82', b'\xed\xa0\x80', b'\x80\x80'][rng.integers(5)]
        data = data[:at] + bad + data[at:]
    elif how == 'other top-level type':
        value = json.loads(data)
        choices = [OTHER_VALUES[rng.integers(len(OTHER_VALUES))]]
        choices += [v for v in (value.values() if isinstance(value, dict) else [])]
        data = json.dumps(choices[rng.integers(len(choices))]).encode()
    elif how == 'value swapped':
        data = json.dumps(_swapped(json.loads(data), rng)).encode()
    elif how == 'edge number':
        text = data.decode()
        numbers = list(re.finditer(r'-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?', text))
        m = numbers[rng.integers(len(numbers))]
        number = EDGE_NUMBERS[rng.integers(len(EDGE_NUMBERS))]
        data = (text[:m.start()] + number + text[m.end():]).encode()
    path.write_bytes(data)


def _restore(path: Path, template: Path) -> None:
    if path.is_symlink() or path.is_file():
        path.unlink()
    elif path.is_dir():
        shutil.rmtree(path)
    shutil.copyfile(template, path)


# What a line shows of an exception that no reader put in words: Python's and the OS's
# spelling, an object's address, a byte string, the text of a traceback.
LIBRARY_TEXT = re.compile(r"Errno|object at 0x|b'|\\x[0-9a-f]{2}|Traceback|a bug")


def check_refusal(error: BaseException, kind: type, named, how: str, pattern=None) -> str:
    """The one line of ``error``, checked: the reader's class, one line naming ``named`` (the
    file, or the folder it is in) as the command line prints it, without traceback, "a bug" or
    library text (:data:`LIBRARY_TEXT`), matching ``pattern`` when given."""
    assert isinstance(error, kind), (how, type(error), error)
    line = describe(error, None)
    assert '\n' not in line and not LIBRARY_TEXT.search(line), (how, line)
    assert str(named) in line, (how, line)
    assert pattern is None or re.fullmatch(pattern, line), (how, line)
    return line


def run_cases(template: Path, path: Path, read, error: type, damages, seed: str, named=None,
              pattern=None):
    """Read ``path`` damaged :data:`CASES` times (damage ``i % len(damages)``), each refusal
    naming ``named`` (default: ``path``) and matching ``pattern`` when given; returns
    ``{damage: [read, refused]}`` counts."""
    rng = np.random.default_rng(list(seed.encode()))
    counts = {how: [0, 0] for how in damages}
    for case in range(CASES):
        how = damages[case % len(damages)]
        _restore(path, template)
        damage(path, how, rng)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter('ignore')     # e.g. a frame skipped for its image
                read(path)
            counts[how][0] += 1
        except Exception as e:      # noqa: BLE001 - what is raised is the test's subject
            check_refusal(e, error, path if named is None else named, how, pattern)
            counts[how][1] += 1
    _restore(path, template)
    return counts


def _every_damage_refused_some(counts, always=('empty', 'folder', 'link to itself',
                                               'dangling link', 'random bytes')):
    for how, (read, refused) in counts.items():
        assert refused > 0, (how, counts)
        if how in always:
            assert read == 0, (how, counts)


# ------------------------------------------------------------------------- the readers

def test_read_json_messages(tmp_path):
    path = tmp_path / 'a.json'
    for text, detail in [
            ('{"a": 1', 'the JSON is cut short at line 1 column 8'),
            ('{"a', 'the JSON is cut short at line 1 column 2'),
            ("{'a': 1}", 'invalid JSON at line 1 column 2: Expecting property name enclosed in '
                         'double quotes'),
            ('  \n', 'no JSON in it, only white space'),
            ('[1, 2]', 'it holds an array where an object is expected'),
            ('[' * 100000, 'invalid JSON: nested too deeply'),
            ('{"a": ' + '1' * 5000 + '}', 'invalid JSON: a number too long to read')]:
        path.write_text(text)
        with pytest.raises(FileReadError) as e:
            read_json(path, what='test file', remedy='write it again')
        assert str(e.value) == f'{path}: cannot read test file ({detail}): write it again'
    path.write_bytes(b'{"a": "\xff"}')
    with pytest.raises(FileReadError, match=r'\(not UTF-8 text: byte 0xff at offset 7\)$'):
        read_json(path, remedy=None)
    path.write_bytes(b'')
    with pytest.raises(FileReadError, match=r'a\.json: cannot read JSON file \(the file is '
                                            r'empty, 0 bytes\): fix or replace the file$'):
        read_json(path)
    with pytest.raises(FileReadError, match=r'\(a folder, not a file\)'):
        read_json(tmp_path)
    with pytest.raises(FileReadError, match=r'nope\.json: cannot read JSON file \(not found\)'):
        read_json(tmp_path / 'nope.json')
    (tmp_path / 'loop.json').symlink_to('loop.json')
    with pytest.raises(FileReadError, match='Too many levels of symbolic links'):
        read_json(tmp_path / 'loop.json')
    path.write_text('true')
    with pytest.raises(FileReadError, match='it holds true or false where a number is'):
        read_json(path, expect=(int, float))
    path.write_bytes(b'\xef\xbb\xbf[1]')                   # a byte order mark is read
    assert read_json(path, expect=list) == [1]
    path.write_text('{"a": 1}')
    from mi_nerfpp.data import DatasetError
    with pytest.raises(DatasetError, match='an object where an array'):
        read_json(path, expect=list, error=DatasetError)


def test_read_json_property(tmp_path):
    template = tmp_path / 'template.json'
    template.write_text(json.dumps({'format': 'x', 'values': [1, 2.5, 's', None, True],
                                    'nested': {'a': [[1, 2], [3, 4]], 'b': 'é'}}, indent=1))
    start = time.perf_counter()
    path = tmp_path / 'file.json'
    counts = run_cases(template, path,
                       lambda p: read_json(p, what='test file', remedy='write it again'),
                       FileReadError, JSON_DAMAGE, 'read_json',
                       pattern=re.escape(f'{path}: cannot read test file (') + r'.+\): write '
                                                                               r'it again')
    _every_damage_refused_some({k: v for k, v in counts.items()
                                if k not in ('value swapped', 'edge number')})
    assert time.perf_counter() - start < 30


def test_read_npz_and_npy_property(tmp_path):
    npz, npy = tmp_path / 'template.npz', tmp_path / 'template.npy'
    np.savez(npz, a=np.arange(12.0).reshape(3, 4), b=np.array('text'), c=np.int64(7))
    np.save(npy, np.arange(34.0).reshape(2, 17))
    for template, read in ((npz, read_npz), (npy, read_npy)):
        path = tmp_path / f'file{template.suffix}'
        counts = run_cases(template, path, read, FileReadError, BINARY_DAMAGE, template.suffix,
                           pattern=re.escape(f'{path}: cannot read NumPy ') + r'.+\): fix or '
                                                                             r'replace the file')
        _every_damage_refused_some(counts)
    with pytest.raises(FileReadError, match=r'\(a NumPy array file, not an \.npz archive\)'):
        read_npz(npy)
    with pytest.raises(FileReadError, match=r'\(an \.npz archive of arrays, not one array\)'):
        read_npy(npz)
    np.save(npy, np.array([{'a': 1}], dtype=object), allow_pickle=True)
    with pytest.raises(FileReadError, match=r'Python objects \(pickled data\)'):
        read_npy(npy)


def test_read_exr_and_read_image_property(tmp_path, capsys):
    """EXR (flat and deep), PNG and JPEG: damaged as the other binary files, and a file of
    another type in the place of each (a PNG for an EXR, an EXR for a PNG); OpenEXR's own
    warnings of unreadable pixels are not printed."""
    from mi_nerfpp.files.exr import write_exr
    from mi_nerfpp.output.deep import write_deep_exr
    rng = np.random.default_rng(7)
    flat, deep = tmp_path / 'template.exr', tmp_path / 'template_deep.exr'
    write_exr(flat, {c: rng.random((6, 8)) for c in 'RGBA'})
    counts = rng.integers(0, 3, (4, 5))
    n = int(counts.sum())
    write_deep_exr(deep, counts, {c: np.sort(rng.random(n)).astype(np.float32)
                                  for c in ('R', 'G', 'B', 'A', 'Z', 'ZBack')})
    png, jpg = tmp_path / 'template.png', tmp_path / 'template.jpg'
    pixels = (rng.random((12, 16, 3)) * 255).astype(np.uint8)
    Image.fromarray(pixels).save(png)
    Image.fromarray(pixels).save(jpg, quality=90)
    header, channels = read_exr(flat, separate_channels=True)
    assert sorted(channels) == list('ABGR') and channels['R'].dtype == np.float32
    assert np.array_equal(read_image(png), pixels) and read_image(jpg).shape == (12, 16, 3)
    start = time.perf_counter()
    for template, read, kind in ((flat, read_exr, 'EXR image'), (deep, read_exr, 'EXR image'),
                                 (png, read_image, 'image'), (jpg, read_image, 'image')):
        path = tmp_path / f'file{template.suffix}'
        found = run_cases(template, path, read, FileReadError, BINARY_DAMAGE,
                          template.name, pattern=re.escape(f'{path}: cannot read {kind} (') +
                          r'.+\): fix or replace the file')
        _every_damage_refused_some(found)
    assert time.perf_counter() - start < 20
    assert capsys.readouterr().out == ''
    for read, other in ((read_exr, png), (read_image, flat), (read_image, npz_file(tmp_path))):
        with pytest.raises(FileReadError, match=r'\(not an OpenEXR file|\(neither a PNG nor'):
            read(other)


def _photo_size(path):
    from mi_nerfpp.files.readers import open_photo
    with open_photo(path) as img:
        return img.size


def test_open_photo_property(tmp_path):
    """Photos for structure from motion (JPEG, PNG, TIFF: Pillow, for their EXIF, turning them
    upright, crops) are damaged as the other binary files: each opens whole (its pixels
    decoded) or ends with the reader's one line."""
    rng = np.random.default_rng(8)
    pixels = (rng.random((12, 16, 3)) * 255).astype(np.uint8)
    for suffix in ('.jpg', '.png', '.tif'):
        template = tmp_path / f'template{suffix}'
        Image.fromarray(pixels).save(template)
        assert _photo_size(template) == (16, 12)
        path = tmp_path / f'photo{suffix}'
        found = run_cases(template, path, _photo_size, FileReadError, BINARY_DAMAGE,
                          template.name, pattern=re.escape(f'{path}: cannot read photo (') +
                          r'.+\): fix or replace the file')
        _every_damage_refused_some(found)


def npz_file(folder: Path) -> Path:
    path = folder / 'other.npz'
    np.savez(path, a=np.zeros(3))
    return path


# ------------------------------------------------------------------- the files it reads

def test_camera_path_files_property(tmp_path):
    from mi_nerfpp.output.camera_path import CameraPath, CameraPathError, Pose, read_path, \
        write_path
    keys = []
    for angle in (0.0, 0.4, 0.8):
        c2w = np.eye(4)
        c2w[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0],
                       [-np.sin(angle), 0, np.cos(angle)]]
        c2w[:3, 3] = [np.sin(angle), 0.1, np.cos(angle)]
        keys.append(Pose(c2w, 40.0 + 5 * angle))
    path = CameraPath(keys, resolution=(32, 18), fps=4, seconds=1.0).resample()
    template = tmp_path / 'template.json'
    write_path(template, path)
    assert len(read_path(template).frames) == 4
    counts = run_cases(template, tmp_path / 'path.json', read_path, CameraPathError,
                       JSON_DAMAGE, 'camera path')
    _every_damage_refused_some(counts)


def _blender(root: Path):
    root.mkdir()
    frames = []
    for i in range(3):
        Image.fromarray(np.full((6, 8, 3), 60 + 30 * i, np.uint8)).save(root / f'{i}.png')
        pose = np.eye(4)
        pose[:3, 3] = [i - 1.0, 0.2 * i, 3.0]
        frames.append({'file_path': f'{i}.png', 'transform_matrix': pose.tolist()})
    (root / 'transforms.json').write_text(json.dumps({'camera_angle_x': 0.8, 'frames': frames},
                                                     indent=1))


def test_transforms_json_property(tmp_path):
    from mi_nerfpp.data import DatasetError, load_dataset
    data = tmp_path / 'data'
    _blender(data)
    template = tmp_path / 'template.json'
    shutil.copyfile(data / 'transforms.json', template)
    assert len(load_dataset(str(data), downscale=1).train) > 0
    counts = run_cases(template, data / 'transforms.json',
                       lambda p: load_dataset(str(data), downscale=1), DatasetError,
                       JSON_DAMAGE, 'transforms', named=data)
    _every_damage_refused_some(counts)


def test_checkpoints_property(tmp_path):
    from mi_nerfpp.files.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
    from tests.helpers import tiny_model
    template = tmp_path / 'template.npz'
    save_checkpoint(template, tiny_model())
    counts = run_cases(template, tmp_path / 'model.npz', load_checkpoint, CheckpointError,
                       BINARY_DAMAGE, 'checkpoint')
    _every_damage_refused_some(counts)
