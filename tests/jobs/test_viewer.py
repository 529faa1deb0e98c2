"""The web viewer (``view``, ``optimize --view``) driven as a user drives it: headless Chromium
opens the page of a tiny run, and the tests click its controls and read its screen; and the
camera-path files that its editor saves and ``video --path`` renders.

The browser tests need Debian's ``chromium`` and ``chromium-driver`` (``scripts/setup.sh
--test`` installs them) and the extras ``[viewer,test]`` (viser, selenium); without Chromium
they fail, unless ``MI_NERFPP_NO_BROWSER=1`` skips them.
"""
from __future__ import annotations

import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from types import SimpleNamespace

import imageio.v3 as iio
import numpy as np
import pytest
from PIL import Image

from mi_nerfpp.commands.cli import main
from mi_nerfpp.files.atomic import lock_folder
from mi_nerfpp.jobs.viewer import (MOVING_WIDTH, SETTLE_SECONDS, View,
                                   display, letterbox, open_viewer,
                                   render_widths, viewer_camera, wxyz_of)
from mi_nerfpp.output.camera_path import (CameraPath, CameraPathError, Pose,
                                          path_cameras, read_path,
                                          sample_frames, write_path)
from mi_nerfpp.output.views import ViewRenderer
from tests.helpers import orbit_camera

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CHROMIUM = shutil.which('chromium') or shutil.which('chromium-browser')
CHROMEDRIVER = shutil.which('chromedriver')
NO_BROWSER = os.environ.get('MI_NERFPP_NO_BROWSER', '').strip() not in ('', '0')
WINDOW = (1000, 700)


def free_port():
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def env():
    """The environment of a command run as a subprocess: this checkout's package first."""
    e = dict(os.environ)
    e['PYTHONPATH'] = ROOT + os.pathsep + e.get('PYTHONPATH', '')
    return e


# ------------------------------------------------------------------------------- camera paths

def _pose(angle, height=0.2, fov=40.0, radius=3.0):
    """A pose at ``height`` on a circle of ``radius`` about the y axis, looking at the origin."""
    camera = orbit_camera(angle, math.atan2(height, radius), math.hypot(radius, height), 8, 8)
    return Pose(camera.c2w, fov)


def test_a_path_passes_through_its_keyframes_smoothly_and_a_loop_closes():
    keys = [_pose(a, fov=f) for a, f in ((0, 40), (0.6, 50), (1.3, 45), (2.0, 40))]
    frames = sample_frames(keys, 31)
    assert np.allclose(frames[0].c2w, keys[0].c2w, atol=1e-12)
    assert np.allclose(frames[-1].c2w, keys[-1].c2w, atol=1e-12)
    assert np.allclose(frames[10].c2w, keys[1].c2w, atol=1e-12) and frames[10].fov_y == 50
    for f in frames:                     # rotations stay rotations
        r = f.c2w[:3, :3]
        assert np.allclose(r.T @ r, np.eye(3), atol=1e-9) and np.linalg.det(r) > 0
    steps = np.diff([f.c2w[:3, 3] for f in frames], axis=0)
    sizes = np.linalg.norm(steps, axis=1)
    assert sizes.max() < 2.5 * sizes.min()           # no jumps, no stops
    loop = sample_frames(keys, 40, loop=True)
    assert np.allclose(loop[0].c2w, keys[0].c2w) and np.allclose(loop[30].c2w, keys[3].c2w)
    closing = np.linalg.norm(loop[-1].c2w[:3, 3] - loop[0].c2w[:3, 3])
    assert closing < 2.5 * np.median(np.linalg.norm(np.diff(
        [f.c2w[:3, 3] for f in loop], axis=0), axis=1))      # the seam is one more step


