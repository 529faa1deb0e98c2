"""Export to DCC tools (issue 35): USD cameras named after the images, in the capture's world
frame, checked with usd-core's own camera math; Nuke .chan; a proxy mesh of the foreground;
and a headless Blender building its camera from the USD and projecting like the EXR header."""
import contextlib
import glob
import json
import os
import signal
import subprocess
import sys

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.jobs import export
from mi_nerfpp.data import Camera, mitsuba_sensor_dict
from mi_nerfpp.core.frame import Normalization
from mi_nerfpp.core.geometry import rotation_zxy
from mi_nerfpp.core.model import NeRFPPModel
from tests.helpers import AnalyticField, blender_python, debian_blender

from pxr import Gf, Usd, UsdGeom  # noqa: E402  (usd-core: a test dependency, setup.sh)


@pytest.fixture(scope='module')
def exported(tiny_run, tmp_path_factory):
    from mi_nerfpp.commands.cli import main
    out = str(tmp_path_factory.mktemp('export') / 'dcc')
    # A 5-step model has no clear surface: mesh it where its density is in the top 2 %.
    from mi_nerfpp.jobs.run import open_run
    model = open_run(tiny_run)[0]
    x = np.random.default_rng(0).uniform(-0.7, 0.7, (20000, 3)).astype(np.float32)
    density = np.array(model.radiance_fields()[0].density([mi.Float(x[:, i]) for i in range(3)]))
    level = float(np.quantile(density, 0.98))
    assert main(['export', tiny_run, '--out', out, '--resolution', '48',
                 '--density', str(level), '--texture-size', '64']) == 0
    return tiny_run, out


def _opencv_projection(camera, point):
    x = np.linalg.inv(camera.c2w) @ np.append(point, 1.0)
    return (camera.K @ x[:3])[:2] / x[2]


def _dataset_cameras(run):
    """The capture's cameras as its files give them (world frame), by (split, image stem):
    the NeRF++ layout numbers each split's images from 000000."""
    from mi_nerfpp.jobs.run import open_run
    meta = open_run(run)[1]
    root = meta['dataset']
    out = {}
    for split in ('train', 'validation', 'test'):
        for pose in sorted(glob.glob(os.path.join(root, split, 'pose', '*.txt'))):
            stem = os.path.splitext(os.path.basename(pose))[0]
            K = np.loadtxt(os.path.join(root, split, 'intrinsics', stem + '.txt'))[:3, :3]
            out[split, stem] = Camera(K, np.loadtxt(pose), 32, 24, stem)
    return out


def test_usd_cameras_are_the_dataset_cameras(exported):
    """One camera per image, named after its stem, within 1e-4 of the dataset pose, and
    usd-core's own projection (Gf.Camera frustum) puts known points on the OpenCV pixels."""
    run, out = exported
    stage = Usd.Stage.Open(os.path.join(out, 'scene.usda'))
    dataset = _dataset_cameras(run)
    found = {}
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Camera) and prim.GetName() != 'video_orbit':
            split = prim.GetParent().GetName()
            stem = prim.GetCustomDataByKey('imageStem')
            found[split, stem] = prim
            assert prim.GetDisplayName() == stem
            # A valid identifier, unique over the splits (Blender flattens the hierarchy).
            assert prim.GetName() == f'{split}_{stem}'
    assert len({p.GetName() for p in found.values()}) == len(found)
    assert set(found) == set(dataset) and len(found) == 24
    rng = np.random.default_rng(1)
    for (split, stem), prim in found.items():
        camera = dataset[split, stem]
        gf = UsdGeom.Camera(prim).GetCamera(Usd.TimeCode.Default())
        c2w_gl = np.array(gf.transform, dtype=np.float64).T
        c2w = c2w_gl @ np.diag([1.0, -1.0, -1.0, 1.0])
        np.testing.assert_allclose(c2w, camera.c2w, atol=1e-4)
        fov = 2 * np.degrees(np.arctan(gf.horizontalAperture / 2 / gf.focalLength))
        assert fov == pytest.approx(camera.fov_x, abs=1e-4)
        projection = np.array(gf.frustum.ComputeProjectionMatrix(), dtype=np.float64).T
        view = np.linalg.inv(c2w_gl)
        for _ in range(5):
            u, v, z = rng.uniform(0, 32), rng.uniform(0, 24), rng.uniform(1, 20)
            local = np.linalg.inv(camera.K) @ np.array([u, v, 1.0]) * z
            point = camera.c2w[:3, :3] @ local + camera.c2w[:3, 3]
            clip = projection @ view @ np.append(point, 1.0)
            ndc = clip[:2] / clip[3]
            pixel = [(ndc[0] + 1) / 2 * camera.width, (1 - ndc[1]) / 2 * camera.height]
            np.testing.assert_allclose(pixel, [u, v], atol=1e-2)
    # The video's orbit: one time sample per frame.
    video = UsdGeom.Camera(stage.GetPrimAtPath('/World/cameras/video_orbit'))
    assert len(video.GetPrim().GetAttribute('xformOp:transform').GetTimeSamples()) == 60
    # The proxy is referenced and has geometry.
    proxy = stage.GetPrimAtPath('/World/proxy')
    assert proxy.IsA(UsdGeom.Mesh) and len(UsdGeom.Mesh(proxy).GetPointsAttr().Get()) > 10


