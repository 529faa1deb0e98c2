"""A tracked camera in (issue 62, item 2): the project's own USD and .chan exports and nerfstudio's
camera_path.json read back as the cameras written; a camera animated in Blender 4.2 and exported
to USD reads back as Blender's own matrices, keeps its frame numbers, and renders (video, render)
as the same poses given directly; bad files end with one line naming the file."""
import json
import os
import subprocess

import numpy as np
import pytest

from mi_nerfpp.commands.cli import main
from mi_nerfpp.data import Camera, opencv_to_opengl
from mi_nerfpp.jobs import export
from mi_nerfpp.output.tracked_camera import (TrackedCameraError, read_shot,
                                             shot_format)
from tests.helpers import blender_python, debian_blender, orbit_camera

from pxr import Usd, UsdGeom  # noqa: E402  (usd-core: a test dependency, setup.sh)

WIDTH, HEIGHT = 32, 24


def known_cameras(off_centre=True):
    """Cameras of several positions, focal lengths and (with ``off_centre``) principal
    points, named a, b, c, d."""
    cameras = []
    for i, (angle, focal, shift) in enumerate([(0.3, 0.8, (2.5, -1.25)), (1.4, 1.1, (-3.0, 0.5)),
                                               (2.9, 0.95, (0.0, 2.0)), (4.4, 1.3, (1.0, 1.0))]):
        camera = orbit_camera(angle, 0.2 + 0.1 * i, 2.5 + 0.3 * i, WIDTH, HEIGHT, focal)
        camera.c2w[:3, 3] += [0.4, -0.2, 1.1]           # not centred on the origin
        if off_centre:
            camera.K[:2, 2] += shift
        camera.name = 'abcd'[i]
        cameras.append(camera)
    return cameras


def assert_same_camera(read: Camera, written: Camera, tol=1e-6):
    assert (read.width, read.height) == (written.width, written.height)
    np.testing.assert_allclose(read.c2w, written.c2w, rtol=0, atol=tol)
    np.testing.assert_allclose(read.K, written.K, rtol=tol, atol=tol)


def one_line_error(path, *needles, **kwargs):
    with pytest.raises(TrackedCameraError) as caught:
        read_shot(path, **kwargs)
    message = str(caught.value)
    assert '\n' not in message and message.startswith(str(path)), message
    for needle in needles:
        assert needle in message, message
    return message


# ----------------------------------------------------------------------------- round trips

def test_the_projects_usd_export_reads_back_as_the_cameras_written(tmp_path):
    """export's scene.usda: each still camera (by name, off-centre principal points) and every
    frame of the animated one read back within 1e-6 (pose and K); several cameras and no
    --camera, or an unknown name, is one line listing the names."""
    stills, video = known_cameras(), known_cameras()[::-1]
    export.write_usd(str(tmp_path), {'train': stills}, video=video, proxy=None)
    path = tmp_path / 'scene.usda'
    assert shot_format(path) == 'usd'
    for camera in stills:
        shot = read_shot(path, camera=f'train_{camera.name}')
        assert shot.camera == f'/World/cameras/train/train_{camera.name}'
        assert shot.numbers == [1, 2, 3, 4]                # the stage's frame range
        assert_same_camera(shot.cameras(WIDTH, HEIGHT)[1], camera)
        assert shot.image_size(WIDTH, 999) == (WIDTH, HEIGHT)   # the film's aspect
        assert shot.frames[0].focal_mm == pytest.approx(camera.K[0, 0] * 36 / WIDTH, rel=1e-6)
    shot = read_shot(path, camera='video_orbit')
    assert shot.numbers == [1, 2, 3, 4] and shot.fps == export.VIDEO_FPS
    for number, camera in zip(shot.numbers, video):
        assert_same_camera(shot.cameras(WIDTH, HEIGHT)[number], camera)
    names = 'train_a, train_b, train_c, train_d, video_orbit'
    one_line_error(path, f'5 cameras in the USD file ({names})', '--camera NAME')
    one_line_error(path, f'no camera named nope in the USD file; its cameras: {names}',
                   camera='nope')