def test_a_path_file_round_trips_and_bad_files_are_named(tmp_path):
    path = CameraPath([_pose(0), _pose(1)], resolution=(64, 36), fps=12, seconds=2).resample()
    assert len(path.frames) == 24
    write_path(tmp_path / 'p.json', path)
    back = read_path(tmp_path / 'p.json')
    assert back.resolution == (64, 36) and back.fps == 12 and len(back.frames) == 24
    assert all(np.array_equal(a.c2w, b.c2w) and a.fov_y == b.fov_y
               for a, b in zip(path.frames, back.frames))
    cams = path_cameras(back)
    assert cams[0].width == 64 and abs(cams[0].fov_y - 40) < 1e-9
    data = json.loads((tmp_path / 'p.json').read_text())
    data['frames'][3]['c2w'][0][0] = 7.0
    (tmp_path / 'bad.json').write_text(json.dumps(data))
    with pytest.raises(CameraPathError, match=r'bad\.json: frame 3: c2w must be a rotation'):
        read_path(tmp_path / 'bad.json')
    (tmp_path / 'other.json').write_text('{"frames": []}')
    with pytest.raises(CameraPathError, match='not a camera path file'):
        read_path(tmp_path / 'other.json')
    del data['frames']                  # keyframes only: the frames are sampled
    (tmp_path / 'keys.json').write_text(json.dumps(data))
    assert len(read_path(tmp_path / 'keys.json').frames) == 24


def test_video_writes_its_orbit_as_a_path_that_renders_the_same_frames(tiny_run, tmp_path):
    orbit = str(tmp_path / 'orbit.json')
    assert main(['video', tiny_run, '--write-path', orbit, '--frames', '6', '--res',
                 '24x16']) == 0
    path = read_path(orbit)
    assert len(path.frames) == 6 and len(path.keyframes) == 8 and path.loop
    assert main(['video', tiny_run, '--frames', '6', '--res', '24x16', '-o',
                 str(tmp_path / 'a.gif')]) == 0
    assert main(['video', tiny_run, '--path', orbit, '-o', str(tmp_path / 'b.gif')]) == 0
    for i in range(6):
        a = iio.imread(tmp_path / 'a_frames' / f'frame_{i:05d}.png')
        b = iio.imread(tmp_path / 'b_frames' / f'frame_{i:05d}.png')
        assert np.array_equal(a, b)


def test_viewer_pieces():
    cam = viewer_camera([0.1, 0.2, 0.3], wxyz_of(_pose(0.4).c2w), np.radians(50), 16 / 9, 320)
    assert (cam.width, cam.height) == (320, 180) and abs(cam.fov_y - 50) < 1e-9
    assert np.allclose(cam.c2w[:3, :3], _pose(0.4).c2w[:3, :3])
    assert render_widths(1000, 1280) == [MOVING_WIDTH, 640, 1000]
    assert render_widths(200, 1280) == [MOVING_WIDTH]
    assert letterbox(np.zeros((9, 16, 3), np.uint8), 1.0).shape == (16, 16, 3)
    layers = {k: np.full((2, 3), 0.5, np.float32) for k in
              ('R', 'G', 'B', 'fg.R', 'fg.G', 'fg.B', 'fg.A', 'bg.R', 'bg.G', 'bg.B')}
    layers['depth.Z'] = np.array([[1, 2, 3], [4, 5, 6]], np.float32)
    for layer in ('beauty', 'foreground', 'background', 'depth', 'alpha'):
        image = display(layers, layer)
        assert image.shape == (2, 3, 3) and image.dtype == np.uint8