def test_chan_files_and_camera_table(exported):
    run, out = exported
    dataset = _dataset_cameras(run)
    table = json.load(open(os.path.join(out, 'cameras.json')))['cameras']
    rows = {s: np.loadtxt(os.path.join(out, f'{s}.chan'), ndmin=2)
            for s in ('train', 'validation', 'test', 'video_orbit')}
    assert len(rows['video_orbit']) == 60
    for entry in table:
        if entry['split'] == 'video_orbit':
            continue
        camera = dataset[entry['split'], entry['name']]
        frame, tx, ty, tz, rx, ry, rz, vfov = rows[entry['split']][entry['frame'] - 1]
        assert frame == entry['frame']
        np.testing.assert_allclose([tx, ty, tz], camera.center, atol=1e-5)
        # Nuke's ZXY rotation of a camera looking down -z gives back the pose.
        R = rotation_zxy(rx, ry, rz) @ np.diag([1.0, -1.0, -1.0])
        np.testing.assert_allclose(R, camera.c2w[:3, :3], atol=1e-6)
        assert vfov == pytest.approx(np.degrees(2 * np.arctan(12 / camera.K[1, 1])), abs=1e-5)


def test_proxy_mesh_of_a_reconstructed_sphere_is_in_world_coordinates(tmp_path):
    """An opaque sphere of radius 0.5 (model frame) of constant colour: the mesh's vertices lie
    on it, moved back to the world by the normalization, with that colour."""
    def ball(x):
        return dr.select(dr.norm(mi.Vector3f(x[0], x[1], x[2])) < 0.5, 50.0, 0.0)
    norm = Normalization(center=(1.0, -2.0, 3.0), scale=0.25)
    model = NeRFPPModel(AnalyticField(ball, (0.5, 0.25, 0.125)), None, normalization=norm,
                        color_space='linear')
    vertices, faces, colors = export.proxy_mesh(model, resolution=64)
    radius = np.linalg.norm((vertices - norm.center_array) * norm.scale, axis=1)
    np.testing.assert_allclose(radius, 0.5, atol=2.0 / 63)
    np.testing.assert_allclose(colors, np.broadcast_to([0.5, 0.25, 0.125], colors.shape),
                               atol=1e-6)
    export.write_ply(tmp_path / 'p.ply', vertices, faces, colors)
    header = open(tmp_path / 'p.ply').read().split('end_header')[0]
    assert f'element vertex {len(vertices)}' in header and f'element face {len(faces)}' in header
    with pytest.raises(ValueError, match='never reaches'):
        export.proxy_mesh(model, resolution=16, level=1e6)


BLENDER_SCRIPT = r'''
import json, sys
sys.path.append(sys.argv[sys.argv.index('--') + 1])      # usd-core, after Blender's own paths
import bpy
from mathutils import Matrix, Vector
from bpy_extras.object_utils import world_to_camera_view
from pxr import Usd, UsdGeom
args = json.loads(sys.argv[sys.argv.index('--') + 2])
stage = Usd.Stage.Open(args['usd'])
gf = UsdGeom.Camera(stage.GetPrimAtPath(args['prim'])).GetCamera(Usd.TimeCode.Default())
scene = bpy.context.scene
scene.render.resolution_x, scene.render.resolution_y = args['width'], args['height']
scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
data = bpy.data.cameras.new('usd')
data.sensor_fit = 'HORIZONTAL'
data.sensor_width = gf.horizontalAperture
data.lens = gf.focalLength
# Blender's shift is in units of the larger film side (the width here).
data.shift_x = gf.horizontalApertureOffset / gf.horizontalAperture
data.shift_y = gf.verticalApertureOffset / gf.horizontalAperture
cam = bpy.data.objects.new('usd', data)
scene.collection.objects.link(cam)
m = gf.transform                                         # row vectors
cam.matrix_world = Matrix([[m[j][i] for j in range(4)] for i in range(4)])
bpy.context.view_layer.update()
out = []
for p in args['points']:
    uv = world_to_camera_view(scene, cam, Vector(p))
    out.append([uv.x * args['width'], (1 - uv.y) * args['height']])
print('PIXELS ' + json.dumps(out))
'''


