"""Paths are bytes (issue 49, item 4): a Linux file name may be any bytes but ``/`` and NUL
(cameras and unzipped archives write names that are not UTF-8), and every command takes such a
path, writes its outputs at exactly those bytes and prints the path back as its bytes. Random
names from a seeded generator, each with a space and bytes that are not UTF-8."""
import json
import os
import random
import shutil
import subprocess
import sys

import numpy as np
import OpenEXR
import pytest
from PIL import Image

from mi_nerfpp.data import load_dataset
from mi_nerfpp.data.synth import scene_file
from mi_nerfpp.files.atomic import (LOCK_NAME, atomic_write_path, is_utf8, lock_folder,
                                    readable_path, remove_stale_temporaries, write_json)
from mi_nerfpp.files.exr import read_exr, read_header, write_exr
from tests.helpers import make_capture
from tests.robustness.common import TINY

SEED = 49
NAME_BYTES = [b for b in range(1, 256) if b != ord('/')]


def byte_name(rng, suffix=b''):
    """A random file name Linux takes and UTF-8 does not (as Python gives it: ``os.fsdecode``):
    up to 12 random bytes (any but ``/`` and NUL), a space and a byte that starts a UTF-8
    character followed by none (so never valid, whatever precedes it), in random order."""
    while True:
        parts = [bytes(rng.choice(NAME_BYTES) for _ in range(rng.randint(0, 12))), b' ',
                 bytes([rng.randint(0xc2, 0xf4)]) + b' ']
        rng.shuffle(parts)
        name = b''.join(parts) + suffix
        if not is_utf8(name):
            return os.fsdecode(name)


def run_command(*argv):
    """``python -m mi_nerfpp ARGV`` in a child whose standard streams encode UTF-8 strictly (as
    a UTF-8 locale other than C.UTF-8 sets them): (status, stdout and stderr as bytes)."""
    env = dict(os.environ, PYTHONIOENCODING='utf-8')
    r = subprocess.run([sys.executable, '-m', 'mi_nerfpp', *map(str, argv)],
                       capture_output=True, env=env, timeout=600)
    return r.returncode, r.stdout + r.stderr


@pytest.fixture(scope='module')
def places(tmp_path_factory):
    """A folder of the tests, and a capture in a folder of a random byte name in it."""
    root = str(tmp_path_factory.mktemp('paths'))
    capture = make_capture(os.path.join(root, byte_name(random.Random(SEED))), views=12,
                           width=16, height=12, spp=2)
    return root, capture


@pytest.fixture(scope='module')
def trained(places):
    """A run folder of a random byte name, trained on the capture."""
    root, capture = places
    out = os.path.join(root, byte_name(random.Random(SEED + 1)))
    status, output = run_command('optimize', capture, '--out', out, *TINY)
    assert status == 0, output.decode(errors='replace')
    return out


@pytest.fixture(scope='module')
def photos(places):
    """A folder of a random byte name of photos named with random bytes (no poses): a small
    textured capture that COLMAP registers."""
    from mi_nerfpp.data.synth import synthesize
    root, _ = places
    capture = os.path.join(root, 'plaza')
    synthesize(scene_file('gt_plaza.xml'), capture, views=20, res=(240, 180), spp=32,
               trajectory='arc', progress=False)
    rng = random.Random(SEED + 2)
    folder = os.path.join(root, byte_name(rng))
    os.makedirs(folder)
    for split in ('train', 'validation', 'test'):
        rgb = os.path.join(capture, split, 'rgb')
        for name in sorted(os.listdir(rgb)) if os.path.isdir(rgb) else []:
            shutil.copy(os.path.join(rgb, name), os.path.join(folder, byte_name(rng, b'.png')))
    return folder


def _video_name():
    import importlib.util
    return b'.mp4' if importlib.util.find_spec('imageio_ffmpeg') else b'.gif'