def test_a_moving_view_renders_coarse_and_is_refined_once_it_settled(tiny_run):
    """A moving view is rendered without fine samples, its refinement with the run's, and
    only SETTLE_SECONDS after the moving view was sent; a view with no refinement to come is
    rendered with the run's samples at once (no browser: a stand-in for the page's client)."""
    viewer = open_viewer(tiny_run, port=free_port(), max_width=640)
    try:
        assert viewer.moving_renderer.scene.integrator().sampling_overrides['fine_samples'] == 0
        assert viewer.renderer.scene.integrator().sampling_overrides['fine_samples'] is None
        used = []
        for name in ('renderer', 'moving_renderer'):
            renderer = getattr(viewer, name)
            renderer.render = (lambda render, name: lambda camera: (used.append(name),
                                                                     render(camera))[1])(
                renderer.render, name)
        camera = SimpleNamespace(position=(0.1, 0.2, 0.9), wxyz=wxyz_of(_pose(0.4).c2w),
                                 fov=np.radians(50), aspect=16 / 9, image_width=640)
        client = SimpleNamespace(client_id=1, camera=camera, flush=lambda: None,
                                 scene=SimpleNamespace(set_background_image=lambda *a, **k: 0))
        view = viewer.views[1] = View(client)
        assert viewer.work() and used == ['moving_renderer'] and view.stage == 0
        sent = view.moving_sent
        assert sent >= view.changed
        assert viewer.pending(sent + 0.5 * SETTLE_SECONDS) is None
        assert viewer.pending(sent + SETTLE_SECONDS + 1e-3)[1:] == (640, 1)
        while time.monotonic() < sent + SETTLE_SECONDS + 1e-3:
            time.sleep(0.05)
        assert viewer.work() and used[-1] == 'renderer' and view.stage == 1
        camera.image_width = 200            # one stage (320 pixels): the run's samples at once
        assert viewer.work() and used[-1] == 'renderer' and view.stage == 0
    finally:
        viewer.close()



def test_the_viewer_shows_a_training_photos_appearance(capture, tiny_run, tmp_path):
    """A run with per-photo appearance offers 'neutral' and each training photo in its
    'Appearance' menu; choosing a photo renders with its code, 'neutral' with none; a run
    without has no menu."""
    import mitsuba as mi
    from tests.helpers import TINY_RUN
    out = str(tmp_path / 'run')
    assert main(['optimize', capture, '--out', out, '--appearance-embedding', '3',
                 *TINY_RUN]) == 0
    viewer = open_viewer(out, port=free_port(), max_width=320)
    try:
        choices = viewer.appearance_choices()
        names = [os.path.basename(p) for p in viewer.splits.train.image_paths]
        assert choices == ['neutral'] + [f'{i}: {n}' for i, n in enumerate(names)]
        assert viewer.appearance is not None and viewer.appearance.value == 'neutral'
        table = np.zeros((len(names), 3), np.float32)
        table[2] = [2.0, -2.0, 1.5]
        viewer.model.embedding = mi.TensorXf(table)
        camera = viewer.splits.train.cameras[2]
        neutral = viewer.renderer.render(camera)['R']
        viewer.show_appearance(choices[3])
        assert viewer.renderer.scene.integrator().appearance_image == 2
        assert viewer.moving_renderer.scene.integrator().appearance_image == 2
        assert np.abs(viewer.renderer.render(camera)['R'] - neutral).max() > 1e-3
        viewer.show_appearance('neutral')
        np.testing.assert_array_equal(viewer.renderer.render(camera)['R'], neutral)
    finally:
        viewer.close()
    plain = open_viewer(tiny_run, port=free_port(), max_width=320)
    try:
        assert plain.appearance_choices() == ['neutral'] and plain.appearance is None
    finally:
        plain.close()


# ------------------------------------------------------------------------------- the browser

needs_browser = pytest.mark.skipif(NO_BROWSER, reason='MI_NERFPP_NO_BROWSER is set')


@pytest.fixture(scope='module')
def browser():
    if not (CHROMIUM and CHROMEDRIVER):
        pytest.fail('the viewer tests need Chromium and its driver: apt-get install chromium '
                    'chromium-driver (scripts/setup.sh --test), or set MI_NERFPP_NO_BROWSER=1 '
                    'to skip them')
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service
    options = Options()
    options.binary_location = CHROMIUM
    for arg in ('--headless=new', '--no-sandbox', '--disable-dev-shm-usage', '--disable-gpu',
                f'--window-size={WINDOW[0]},{WINDOW[1]}'):
        options.add_argument(arg)
    driver = webdriver.Chrome(options=options, service=Service(CHROMEDRIVER))
    yield driver
    driver.quit()