def test_blender_builds_the_usd_camera_and_projects_like_the_exr_header(exported, tmp_path):
    """Headless Blender (Debian's, built without USD import: the camera is built from the USD
    file through usd-core, as a user's script would) projects points onto the pixels that
    the EXR header's worldToNDC gives for the same camera."""
    blender = debian_blender()
    from mi_nerfpp.output.views import camera_attributes
    run, out = exported
    (split, stem), camera = sorted(_dataset_cameras(run).items())[0]
    stage = Usd.Stage.Open(os.path.join(out, 'scene.usda'))
    prim = next(p for p in stage.Traverse() if p.GetCustomDataByKey('imageStem') == stem
                and p.GetParent().GetName() == split)
    rng = np.random.default_rng(2)
    points = []
    for u, v, z in zip(rng.uniform(0, 32, 6), rng.uniform(0, 24, 6), rng.uniform(1, 10, 6)):
        local = np.linalg.inv(camera.K) @ np.array([u, v, 1.0]) * z
        points.append((camera.c2w[:3, :3] @ local + camera.c2w[:3, 3]).tolist())
    script = tmp_path / 'camera.py'
    script.write_text(BLENDER_SCRIPT)
    site = os.path.dirname(os.path.dirname(pxr_module_file()))
    r = subprocess.run([blender, '-b', '--factory-startup', '--python-exit-code', '1',
                        '--python', str(script), '--', site, json.dumps(
                            {'usd': os.path.join(out, 'scene.usda'),
                             'prim': prim.GetPath().pathString, 'width': camera.width,
                             'height': camera.height, 'points': points})],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    line = next(l for l in r.stdout.splitlines() if l.startswith('PIXELS '))
    blender_pixels = np.array(json.loads(line[len('PIXELS '):]))
    attributes = camera_attributes(mi.load_dict(mitsuba_sensor_dict(camera)))
    for point, got in zip(points, blender_pixels):
        ndc = np.append(point, 1.0) @ attributes['worldToNDC'].astype(np.float64)
        header = ndc[:2] / ndc[3] * [camera.width, camera.height]
        np.testing.assert_allclose(got, header, atol=1e-2)


def pxr_module_file():
    import pxr as module
    return module.__file__


# ----------------------------------------------------------------------------- all or nothing

def _files(folder):
    """``{relative path: bytes}`` of every file under ``folder``."""
    out = {}
    for root, _, names in os.walk(folder):
        for name in names:
            path = os.path.join(root, name)
            out[os.path.relpath(path, folder)] = open(path, 'rb').read()
    return out


def _export(run, out, resolution=16, **kw):
    return export.export_run(run, str(out), resolution=resolution, density=1e-6,
                             texture_size=32, **kw)


@contextlib.contextmanager
def _sigterm_raises():
    """SIGTERM raises SystemExit for the time of the ``with``, rather than end the test process
    (its default action, which the swap holds back the same way), and SIGINT raises
    KeyboardInterrupt as in a terminal: a process started in the background by a shell
    without job control (``cmd &`` in a script, as a CI runner may start the tests) inherits
    SIGINT ignored, and then nothing is sent to hold back."""
    def handler(signum, frame):
        raise SystemExit(143)
    before = signal.signal(signal.SIGTERM, handler)
    before_int = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, before)
        signal.signal(signal.SIGINT, before_int)