def _case(command, rng, root, capture, trained, photos):
    """(argv, files it must write, path it must print) of ``command`` on random byte paths."""
    here = os.path.join(root, byte_name(rng))          # a fresh folder of a random name
    os.makedirs(here)
    if command == 'colmap':
        out = os.path.join(here, byte_name(rng))
        return (['colmap', photos(), '--out', out],
                [os.path.join(out, 'sfm.json'), os.path.join(out, 'train', 'rgb')], out)
    if command == 'optimize --out':
        out = os.path.join(here, byte_name(rng))
        return (['optimize', capture, '--out', out, *TINY],
                [os.path.join(out, f) for f in ('model.npz', 'metrics.json', 'render.xml',
                                                'training.png', LOCK_NAME)], out)
    if command == 'read a capture':
        data = os.path.join(here, byte_name(rng))
        shutil.copytree(capture, data)
        out = os.path.join(here, 'run')
        return ['optimize', data, '--out', out, *TINY], [os.path.join(out, 'model.npz')], data
    if command == 'evaluate':
        run = os.path.join(here, byte_name(rng))
        shutil.copytree(trained, run)
        os.remove(os.path.join(run, 'metrics.json'))
        return ['evaluate', run], [os.path.join(run, 'metrics.json')], run
    if command == 'sweep':
        out = os.path.join(here, byte_name(rng))
        run = os.path.join(out, os.path.basename(capture))
        return (['sweep', capture, '--out', out, *TINY],
                [os.path.join(out, 'sweep.json'), os.path.join(run, 'model.npz'),
                 os.path.join(run, 'optimize.log')], out)
    if command == 'export':
        out = os.path.join(here, byte_name(rng))
        return (['export', trained, '--out', out, '--resolution', '8'],
                [os.path.join(out, f) for f in ('scene.usda', 'cameras.json', 'train.chan')],
                os.path.join(out, 'scene.usda'))
    if command == 'synth --out':
        out = os.path.join(here, byte_name(rng))
        return (['synth', scene_file('gt_bounded.xml'), '--out', out, '--views', '3', '--res',
                 '8x6', '--spp', '1'],
                [os.path.join(out, 'capture.json'), os.path.join(out, 'train', 'rgb')], out)
    if command == 'render -o --preview':
        scene = os.path.join(here, byte_name(rng, b'.xml'))
        shutil.copy(scene_file('render_random.xml'), scene)
        exr = os.path.join(here, byte_name(rng, b'.exr'))
        png = os.path.join(here, byte_name(rng, b'.png'))
        return (['render', scene, '-o', exr, '--preview', png, '-D', 'res_x=8', '-D', 'res_y=6'],
                [exr, png], exr)
    if command == 'video':
        video = os.path.join(here, byte_name(rng, _video_name()))
        return (['video', trained, '-o', video, '--frames', '2', '--res', '8x6', '--exr'],
                [video], video)
    raise AssertionError(command)


COMMANDS = ['optimize --out', 'read a capture', 'evaluate', 'sweep', 'export', 'synth --out',
            'render -o --preview', 'video', 'colmap']


@pytest.mark.parametrize('command', COMMANDS)
def test_every_command_takes_a_path_of_any_bytes(command, places, trained, request):
    """The commands failed with "'utf-8' codec can't encode ..." (the lock file, logs, the
    console) or OpenEXR's "use write(path: str) ..." (OpenEXR, Mitsuba and USD take UTF-8 names
    only; colmap: "import_images(): incompatible function arguments", COLMAP's too). Now each
    ends with status 0, its files at the exact bytes of the names given, the path printed as
    its bytes, and no temporary file left."""
    root, capture = places
    rng = random.Random(f'{SEED} {command}')
    argv, outputs, printed = _case(command, rng, root, capture, trained,
                                   lambda: request.getfixturevalue('photos'))
    status, output = run_command(*argv)
    assert status == 0, output.decode(errors='replace')
    for path in outputs:
        assert os.path.exists(os.fsencode(path)), (command, os.fsencode(path))
    assert os.fsencode(printed) in output, (os.fsencode(printed), output)
    assert b'\\udc' not in output and b'Traceback' not in output
    for folder, _, files in os.walk(os.fsencode(root)):
        assert not [f for f in files if b'.tmp' in f], (folder, files)


def test_view_serves_a_run_of_any_bytes(trained):
    """``view`` (the command that writes nothing) on a run folder of a random byte name: the
    page is served, the path printed as its bytes, and Ctrl-C ends it with 130."""
    import signal
    import socket
    import threading
    import time
    import urllib.request
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, '-m', 'mi_nerfpp', 'view', trained, '--port',
                             str(port)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            env=dict(os.environ, PYTHONIOENCODING='utf-8'))
    lines = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        start = time.monotonic()       # the address is printed once the page is ready
        while not any(b'http://' in line for line in lines) and proc.poll() is None \
                and time.monotonic() - start < 300:
            time.sleep(0.2)
        status = urllib.request.urlopen(f'http://127.0.0.1:{port}/', timeout=30).status
        proc.send_signal(signal.SIGINT)
        proc.wait(120)
        reader.join(30)
    finally:
        proc.kill()
    output = b''.join(lines)
    assert status == 200, output
    assert proc.returncode == 130 and os.fsencode(trained) in output, output
    assert b'Traceback' not in output and b'\\udc' not in output