class Page:
    """The viewer's page in the browser, as a user sees and uses it."""

    def __init__(self, driver):
        self.driver = driver

    def control(self, label):
        """The input that the label ``label`` names (a checkbox, a dropdown, a text box)."""
        from selenium.webdriver.common.by import By
        return self.driver.find_element(
            By.XPATH, f"//label[text()='{label}']/ancestor::div[contains(@class, "
                      f"'mantine-Flex-root')][1]//input")

    def click(self, text):
        """Click the button that says ``text``."""
        from selenium.webdriver.common.by import By
        button = self.driver.find_element(By.XPATH, f"//button[.//span[text()='{text}']]")
        self.driver.execute_script('arguments[0].scrollIntoView({block: "center"});', button)
        button.click()

    def choose(self, label, option):
        """Pick ``option`` in the dropdown ``label``."""
        from selenium.webdriver.common.by import By
        self.control(label).click()
        deadline = time.time() + 5
        while time.time() < deadline:
            options = [o for o in self.driver.find_elements(By.XPATH, "//*[@role='option']")
                       if o.text.strip() == option]
            if options:
                options[0].click()
                return
            time.sleep(0.05)
        raise AssertionError(f'no option {option!r} in {label!r}')

    def type(self, label, text):
        from selenium.webdriver.common.keys import Keys
        box = self.control(label)
        box.send_keys(Keys.CONTROL, 'a')
        box.send_keys(text, Keys.ENTER)

    def drag(self, dx, dy):
        """Orbit the camera: drag the mouse across the middle of the left of the canvas."""
        from selenium.webdriver.common.action_chains import ActionChains
        from selenium.webdriver.common.by import By
        canvas = self.driver.find_element(By.TAG_NAME, 'canvas')
        chain = ActionChains(self.driver, duration=50)
        chain.move_to_element_with_offset(canvas, -200, 0).click_and_hold()
        for _ in range(5):
            chain.move_by_offset(dx // 5, dy // 5)
        chain.release().perform()

    def screenshot(self):
        png = self.driver.get_screenshot_as_png()
        return iio.imread(png, extension='.png')[..., :3]

    def text(self):
        from selenium.webdriver.common.by import By
        return self.driver.find_element(By.TAG_NAME, 'body').text


def wait_for(condition, seconds=60, what='the viewer'):
    deadline = time.time() + seconds
    while time.time() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f'timed out waiting for {what}')


@pytest.fixture(scope='module')
def served(tiny_run):
    """The viewer of the tiny run, serving from a thread of this process."""
    viewer = open_viewer(tiny_run, port=free_port(), max_width=640)
    stop = threading.Event()
    thread = threading.Thread(target=viewer.serve, args=(stop,), daemon=True)
    thread.start()
    yield viewer
    stop.set()
    thread.join(10)
    viewer.close()


def test_the_editor_loads_the_built_in_paths_as_video_makes_them(served, tmp_path):
    from mi_nerfpp.output.video import built_in_path
    viewer = served
    viewer.width.value, viewer.height.value = 48, 27
    for name in ('orbit', 'test'):
        viewer.builtin.value = name
        viewer._load_builtin()
        expected = built_in_path(name, viewer.splits, viewer.normalization, res=(48, 27))
        assert len(viewer.path.frames) == len(expected.frames)
        assert all(np.allclose(a.c2w, b.c2w) for a, b in zip(viewer.path.frames,
                                                              expected.frames))
        viewer.save_path(str(tmp_path / f'{name}.json'))
        saved = read_path(tmp_path / f'{name}.json')
        assert len(saved.keyframes) == len(expected.keyframes) and saved.loop == (name == 'orbit')
    viewer._edit_keys(lambda keys: [])
    assert viewer.path.frames == []


def test_a_viewer_reloads_the_model_that_a_training_elsewhere_writes(tiny_run, tmp_path):
    run_dir = str(tmp_path / 'run')
    shutil.copytree(tiny_run, run_dir)
    viewer = open_viewer(run_dir, port=free_port(), max_width=320)
    try:
        assert viewer.stats.iteration == 5 and viewer.stats.state == 'finished run'
        assert not viewer.check_model_file()            # nothing new
        before, version = viewer.renderer, viewer.model_version
        model = os.path.join(run_dir, 'model.npz')
        stat = os.stat(model)
        os.utime(model, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10 ** 9))   # a new checkpoint
        viewer._checked = float('-inf')                  # past RELOAD_SECONDS
        assert viewer.check_model_file()
        assert viewer.renderer is not before and viewer.model_version == version + 1
        assert viewer.stats.state == 'model.npz'
    finally:
        viewer.close()