def test_the_projects_chan_export_reads_back_as_the_cameras_written(tmp_path):
    """export's .chan (frame tx ty tz rx ry rz vfov, ZXY, film back of the images' aspect):
    frames 1.. read back within 1e-6 at the images' size."""
    cameras = known_cameras(off_centre=False)
    path = tmp_path / 'train.chan'
    export.write_chan(str(path), cameras)
    shot = read_shot(path)
    assert shot.format == 'chan' and shot.numbers == [1, 2, 3, 4] and shot.size is None
    assert shot.image_size(WIDTH, HEIGHT) == (WIDTH, HEIGHT)
    for number, camera in zip(shot.numbers, cameras):
        assert_same_camera(shot.cameras(WIDTH, HEIGHT)[number], camera)


def test_a_nerfstudio_camera_path_reads_back_identical(tmp_path):
    """nerfstudio's rendered camera path (OpenGL camera_to_world row-major, vertical fov,
    render size, fps): frames 0.. as ns-render numbers them, the cameras identical."""
    cameras = known_cameras(off_centre=False)
    path = tmp_path / 'camera_path.json'
    path.write_text(json.dumps({
        'camera_type': 'perspective', 'render_width': WIDTH, 'render_height': HEIGHT,
        'fps': 30, 'seconds': len(cameras) / 30, 'smoothness_value': 0.5, 'is_cycle': False,
        'camera_path': [{'camera_to_world': opencv_to_opengl(c.c2w).ravel().tolist(),
                         'fov': c.fov_y, 'aspect': WIDTH / HEIGHT} for c in cameras]}))
    assert shot_format(path) == 'nerfstudio'
    shot = read_shot(path)
    assert shot.numbers == [0, 1, 2, 3] and shot.fps == 30
    assert shot.image_size(640, 360) == (WIDTH, HEIGHT)
    for number, camera in zip(shot.numbers, cameras):
        assert_same_camera(shot.cameras(WIDTH, HEIGHT)[number], camera, tol=1e-12)
    assert shot.frame_name.format(7) == 'camera_path.0007'


def _nerfstudio_path(path, cameras, aspects, size=None):
    """nerfstudio's camera path of ``cameras`` with a per-frame ``aspect`` (``size``: its
    render_width x render_height, none where None)."""
    data = {'camera_type': 'perspective', 'fps': 24, 'camera_path': [
        {'camera_to_world': opencv_to_opengl(c.c2w).ravel().tolist(), 'fov': c.fov_y,
         'aspect': a} for c, a in zip(cameras, aspects)]}
    if size:
        data['render_width'], data['render_height'] = size
    path.write_text(json.dumps(data))
    return path