# ------------------------------------------------------------------------- in-process

def test_files_written_and_read_at_random_byte_paths(tmp_path):
    """What the commands write through OpenEXR and JSON, and the run-folder lock, at 20 random
    byte paths: written at those bytes, read back, no temporary left."""
    rng = random.Random(SEED)
    channels = {c: np.full((3, 4), 0.25, np.float32) for c in 'RGB'}
    for _ in range(20):
        folder = os.path.join(str(tmp_path), byte_name(rng))
        exr = os.path.join(folder, byte_name(rng, b'.exr'))
        write_exr(exr, channels)
        assert read_exr(exr)['G'][0, 0] == 0.25 and 'channels' in read_header(exr)
        with readable_path(exr) as readable:
            assert is_utf8(readable) and open(readable, 'rb').read() == open(exr, 'rb').read()
        doc = os.path.join(folder, byte_name(rng, b'.json'))
        write_json(doc, {'path': exr})
        with open(doc) as f:
            assert json.load(f)['path'] == exr                 # stored escaped, read back
        with lock_folder(folder):
            with open(os.path.join(folder, LOCK_NAME), 'rb') as f:
                assert f.read().startswith(b'pid ')
        assert not [f for f in os.listdir(folder) if '.tmp' in f]
        assert sorted(os.listdir(folder)) == sorted([os.path.basename(exr),
                                                    os.path.basename(doc), LOCK_NAME])


def test_a_temporary_of_a_byte_name_is_utf8_and_found_when_stale(tmp_path):
    """The temporary name of a file of any bytes is ASCII in a UTF-8 path; one left by a
    killed process is removed."""
    rng = random.Random(SEED + 2)
    folder = os.path.join(str(tmp_path), byte_name(rng))
    name = byte_name(rng, b'.npz')
    with pytest.raises(KeyboardInterrupt):
        with atomic_write_path(os.path.join(folder, name)) as tmp:
            assert is_utf8(tmp) and os.path.basename(tmp).isascii()
            open(tmp, 'wb').close()
            raise KeyboardInterrupt
    assert os.listdir(folder) == []                   # removed on the way out
    with atomic_write_path(os.path.join(folder, name)) as tmp:
        open(tmp, 'wb').close()
        kept = os.path.join(folder, os.path.basename(tmp) + '.kept')
        os.link(tmp, kept)                            # as if the process were killed here
    os.rename(kept, os.path.join(folder, os.path.basename(tmp)))
    assert remove_stale_temporaries(folder, name) == [os.path.join(folder,
                                                                   os.path.basename(tmp))]
    assert os.listdir(folder) == [name]


def _image(path, kind, value):
    if kind == 'exr':
        channels = {c: np.full((6, 8), value / 255, np.float32) for c in 'RGB'}
        with atomic_write_path(path) as tmp, OpenEXR.File(
                {'type': OpenEXR.scanlineimage}, channels) as f:
            f.write(tmp)
    elif kind == 'png16':
        with atomic_write_path(path) as tmp:
            Image.fromarray(np.full((6, 8), value * 257, np.uint16)).save(tmp, format='PNG')
    else:
        Image.fromarray(np.full((6, 8, 3), value, np.uint8)).save(
            path, format='JPEG' if kind == 'jpg' else 'PNG')


@pytest.mark.parametrize('kind', ['png8', 'png16', 'jpg', 'exr'])
@pytest.mark.parametrize('distorted', [False, True])
def test_a_capture_of_byte_named_images_reads(tmp_path, kind, distorted):
    """A transforms.json capture in a folder of a random byte name, its images named with
    random bytes too (8- and 16-bit PNG, JPEG, EXR: Pillow, Mitsuba, OpenEXR), read as it is
    and undistorted into its cache."""
    rng = random.Random(f'{SEED} {kind} {distorted}')
    root = os.path.join(str(tmp_path), byte_name(rng))
    os.makedirs(root)
    ext = {'png8': b'.png', 'png16': b'.png', 'jpg': b'.jpg', 'exr': b'.exr'}[kind]
    frames = []
    for i in range(3):
        name = byte_name(rng, ext)
        _image(os.path.join(root, name), kind, 100 + 20 * i)
        pose = np.eye(4)
        pose[:3, 3] = [i, 0, 3]
        frames.append({'file_path': name, 'transform_matrix': pose.tolist()})
    meta = dict({'camera_angle_x': 0.8, 'frames': frames}, **({'k1': 0.01} if distorted else {}))
    with open(os.path.join(root, 'transforms.json'), 'w') as f:
        json.dump(meta, f)                       # the names as JSON escapes, as Python writes
    dataset = load_dataset(root)
    splits = (dataset.train, dataset.validation, dataset.test)
    read = [path for split in splits for path in split.image_paths]
    assert len(read) == 3 and all(os.path.isfile(os.fsencode(path)) for path in read)
    if not distorted:
        assert sorted(read) == sorted(os.path.join(root, f['file_path']) for f in frames)
    else:                       # undistorted copies in the cache, named after the images
        def stem(path):
            return os.path.splitext(os.path.basename(path))[0]
        assert sorted(map(stem, read)) == sorted(stem(f['file_path']) for f in frames)