def settled(viewer):
    """The one view of the page, once its camera stood still for a second (the orbit controls
    glide on after a drag) and its last refinement was rendered and shown."""
    def done():
        views = list(viewer.views.values())
        if len(views) != 1 or views[0].last_camera is None:
            return None
        key = viewer._camera_key(views[0].client)
        if key is None or key != views[0].key or viewer.layer.value != views[0].layer or \
                views[0].stage != len(render_widths(key[4], viewer.max_width)) - 1:
            return None
        if time.monotonic() - views[0].changed < 1.0:
            return None
        return views[0]
    view = wait_for(done, what='a refined view')
    time.sleep(1.0)                      # the browser draws it
    return view


def screen_region(image):
    """The part of the canvas that no control, notice or axes gizmo covers: left of the GUI
    panel, below the browser's notices, above the gizmo (fractions of the window)."""
    h, w = image.shape[:2]
    return image[int(0.35 * h):int(0.85 * h), int(0.12 * w):int(0.6 * w)].astype(np.float64)


def expected_screen(viewer, view, layer, shape):
    """What the canvas should show: the integrator's render of the view's camera (rendered
    here, again), displayed as ``layer`` and stretched to the canvas."""
    layers = ViewRenderer(viewer.model).render(view.last_camera)
    image = Image.fromarray(display(layers, layer)).resize((shape[1], shape[0]), Image.BILINEAR)
    return np.asarray(image)