def test_an_export_cut_short_at_any_write_leaves_the_earlier_export_whole(tiny_run, tmp_path,
                                                                         monkeypatch):
    """A signal or a full disk during an export over an earlier one left a new proxy beside the
    old USD files and a stub .tmp.usda (issue 49, item 3). Cut at every write of the export
    (each file) and at every move of the swap: the folder holds the earlier export or the new
    one, never a mix, a user's own file stays, and the next export completes. A signal during
    the swap waits for its end (issue 63, item 5)."""
    out = tmp_path / 'dcc'
    out.mkdir()
    (out / 'notes.txt').write_text('mine')
    _export(tiny_run, out)
    before = _files(out)
    assert '.export.json' in before and 'scene.usda' in before and 'proxy.ply' in before
    writers = ['write_ply', 'write_texture', 'write_obj', 'write_proxy_usd', 'write_usd',
               'write_chan', 'atomic_write_path']
    cut = 0
    for name in writers:
        real = getattr(export, name)
        for k in range(1, 6):
            calls = []

            def failing(*args, _real=real, _k=k, **kwargs):
                calls.append(1)
                if len(calls) == _k:
                    raise KeyboardInterrupt          # what SIGINT raises; SIGTERM ends the same
                return _real(*args, **kwargs)
            monkeypatch.setattr(export, name, failing)
            try:
                _export(tiny_run, out, opened=None)
            except KeyboardInterrupt:
                cut += 1
                assert _files(out) == before, (name, k)
            monkeypatch.setattr(export, name, real)
    assert cut >= 8
    # Cut during the swap itself, at each move (a finer proxy than the one before, so that a
    # mix would show): Ctrl-C raised there, or SIGINT / SIGTERM sent there, waits for the last
    # move and leaves the new export (issue 63, item 5); a kill that cannot be caught (here an
    # exception no handler expects) leaves the move begun, and the next swap finishes it.
    _export(tiny_run, tmp_path / 'reference', resolution=20)
    new = _files(tmp_path / 'reference')
    assert new['proxy.ply'] != before['proxy.ply']
    real_replace = os.replace

    class Killed(BaseException):
        pass
    for how in ('KeyboardInterrupt', 'SIGINT', 'SIGTERM', 'killed'):
        for k in range(1, 16):
            moves = []

            def replace(a, b, _k=k, _how=how):
                swap = ('.export.partial' in str(a)) != ('.export.partial' in str(b)) \
                    or '.export.old' in str(b)              # a move of the swap, not a write
                if swap:
                    moves.append(1)
                    if len(moves) == _k:
                        if _how == 'KeyboardInterrupt':
                            raise KeyboardInterrupt
                        if _how == 'killed':
                            raise Killed
                        os.kill(os.getpid(), getattr(signal, _how))
                return real_replace(a, b)
            monkeypatch.setattr(export.os, 'replace', replace)
            cut = False
            try:
                with _sigterm_raises():
                    _export(tiny_run, out, resolution=20)
            except (KeyboardInterrupt, SystemExit, Killed):
                cut = True
            monkeypatch.setattr(export.os, 'replace', real_replace)
            assert cut == (len(moves) >= k), (how, k)
            if how == 'killed':
                export.finish_swap(str(out))
            after = _files(out)
            assert after['notes.txt'] == b'mine'
            del after['notes.txt']
            assert after == new, (how, k)
            assert not any(name.startswith('.export.partial') or name.startswith('.export.old')
                           or '.tmp' in name for name in after)
            if not cut:
                break
            _export(tiny_run, out)                  # back to the earlier export for the next cut
    assert len(moves) < 15                          # every move of the swap was cut once


def test_a_model_without_a_surface_exports_its_cameras_and_says_which_density_meshes(
        tiny_run, tmp_path):
    """A run whose density never reaches the mesh level exported no cameras at all (issue 49,
    item 3): the cameras are written, the mesh is skipped with a warning naming a --density."""
    warnings = []
    written = export.export_run(tiny_run, str(tmp_path / 'dcc'), resolution=16, density=1e30,
                                warn=warnings.append, texture_size=32)
    names = {os.path.basename(p) for p in written}
    assert {'scene.usda', 'train.chan', 'cameras.json'} <= names
    assert not names & {'proxy.ply', 'proxy.usda', 'proxy.obj', 'proxy.mtl',
                        'proxy_texture.png'}
    assert len(warnings) == 1 and 'no proxy mesh' in warnings[0] and '--density ' in warnings[0]
    stage = Usd.Stage.Open(str(tmp_path / 'dcc' / 'scene.usda'))
    assert not stage.GetPrimAtPath('/World/proxy')
    assert len([p for p in stage.Traverse() if p.IsA(UsdGeom.Camera)]) > 10


BPY_IMPORT = r'''
import json, sys
import bpy
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.wm.usd_import(filepath=sys.argv[1])
cameras = {o.name: {'lens': o.data.lens, 'sensor': o.data.sensor_width}
           for o in bpy.data.objects if o.type == 'CAMERA'}
print('CAMERAS ' + json.dumps(cameras))
'''


def test_blenders_usd_importer_keeps_one_named_camera_per_image(exported, tmp_path):
    """Blender 4.2's USD importer (pip bpy: Debian's Blender has none) flattens the prim
    hierarchy; the cameras arrived as _00000, _00000.001, ... (issue 49, item 3). Each
    arrives as <split>_<image stem>, one per image, with the USD lens."""
    python = blender_python()
    run, out = exported
    script = tmp_path / 'import.py'
    script.write_text(BPY_IMPORT)
    done = subprocess.run([python, str(script), os.path.join(out, 'scene.usda')],
                          capture_output=True, text=True, timeout=300)
    line = next((x for x in done.stdout.splitlines() if x.startswith('CAMERAS ')), None)
    assert line, done.stdout + done.stderr
    cameras = json.loads(line[len('CAMERAS '):])
    expected = {f'{split}_{stem}' for split, stem in _dataset_cameras(run)} | {'video_orbit'}
    assert set(cameras) == expected
    stage = Usd.Stage.Open(os.path.join(out, 'scene.usda'))
    lens = UsdGeom.Camera(stage.GetPrimAtPath('/World/cameras/train/train_000000'))
    assert cameras['train_000000']['lens'] == pytest.approx(lens.GetFocalLengthAttr().Get(),
                                                          rel=1e-5)