# ------------------------------------------------------------------- names in text formats

def test_as_text_and_name_bytes():
    from mi_nerfpp.files.atomic import as_text, name_bytes
    name = os.fsdecode(b'caf\xc3\xa9 \xff\x80.png')     # UTF-8 é, then two bytes that are not
    assert as_text(name) == 'café \\xff\\x80.png' and as_text(name).encode('utf-8')
    assert bytes.fromhex(name_bytes(name)) == os.fsencode(name)
    assert as_text('plain.png') == 'plain.png' and name_bytes('plain.png') is None
    assert as_text(None) is None and name_bytes(None) is None


def test_image_names_that_are_not_utf8_reach_usd_and_json_as_text(tmp_path):
    """Export ended with "'utf-8' codec can't encode character '\\udcc2' ... surrogates not
    allowed" (USD takes UTF-8 text only) for photos whose names are not UTF-8, and
    metrics.json held them as lone surrogates (``\\udcc2``), which strict JSON readers refuse.
    Now USD has each name as text (``\\xNN`` per such byte) with its exact bytes in
    customData, cameras.json likewise (``name_bytes``), metrics.json as text, and the export
    says so."""
    rng = random.Random(f'{SEED} text names')
    capture = make_capture(str(tmp_path / 'capture'), views=12, width=16, height=12, spp=2)
    stems = {}
    for split in ('train', 'validation', 'test'):
        for f in sorted(os.listdir(os.path.join(capture, split, 'rgb'))):
            stem, ext = os.path.splitext(f)
            new = byte_name(rng)
            stems[new] = split
            for folder, suffix in (('rgb', ext), ('pose', '.txt'), ('intrinsics', '.txt')):
                os.rename(os.path.join(capture, split, folder, stem + suffix),
                          os.path.join(capture, split, folder, new + suffix))
    run = str(tmp_path / 'run')
    status, output = run_command('optimize', capture, '--out', run, *TINY)
    assert status == 0, output.decode(errors='replace')
    metrics = (tmp_path / 'run' / 'metrics.json').read_text(encoding='ascii')
    assert '\\udc' not in metrics
    names = {view['image'] for view in json.loads(metrics)['test']['views']}
    from mi_nerfpp.files.atomic import as_text
    assert names == {as_text(s) + '.png' for s, split in stems.items() if split == 'test'}

    out = str(tmp_path / 'export')
    status, output = run_command('export', run, '--out', out, '--resolution', '8')
    assert status == 0, output.decode(errors='replace')
    assert f'note: export: {len(stems)} image names are not UTF-8'.encode() in output
    table = json.loads((tmp_path / 'export' / 'cameras.json').read_text(encoding='ascii'))
    named = [c for c in table['cameras'] if c['split'] != 'video_orbit']
    assert sorted(bytes.fromhex(c['name_bytes']) for c in named) == sorted(
        os.fsencode(s) for s in stems)
    assert all(c['name'] == as_text(os.fsdecode(bytes.fromhex(c['name_bytes'])))
               for c in named)
    from pxr import Usd
    stage = Usd.Stage.Open(os.path.join(out, 'scene.usda'))
    cameras = [p for p in stage.Traverse() if p.GetCustomDataByKey('imageStem') is not None]
    assert len(cameras) == len(stems)
    for prim in cameras:
        exact = bytes.fromhex(prim.GetCustomDataByKey('imageStemBytes'))
        assert os.fsdecode(exact) in stems
        assert prim.GetDisplayName() == prim.GetCustomDataByKey('imageStem') == as_text(
            os.fsdecode(exact))