@needs_browser
def test_the_page_shows_the_model_its_layers_and_saves_a_path_that_video_renders(
        served, browser, tiny_run, tmp_path):
    viewer = served
    page = Page(browser)
    browser.get(viewer.url)
    wait_for(lambda: 'Add keyframe' in page.text(), what='the page')
    # The overlays off (as a user would, to look at the model alone).
    page.control('Cameras').click()
    page.control('Unit sphere').click()
    wait_for(lambda: not viewer.show_cameras.value and not viewer.show_sphere.value)
    view = settled(viewer)
    shot = page.screenshot()
    expected = expected_screen(viewer, view, 'beauty', shot.shape)
    error = np.abs(screen_region(shot) - screen_region(expected)).mean()
    other = np.abs(screen_region(expected) - screen_region(
        expected_screen(viewer, view, 'depth', shot.shape))).mean()
    # JPEG, the browser's resampling and colour management differ from PIL's by a few levels;
    # another image differs by tens.
    assert error < 8 and other > 3 * error, (error, other)

    page.choose('Layer', 'depth')
    wait_for(lambda: viewer.layer.value == 'depth')
    view = settled(viewer)
    depth_shot = page.screenshot()
    changed = np.abs(screen_region(depth_shot) - screen_region(shot)).mean()
    depth_error = np.abs(screen_region(depth_shot) - screen_region(
        expected_screen(viewer, view, 'depth', shot.shape))).mean()
    assert changed > 3 * depth_error and depth_error < 8, (changed, depth_error)
    page.choose('Layer', 'beauty')

    # A path of three keyframes, the camera orbited between them, saved from the page.
    cameras = []
    for i in range(3):
        if i:
            before = view.client.camera.position.copy()
            page.drag(120, 10)
            wait_for(lambda: not np.allclose(view.client.camera.position, before),
                     what='the camera to move')
        view = settled(viewer)
        cameras.append(view.last_camera)
        page.click('Add keyframe')
        wait_for(lambda: len(viewer.path.keyframes) == i + 1, what='a keyframe')
    target = str(tmp_path / 'drawn.json')
    page.type('File', target)
    wait_for(lambda: viewer.file.value == target)
    page.click('Save path')
    wait_for(lambda: os.path.exists(target), what='the saved path')
    path = read_path(target)
    assert len(path.keyframes) == 3 and len(path.frames) == round(path.seconds * path.fps)
    norm = viewer.normalization
    for i, (key, cam) in enumerate(zip(path.keyframes, cameras)):   # each keyframe is the
        world = norm.to_world_camera(cam)                            # view it was added from
        assert np.allclose(key.c2w, world.c2w, atol=1e-9), i
        assert abs(key.fov_y - cam.fov_y) < 1e-9
    # The preview in the page: its frames are the path's.
    page.control('Preview').click()
    wait_for(lambda: viewer.preview_cameras, what='a preview frame')
    preview = viewer.preview_cameras[-1]
    frame0 = path_cameras(path, norm)[0]
    assert np.allclose(preview.c2w, frame0.c2w, atol=1e-12)
    assert abs(preview.fov_y - frame0.fov_y) < 1e-9
    page.control('Preview').click()

    # video renders the saved path: every frame's camera (the EXR header, float32) is the
    # path's, within float32 precision.
    out = str(tmp_path / 'drawn.mp4')
    assert main(['video', tiny_run, '--path', target, '--res', '32x18', '--exr', '-o',
                 out]) == 0
    import OpenEXR
    frames = path_cameras(path)
    for i in (0, len(frames) // 2, len(frames) - 1):
        header = OpenEXR.File(str(tmp_path / 'drawn_frames' / f'frame_{i:05d}.exr')).header()
        world_to_camera = np.array(header['worldToCamera'], dtype=np.float64).T
        expected = np.diag([1.0, -1, 1, 1]) @ np.linalg.inv(frames[i].c2w)
        assert np.abs(world_to_camera - expected).max() < 1e-5
        assert abs(header['fovY'] - frames[i].fov_y) < 1e-4


@needs_browser
def test_ctrl_c_stops_the_viewer_cleanly_and_it_never_holds_the_run_lock(
        tiny_run, browser):
    port = free_port()
    proc = subprocess.Popen([sys.executable, '-m', 'mi_nerfpp', 'view', tiny_run, '--port',
                             str(port), '--max-width', '320'], env=env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert f'http://127.0.0.1:{port}' in line, line
        browser.get(f'http://127.0.0.1:{port}')
        page = Page(browser)
        wait_for(lambda: 'Add keyframe' in page.text(), what='the page')
        with lock_folder(tiny_run, what='run folder'):      # training could start here
            pass
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode in (0, 130), err
    assert 'Traceback' not in err and 'Traceback' not in out, err


@needs_browser
def test_optimize_view_shows_training_and_pauses_it(capture, tmp_path, browser):
    port = free_port()
    out = str(tmp_path / 'run')
    proc = subprocess.Popen([sys.executable, 'optimize.py', capture, '--out', out,
                             '--iterations', '100000', '--batch-rays', '256', '--samples', '8',
                             '8', '8', '--checkpoint-every', '0', '--preview-every', '20',
                             '--view', '--view-port', str(port), '--view-max-width', '320'],
                            cwd=ROOT, env=env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if 'viewer: http://' in line:
                break
        assert any(f'http://127.0.0.1:{port}' in x for x in lines), ''.join(lines)
        page = Page(browser)
        browser.get(f'http://127.0.0.1:{port}')

        def step():
            import re
            found = re.search(r'step (\d+)', page.text())
            return int(found.group(1)) if found else None
        first = wait_for(step, what='the training step')
        wait_for(lambda: (step() or 0) > first + 20, what='training to go on')
        wait_for(lambda: 'preview view PSNR' in page.text(), what='the held-out PSNR')
        assert 'rays/s' in page.text()
        page.click('Pause training')
        wait_for(lambda: 'paused' in page.text(), what='the pause')
        held = step()
        time.sleep(2)
        assert step() == held
        page.click('Resume training')
        wait_for(lambda: (step() or 0) > held + 5, what='training to resume')
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, rest
    assert 'Traceback' not in rest and os.path.exists(os.path.join(out, 'model.npz'))