def test_a_film_aspect_that_changes_between_frames(tmp_path, tiny_run, capsys):
    """nerfstudio keyframes of two aspects (4:3, then 2:1), no render size: each frame alone
    has its own size (the width given, the height from its aspect) with its vertical field of
    view across that height; a video of all of them has no one size: one line naming the
    frames and --res; with --res, or a range of one aspect, it renders; with the file's
    render size, the per-frame aspect is ignored, as ns-render ignores it."""
    cameras = known_cameras(off_centre=False)
    path = _nerfstudio_path(tmp_path / 'aspects.json', cameras, [4 / 3, 4 / 3, 2.0, 2.0])
    shot = read_shot(path)
    assert shot.within((0, 1)).image_size(48, 1) == (48, 36)
    assert shot.within((2, 3)).image_size(48, 1) == (48, 24)
    for number in (1, 2):
        frame = shot.within((number, number))
        size = frame.image_size(48, 1)
        camera = frame.cameras(*size)[number]
        assert camera.K[1, 1] == pytest.approx(cameras[number].K[1, 1] * size[1] / HEIGHT)
        assert camera.K[0, 2] == size[0] / 2 and camera.K[1, 2] == size[1] / 2
    with pytest.raises(TrackedCameraError) as caught:
        shot.image_size(48, 1)
    message = str(caught.value)
    assert message.startswith(str(path)) and '\n' not in message
    assert 'changes from 1.333 at frame 1 to 2 at frame 2' in message and '--res WxH' in message
    assert 'across the height' in message
    fixed = read_shot(_nerfstudio_path(tmp_path / 'fixed.json', cameras, [4 / 3, 4 / 3, 2.0, 2.0],
                                       size=(WIDTH, HEIGHT)))
    assert fixed.image_size(48, 1) == (WIDTH, HEIGHT)
    for number, camera in fixed.cameras(WIDTH, HEIGHT).items():
        assert_same_camera(camera, cameras[number], tol=1e-12)
    # The commands: one line without a size, frames with --res or a range of one aspect.
    capsys.readouterr()
    assert main(['video', tiny_run, '--path', str(path), '-o', str(tmp_path / 'v.gif')]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'changes from 1.333 at frame 1 to 2 at frame 2' in err[0], err
    frames = tmp_path / 'frames'
    assert main(['video', tiny_run, '--path', str(path), '--frame-range', '2-3', '--exr',
                 '--frames-dir', str(frames), '-o', str(tmp_path / 'v.gif')]) == 0
    from mi_nerfpp.files.exr import read_exr
    from mi_nerfpp.jobs.run import open_run
    width = open_run(tiny_run)[3].train.cameras[0].width      # the training images' width
    for number in (2, 3):
        assert read_exr(frames / f'aspects.{number:04d}.exr')['R'].shape == (width // 2, width)


def test_cameras_are_placed_as_export_wrote_them_also_for_a_photo_run(tmp_path):
    """A photo run's export is in COLMAP's frame (structure from motion's normalization and
    the model's undone): read back through both again, the cameras are the model-frame ones."""
    from mi_nerfpp.core.frame import Normalization
    from mi_nerfpp.data.sfm import SFM_FILE, SFM_FORMAT
    from mi_nerfpp.output.tracked_camera import capture_normalizations
    sfm, model = Normalization((0.5, -2.0, 3.0), 0.25), Normalization((0.1, 0.2, -0.3), 0.4)
    (tmp_path / SFM_FILE).write_text(json.dumps({'format': SFM_FORMAT,
                                                 'normalization': sfm.to_config()}))
    placement = capture_normalizations(str(tmp_path))
    assert placement == [sfm] and capture_normalizations(str(tmp_path / 'none')) == []
    in_model = known_cameras()
    in_colmap = [sfm.to_world_camera(model.to_world_camera(c)) for c in in_model]
    export.write_usd(str(tmp_path), {'train': in_colmap}, proxy=None)
    export.write_chan(str(tmp_path / 'train.chan'), in_colmap)
    for camera in in_model:
        shot = read_shot(tmp_path / 'scene.usda', camera=f'train_{camera.name}')
        assert_same_camera(shot.cameras(WIDTH, HEIGHT, placement + [model])[1], camera)
    chan = read_shot(tmp_path / 'train.chan').cameras(WIDTH, HEIGHT, placement + [model])
    for number, camera in zip(chan, in_model):
        np.testing.assert_allclose(chan[number].c2w, camera.c2w, atol=1e-6)


# ----------------------------------------------------------------------------- bad files

def test_bad_camera_files_end_with_one_line_naming_the_file(tmp_path):
    stage = Usd.Stage.CreateNew(str(tmp_path / 'empty.usda'))
    UsdGeom.Xform.Define(stage, '/World')
    stage.GetRootLayer().Save()
    one_line_error(tmp_path / 'empty.usda', 'no camera in the USD file', 'Cameras ticked')

    export.write_usd(str(tmp_path), {'train': known_cameras()[:1]}, proxy=None)
    text = (tmp_path / 'scene.usda').read_text()
    (tmp_path / 'cut.usda').write_text(text[:len(text) // 2])
    one_line_error(tmp_path / 'cut.usda', 'cannot read USD file', 'export the camera')

    export.write_chan(str(tmp_path / 'ok.chan'), known_cameras(off_centre=False))
    lines = (tmp_path / 'ok.chan').read_text().splitlines()
    (tmp_path / 'seven.chan').write_text('\n'.join([lines[0], ' '.join(lines[1].split()[:7])]))
    one_line_error(tmp_path / 'seven.chan', 'line 2 has 7 columns where 8 are expected '
                   '(frame tx ty tz rx ry rz vfov)', 'Export chan file')
    (tmp_path / 'cut.chan').write_text(lines[0] + '\n' + lines[1][:len(lines[1]) // 2])
    one_line_error(tmp_path / 'cut.chan', 'line 2 has')
    (tmp_path / 'word.chan').write_text(lines[0].replace(lines[0].split()[3], 'abc', 1))
    one_line_error(tmp_path / 'word.chan', "line 1: 'abc' is not a number")
    (tmp_path / 'binary.chan').write_bytes(b'\x00\xff\xfe' * 10)
    one_line_error(tmp_path / 'binary.chan', 'cannot read Nuke .chan file (not text')
    (tmp_path / 'empty.chan').write_text('')
    one_line_error(tmp_path / 'empty.chan', 'the file is empty')

    (tmp_path / 'cut.json').write_text('{"camera_path": [{"camera_to_world": [1, 0')
    # Not told apart from a project path file (video reads it as one, naming the problem).
    assert shot_format(tmp_path / 'cut.json') is None
    one_line_error(tmp_path / 'cut.json', 'cannot read camera file (the JSON is cut short')
    (tmp_path / 'bad.json').write_text(json.dumps({'camera_path': [{'camera_to_world': [1, 2],
                                                                    'fov': 50}]}))
    one_line_error(tmp_path / 'bad.json', 'camera_path[0]: camera_to_world must be 16 numbers')

    shot = read_shot(tmp_path / 'ok.chan')
    with pytest.raises(TrackedCameraError, match=r'ok\.chan: frames 3-9 asked for, but the file '
                                                 r'has frames 1-4'):
        shot.within((3, 9))
    with pytest.raises(TrackedCameraError, match=r'no frame 7; the file has frames 1-4'):
        shot.frame(7)
    assert [f.number for f in shot.within((2, 3)).frames] == [2, 3]


# ----------------------------------------------------------------------------- Blender

BPY_SHOT = r'''
import json, math, sys
import bpy
from mathutils import Vector
bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
scene.render.resolution_x, scene.render.resolution_y = 24, 18
scene.render.fps = 25
scene.frame_start, scene.frame_end = 1001, 1004
data = bpy.data.cameras.new('shotcam')
camera = bpy.data.objects.new('shotcam', data)
scene.collection.objects.link(camera)
scene.camera = camera
for i, frame in enumerate(range(1001, 1005)):
    a = 0.4 + 0.35 * i
    # Around the capture (Y-up radius ~2.6, height 0.5): Blender's Z-up (x, -z, y).
    camera.location = Vector((2.6 * math.cos(a), -2.6 * math.sin(a), 0.5 + 0.1 * i))
    camera.rotation_euler = (Vector((0.1, 0.0, 0.2)) - camera.location).to_track_quat(
        '-Z', 'Y').to_euler()
    data.lens = 30 + 4 * i
    data.shift_x, data.shift_y = 0.02 * i, -0.015 * i
    for path in ('location', 'rotation_euler'):
        camera.keyframe_insert(path, frame=frame)
    for path in ('lens', 'shift_x', 'shift_y'):
        data.keyframe_insert(path, frame=frame)
bpy.ops.wm.usd_export(filepath=sys.argv[1], export_animation=True)
frames = {}
for frame in range(1001, 1005):
    scene.frame_set(frame)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    projection = camera.calc_matrix_camera(depsgraph, x=24, y=18)
    frames[frame] = {'matrix_world': [list(row) for row in camera.matrix_world],
                     'lens': data.lens, 'projection': [list(row) for row in projection]}
print('SHOT ' + json.dumps(frames))
'''


@pytest.fixture(scope='module')
def blender_shot(tmp_path_factory):
    """A camera keyframed in Blender 4.2 over frames 1001-1004 and exported to USD (Z-up), and
    what Blender says of each frame: matrix_world, lens, its projection matrix for 24 x 18."""
    python = blender_python()
    folder = tmp_path_factory.mktemp('blender')
    script, usd = folder / 'shot.py', folder / 'shot.usda'
    script.write_text(BPY_SHOT)
    done = subprocess.run([python, str(script), str(usd)], capture_output=True, text=True,
                          timeout=300)
    line = next((x for x in done.stdout.splitlines() if x.startswith('SHOT ')), None)
    assert line and usd.exists(), done.stdout + done.stderr
    return str(usd), {int(k): v for k, v in json.loads(line[len('SHOT '):]).items()}


def blender_camera(frame, width, height) -> Camera:
    """Blender's camera of a frame, from Blender's own matrices alone: its Z-up world turned
    into the Y-up one (x, y, z -> x, z, -y), its OpenGL camera into OpenCV, K from its
    projection matrix (pixel x = (1 + ndc x)·width/2, pixel y = (1 - ndc y)·height/2)."""
    to_y_up = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
    c2w = to_y_up @ np.array(frame['matrix_world']) @ np.diag([1.0, -1, -1, 1])
    P = np.array(frame['projection'])
    K = np.array([[P[0, 0] * width / 2, 0, (1 - P[0, 2]) * width / 2],
                  [0, P[1, 1] * height / 2, (1 + P[1, 2]) * height / 2], [0, 0, 1]])
    return Camera(K, c2w, width, height)


BLENDER_CHAN = r"""
import json, math, sys
import addon_utils
import bpy
args = json.loads(sys.argv[sys.argv.index('--') + 1])
addon_utils.enable('io_anim_nuke_chan', default_set=True)
bpy.ops.wm.read_factory_settings(use_empty=True)
addon_utils.enable('io_anim_nuke_chan', default_set=True)
scene = bpy.context.scene
width, height = args['size']
scene.render.resolution_x, scene.render.resolution_y = width, height


def camera(name):
    data = bpy.data.cameras.new(name)
    data.sensor_fit, data.sensor_width, data.sensor_height = 'HORIZONTAL', *args['sensor']
    obj = bpy.data.objects.new(name, data)
    scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    return obj


def frames(obj, numbers):
    out = {}
    for number in numbers:
        scene.frame_set(number)
        projection = obj.calc_matrix_camera(bpy.context.evaluated_depsgraph_get(), x=width,
                                            y=height)
        out[number] = {'matrix_world': [list(row) for row in obj.matrix_world],
                       'projection': [list(row) for row in projection]}
    return out


# A camera keyframed in Blender (all three angles, rotation mode ZXY), written by the add-on.
shot = camera('shot')
shot.rotation_mode = 'ZXY'
for number, (location, degrees, lens) in zip(args['numbers'], args['keys']):
    shot.location = location
    shot.rotation_euler = [math.radians(a) for a in degrees]
    shot.data.lens = lens
    shot.keyframe_insert('location', frame=number)
    shot.keyframe_insert('rotation_euler', frame=number)
    shot.data.keyframe_insert('lens', frame=number)
scene.frame_start, scene.frame_end = args['numbers'][0], args['numbers'][-1]
assert bpy.ops.export.export_chan(filepath=args['written'], y_up=False,
                                  rotation_order='ZXY') == {'FINISHED'}
written = frames(shot, args['numbers'])
# The project's .chan read by the add-on onto another camera.
shot.select_set(False)
read = camera('read')
assert bpy.ops.import_scene.import_chan(filepath=args['read'], z_up=False, rotation_order='ZXY',
                                        sensor_width=args['sensor'][0],
                                        sensor_height=args['sensor'][1]) == {'FINISHED'}
print('CHAN ' + json.dumps({'written': written, 'read': frames(read, args['read_numbers'])}))
"""


def _blender_gl_camera(frame, width, height) -> Camera:
    """Blender's camera of a frame in its own world, OpenCV, K from its projection matrix."""
    c2w = np.array(frame['matrix_world']) @ np.diag([1.0, -1, -1, 1])
    P = np.array(frame['projection'])
    K = np.array([[P[0, 0] * width / 2, 0, (1 - P[0, 2]) * width / 2],
                  [0, P[1, 1] * height / 2, (1 + P[1, 2]) * height / 2], [0, 0, 1]])
    return Camera(K, c2w, width, height)


def test_a_chan_reads_and_writes_as_blenders_nuke_chan_addon(tmp_path):
    """The .chan column layout and rotation order checked against a reader and writer this
    project did not write: Blender's bundled Nuke .chan add-on (io_anim_nuke_chan, Debian's
    Blender 3.4; rotation order ZXY, no axis swap, the vertical field of view of a horizontal
    sensor fit of the images' aspect). A camera keyframed in Blender with all three angles and
    the lens animated, exported by the add-on, reads back here as Blender's own matrices; the
    project's export (cameras rolled about their axis) imported by the add-on gives Blender
    cameras equal to the ones written."""
    blender = debian_blender()
    numbers = [1001, 1002, 1003, 1004]
    keys = [((0.4 + 0.2 * i, -0.3 + 0.5 * i, 2.0 - 0.1 * i), (-12.0 + 9 * i, 25.0 + 40 * i,
             7.0 - 11 * i), 28.0 + 6 * i) for i in range(4)]
    cameras = known_cameras(off_centre=False)
    for k, camera in enumerate(cameras):            # rolled: rz of the ZXY angles not zero
        roll = np.radians(10.0 + 15 * k)
        turn = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0],
                         [0, 0, 1]])
        camera.c2w[:3, :3] = camera.c2w[:3, :3] @ turn
    ours, theirs = tmp_path / 'ours.chan', tmp_path / 'blender.chan'
    export.write_chan(str(ours), cameras)
    args = {'size': [WIDTH, HEIGHT], 'sensor': [36.0, 36.0 * HEIGHT / WIDTH],
            'numbers': numbers, 'keys': keys, 'written': str(theirs), 'read': str(ours),
            'read_numbers': [1, 2, 3, 4]}
    script = tmp_path / 'chan.py'
    script.write_text(BLENDER_CHAN)
    done = subprocess.run([blender, '-b', '--factory-startup', '--python-exit-code', '1',
                           '--python', str(script), '--', json.dumps(args)],
                          capture_output=True, text=True, timeout=300)
    line = next((x for x in done.stdout.splitlines() if x.startswith('CHAN ')), None)
    assert done.returncode == 0 and line, done.stdout[-3000:] + done.stderr[-3000:]
    blender_frames = json.loads(line[len('CHAN '):])
    # Blender's .chan, read here: frames as in the file, poses and K as Blender's.
    shot = read_shot(theirs)
    assert shot.numbers == numbers
    read = shot.cameras(WIDTH, HEIGHT)
    for number in numbers:
        expected = _blender_gl_camera(blender_frames['written'][str(number)], WIDTH, HEIGHT)
        assert_same_camera(read[number], expected, tol=1e-5)
    # The project's .chan, read by Blender: its cameras are the ones written.
    for number, camera in zip([1, 2, 3, 4], cameras):
        got = _blender_gl_camera(blender_frames['read'][str(number)], WIDTH, HEIGHT)
        assert_same_camera(got, camera, tol=1e-5)


def test_a_blender_usd_camera_reads_back_as_blenders_matrices(blender_shot):
    """Frames 1001-1004 as in the file, 25 fps, each pose within 1e-5 of Blender's
    matrix_world (Z-up stage), the focal length Blender's lens in mm, K Blender's projection
    (lens shift: off-centre principal points)."""
    usd, blender = blender_shot
    stage = Usd.Stage.Open(usd)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    shot = read_shot(usd, camera='shotcam')
    assert shot.numbers == [1001, 1002, 1003, 1004] and shot.fps == 25
    assert shot.image_size(24, 1) == (24, 18)
    cameras = shot.cameras(24, 18)
    for number, frame in blender.items():
        expected = blender_camera(frame, 24, 18)
        np.testing.assert_allclose(cameras[number].c2w, expected.c2w, atol=1e-5)
        np.testing.assert_allclose(cameras[number].K, expected.K, rtol=1e-5, atol=1e-5)
        assert shot.frames[number - 1001].focal_mm == pytest.approx(frame['lens'], rel=1e-5)
    assert abs(cameras[1004].K[0, 2] - 12) > 0.5 and abs(cameras[1004].K[1, 2] - 9) > 0.3


def rms(a, b):
    return float(np.sqrt(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2)))


def test_blenders_camera_renders_as_its_poses_given_directly(blender_shot, tiny_run, tmp_path,
                                                             capsys):
    """``video --path shot.usda --exr --frames-dir D --frame-range 1002-1003`` writes
    D/shot.1002.exr and D/shot.1003.exr (no other frame), each within 1e-4 RMS (every layer)
    of the same view rendered from Blender's matrices; ``render --camera shot.usda --frame
    1003`` equals a scene file whose sensor is that pose; a range outside the file's is one
    line naming its frames."""
    from mi_nerfpp.core.frame import SCENE_NEAR_CLIP
    from mi_nerfpp.files.exr import read_exr
    from mi_nerfpp.jobs.run import open_run
    from mi_nerfpp.output.scene_xml import write_render_xml
    from mi_nerfpp.output.views import ViewRenderer
    usd, blender = blender_shot
    frames = tmp_path / 'plates'
    assert main(['video', tiny_run, '--path', usd, '--res', '24x18', '--exr', '--frames-dir',
                 str(frames), '--frame-range', '1002-1003', '-o', str(tmp_path / 'shot.gif')]) == 0
    assert sorted(n for n in os.listdir(frames) if not n.endswith('.json')) == [
        'shot.1002.exr', 'shot.1002.png', 'shot.1003.exr', 'shot.1003.png']
    model = open_run(tiny_run)[0]
    renderer = ViewRenderer(model)
    direct = {number: renderer.render(model.normalization.to_model_camera(
        blender_camera(blender[number], 24, 18))) for number in (1002, 1003)}
    for number, other in ((1002, 1003), (1003, 1002)):
        plate = read_exr(frames / f'shot.{number}.exr')
        assert set(direct[number]) <= set(plate)
        assert max(rms(plate[name], direct[number][name]) for name in direct[number]) < 1e-4
        assert rms(plate['R'], direct[other]['R']) > 1e-3      # the frames tell apart
    # render --camera: one frame, as the same pose given directly in a scene file.
    checkpoint = os.path.join(tiny_run, 'model.npz')
    near = model.normalization.to_world_distance(SCENE_NEAR_CLIP)
    write_render_xml(str(tmp_path / 'scene.xml'), checkpoint,
                     blender_camera(blender[1001], WIDTH, HEIGHT), near)
    write_render_xml(str(tmp_path / 'direct.xml'), checkpoint,
                     blender_camera(blender[1003], WIDTH, HEIGHT), near)
    assert main(['render', str(tmp_path / 'scene.xml'), '--camera', usd, '--frame', '1003',
                 '-o', str(tmp_path / 'tracked.exr')]) == 0
    assert main(['render', str(tmp_path / 'direct.xml'), '-o', str(tmp_path / 'direct.exr')]) == 0
    tracked, direct = read_exr(tmp_path / 'tracked.exr'), read_exr(tmp_path / 'direct.exr')
    assert tracked['R'].shape == (HEIGHT, WIDTH)       # the film's width, the USD film's aspect
    assert max(rms(tracked[name], direct[name]) for name in direct) < 1e-4
    capsys.readouterr()
    assert main(['video', tiny_run, '--path', usd, '--frame-range', '990-1002', '-o',
                 str(tmp_path / 'out.gif')]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f'{usd}: frames 990-1002 asked for, but the file has frames ' \
                             f'1001-1004' in err[0], err
    assert main(['render', str(tmp_path / 'scene.xml'), '--camera', usd, '--frame', '7',
                 '-o', str(tmp_path / 'x.exr')]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'no frame 7; the file has frames 1001-1004' in err[0], err
