"""The web viewer's targets (issue 50), measured with headless Chromium on this machine.

    python benchmarks/viewer.py RUN [--data DATA] [--rounds 2] [--steps 200]
    python benchmarks/viewer.py RUN --rounds 0 --name viewer_DATE    # no training rounds

RUN: a finished run of the default capture (``python optimize.py --out RUN``). DATA: the
dataset the training rounds train on (default: RUN's own dataset). Measured:

1. **first frame**: seconds from the browser being told to open the page (``driver.get``) to a
   screenshot that shows the viewer's image (its region left of the GUI panel within
   ``SHOWN_LEVELS`` levels of the image last sent, stretched to the canvas), with the times of
   the steps between; the frustums and the sphere are switched off (server side, before the
   page opens) so that the screenshot shows the model alone
   (the page connected, the first view rendered and sent);
2. **frames/s while the camera moves**: the canvas 960x540 (so that a moving view is 320x180),
   the camera turned about the scene 20 times a second from the server for ``--drag`` seconds
   (faster than the viewer renders), then the mouse dragging in the page (trusted mouse events
   through Chrome's DevTools protocol; the page sends its camera at its own frame rate, here
   software WebGL): the views sent per second, and the render time of each;
3. **training with the viewer open** (``--rounds 0``: not measured): ``--rounds`` rounds, each
   training ``--steps`` steps on DATA without the viewer, then with it open in the browser, the
   camera still (the order swapped every round): training rays per second of wall time (the batch rays times the steps
   of the last half, over their wall time; the page opened and settled before them), and their
   ratio;
4. **a drawn path**: three keyframes added in the page (the camera orbited between them), saved,
   played in the page's preview and rendered by ``video --path FILE --exr``: the largest
   difference between the cameras the preview rendered and those ``video`` rendered (both
   float64; and against the EXR headers, which are float32).

Writes ``benchmarks/results/NAME.json`` (``--name``, default ``viewer``; with ``--rounds 0`` the
variant "no training rounds", which the benchmarks page shows beside the last file with them)
and, with ``--screenshot FILE``, a screenshot of the page (the README's).
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import threading
import time

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import mi_nerfpp  # noqa: E402,F401
from mi_nerfpp.commands.cli import main as cli  # noqa: E402
from mi_nerfpp.files.checkpoint import read_meta  # noqa: E402
from mi_nerfpp.jobs import bench, run  # noqa: E402
from mi_nerfpp.jobs.viewer import (ViewerObserver, open_viewer,  # noqa: E402
                                   render_widths)
from mi_nerfpp.output.camera_path import path_cameras, read_path  # noqa: E402
from mi_nerfpp.training.config import TrainConfig  # noqa: E402
from tests.jobs.test_viewer import Page, free_port, wait_for  # noqa: E402


def browser(width, height):
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service
    options = Options()
    options.binary_location = shutil.which('chromium')
    for arg in ('--headless=new', '--no-sandbox', '--disable-dev-shm-usage', '--disable-gpu',
                f'--window-size={width},{height}'):
        options.add_argument(arg)
    driver = webdriver.Chrome(options=options, service=Service(shutil.which('chromedriver')))
    inner = driver.execute_script('return [window.innerWidth, window.innerHeight]')
    driver.set_window_size(width + width - inner[0], height + height - inner[1])
    return driver


# A screenshot shows the model when its region is within this many levels (of 255) of the image
# sent, on average: the frustums and lines drawn over it and the browser's resampling differ
# by about 13 levels; the page before it (white) by about 100.
SHOWN_LEVELS = 30


def region(image):
    h, w = image.shape[:2]
    return image[int(0.35 * h):int(0.85 * h), int(0.12 * w):int(0.6 * w)].astype(np.float64)


def refined(viewer):
    """Whether the one page's view was rendered at its last refinement."""
    views = list(viewer.views.values())
    if len(views) != 1 or views[0].key is None:
        return False
    return views[0].stage == len(render_widths(views[0].key[4], viewer.max_width)) - 1


def serve(run_dir, overlays=True, **options):
    """A viewer of ``run_dir`` on a free port, serving in a thread: ``(viewer, stop, thread)``
    for :func:`finish`; ``overlays=False``: no cameras or unit sphere over the model."""
    viewer = open_viewer(run_dir, port=free_port(), **options)
    if not overlays:
        viewer.show_cameras.value = False
        viewer.show_sphere.value = False
    stop = threading.Event()
    thread = threading.Thread(target=viewer.serve, args=(stop,), daemon=True)
    thread.start()
    return viewer, stop, thread


def finish(viewer, stop, thread):
    """Stop a viewer of :func:`serve`."""
    stop.set()
    thread.join(10)
    viewer.close()


def first_frame(run_dir, driver):
    """Seconds from opening the page to the first image on screen, and the steps between."""
    viewer, stop, thread = serve(run_dir, overlays=False)     # the model alone on screen
    page = Page(driver)
    t0 = time.monotonic()
    driver.get(viewer.url)
    connected = wait_for(lambda: viewer.views and time.monotonic(), 60, 'the page')
    sent = wait_for(lambda: viewer.sent and viewer.sent[0][0], 60, 'the first frame')
    shown = None
    while time.monotonic() - t0 < 30:
        t = time.monotonic()
        latest = viewer.last_image          # the screen may show any image sent so far
        shot = page.screenshot()
        expected = np.asarray(Image.fromarray(latest).resize((shot.shape[1], shot.shape[0]),
                                                             Image.BILINEAR))
        if np.abs(region(shot) - region(expected)).mean() < SHOWN_LEVELS:
            shown = t
            break
    render = viewer.sent[0][3]
    finish(viewer, stop, thread)
    return {'visible': None if shown is None else shown - t0, 'connected': connected - t0,
            'sent': sent - t0, 'render': render, 'size': list(viewer.sent[0][1:3])}


def drag(driver, seconds):
    """One continuous drag across the canvas for ``seconds``, as trusted mouse events through
    Chrome's DevTools protocol (WebDriver's actions arrive a few per second on a busy machine):
    the button held, the mouse moving 6 pixels every 16 ms, back and forth."""
    width, height = driver.execute_script('return [window.innerWidth, window.innerHeight]')
    x, y = int(0.3 * width), int(0.5 * height)

    def mouse(kind, buttons=1):
        driver.execute_cdp_cmd('Input.dispatchMouseEvent', {
            'type': kind, 'x': x, 'y': y, 'button': 'left', 'buttons': buttons,
            'clickCount': 1})
    mouse('mouseMoved', 0)
    mouse('mousePressed')
    start, i = time.monotonic(), 0
    while time.monotonic() - start < seconds:
        i += 1
        x += -6 if (i // 25) % 2 else 6
        mouse('mouseMoved')
        time.sleep(0.016)
    mouse('mouseReleased', 0)


def moving(run_dir, driver, seconds):
    """Views sent per second while the mouse drags the camera (:func:`drag`)."""
    viewer, stop, thread = serve(run_dir)
    page = Page(driver)
    driver.get(viewer.url)
    wait_for(lambda: 'Add keyframe' in page.text(), 60, 'the page')
    wait_for(lambda: refined(viewer), 120, 'the refined view')
    time.sleep(1)
    updates = []
    for view in list(viewer.views.values()):
        view.client.camera.on_update(lambda cam: updates.append(time.monotonic()))
    t0 = time.monotonic()
    start = len(viewer.sent)
    drag(driver, seconds)
    t1 = time.monotonic()
    frames = [f for f in list(viewer.sent)[start:] if t0 <= f[0] <= t1 and f[4] == 0]
    moves = [u for u in updates if t0 <= u <= t1]
    finish(viewer, stop, thread)
    sizes = sorted({(f[1], f[2]) for f in frames})
    return {'frames': len(frames), 'seconds': t1 - t0, 'fps': len(frames) / (t1 - t0),
            'camera_updates_per_second': len(moves) / (t1 - t0),
            'sizes': sizes, 'render_ms': 1000 * float(np.median([f[3] for f in frames]))
            if frames else None}


def moving_camera(run_dir, driver, seconds, rate=20):
    """Views sent per second while the camera of the open page turns about the scene, set from
    the server ``rate`` times a second (faster than the viewer renders: every view it renders
    is of a new camera; a browser with a GPU sends its camera at its frame rate): the rate the
    viewer renders moving views at, whatever the browser's own frame rate. Each camera set
    also makes the page redraw, which here is software WebGL on the same cores."""
    viewer, stop, thread = serve(run_dir)
    page = Page(driver)
    driver.get(viewer.url)
    wait_for(lambda: 'Add keyframe' in page.text(), 60, 'the page')
    wait_for(lambda: refined(viewer), 120, 'the refined view')
    time.sleep(1)
    (view,) = list(viewer.views.values())
    camera = view.client.camera
    center = np.array(camera.position)
    up = np.array(camera.up_direction)
    t0 = time.monotonic()
    start = len(viewer.sent)
    angle = 0.0
    while time.monotonic() - t0 < seconds:
        angle += 0.6 / rate
        rotation = Rotation.from_rotvec(angle * up / np.linalg.norm(up))
        with view.client.atomic():
            camera.position = rotation.apply(center)
            camera.look_at = (0.0, 0.0, 0.0)
        time.sleep(1 / rate)
    t1 = time.monotonic()
    frames = [f for f in list(viewer.sent)[start:] if t0 <= f[0] <= t1 and f[4] == 0]
    finish(viewer, stop, thread)
    return {'frames': len(frames), 'seconds': t1 - t0, 'fps': len(frames) / (t1 - t0),
            'sizes': sorted({(f[1], f[2]) for f in frames}),
            'render_ms': 1000 * float(np.median([f[3] for f in frames])) if frames else None}


class Clock(run.RunObserver):
    """The wall time of every step."""

    def __init__(self):
        self.times, self.rendered, self.viewer = [], [], None

    def step(self, trainer, loss, psnr):
        self.times.append(time.perf_counter())
        self.rendered.append(getattr(self.viewer, 'render_seconds', 0.0))


def train_round(data, steps, driver, view):
    """Training rays per second of wall time over the last half of ``steps`` steps (without or
    with the viewer open in the browser, its camera still: the page opened and showing its
    refined view before the measured steps)."""
    clock = Clock()
    settled = []
    observer = ViewerObserver(clock, port=free_port()) if view else clock
    clock.viewer = observer if view else None
    config = TrainConfig.from_options(iterations=steps, checkpoint_every=0, preview_every=0,
                                      eval_at=())
    out = tempfile.mkdtemp(prefix='viewer_bench_')
    inputs = run.prepare(data, config, out, observer=observer)
    try:
        trainer = run.start(inputs, observer=observer)
        if view:
            def open_page():
                viewer = observer.viewer
                driver.get(viewer.url)
                if os.environ.get('VIEWER_BENCH_DEBUG'):
                    print('page opened at step', len(clock.times), flush=True)
                wait_for(lambda: viewer.sent and viewer.sent[-1][4] >= 1, 300, 'the view')
                if os.environ.get('VIEWER_BENCH_DEBUG'):
                    print('settled at step', len(clock.times), list(viewer.sent), flush=True)
                time.sleep(2)
                settled.append(len(clock.times))
            threading.Thread(target=open_page, daemon=True).start()
        run.train(trainer, observer)
    finally:
        inputs.release()
        if view:
            observer.close()
            driver.get('about:blank')
        shutil.rmtree(out, ignore_errors=True)
    skip = int(0.5 * steps)
    if view:
        if not settled or settled[0] > skip:
            raise RuntimeError(f'the page was not open and settled before step {skip}: more '
                               f'--steps')
    times = clock.times[skip:]
    rays = (len(times) - 1) * config.schedule.batch_rays
    return {'rays_per_second': rays / (times[-1] - times[0]),
            'viewer_seconds': clock.rendered[-1] - clock.rendered[skip],
            'wall_seconds': times[-1] - times[0]}


def drawn_path(run_dir, driver, folder):
    """Cameras of a path drawn in the page: the preview's against video's."""
    viewer, stop, thread = serve(run_dir, max_width=640)
    page = Page(driver)
    driver.get(viewer.url)
    wait_for(lambda: 'Add keyframe' in page.text(), 60, 'the page')
    wait_for(lambda: viewer.sent, 60, 'the first frame')
    for label, value in (('Seconds', '1'), ('FPS', '12'), ('Width', '160'), ('Height', '90')):
        page.type(label, value)
    wait_for(lambda: viewer.height.value == 90, 10, 'the settings')
    for i in range(3):
        if i:
            page.drag(150, 10)
            time.sleep(2)
        page.click('Add keyframe')
        wait_for(lambda: len(viewer.path.keyframes) == i + 1, 20, 'a keyframe')
    target = os.path.join(folder, 'drawn.json')
    page.type('File', target)
    wait_for(lambda: viewer.file.value == target, 10, 'the file name')
    page.click('Save path')
    wait_for(lambda: os.path.exists(target), 20, 'the saved path')
    page.click('Play')
    count = len(viewer.path.frames)
    wait_for(lambda: viewer._playing is None and len(viewer.preview_cameras) >= 1, 120,
             'the preview')
    finish(viewer, stop, thread)
    path = read_path(target)
    norm = viewer.normalization
    video_cams = path_cameras(path, norm)
    preview = [norm.to_world_camera(c) for c in viewer.preview_cameras]
    out = os.path.join(folder, 'drawn.mp4')
    assert cli(['video', run_dir, '--path', target, '--exr', '-o', out]) == 0
    import OpenEXR
    worst_c2w = worst_fov = worst_header = worst_header_fov = 0.0
    video_world = [norm.to_world_camera(c) for c in video_cams]
    for cam in preview:
        # The preview camera of frame i is the path's frame i (the preview renders frames at a
        # smaller size: same c2w and field of view).
        index = int(np.argmin([np.abs(v.c2w - cam.c2w).max() for v in video_world]))
        v = video_world[index]
        worst_c2w = max(worst_c2w, float(np.abs(v.c2w - cam.c2w).max()))
        worst_fov = max(worst_fov, abs(v.fov_y - cam.fov_y))
        header = OpenEXR.File(os.path.join(folder, 'drawn_frames',
                                           f'frame_{index:05d}.exr')).header()
        w2c = np.array(header['worldToCamera'], dtype=np.float64).T
        c2w = np.linalg.inv(np.diag([1.0, -1, 1, 1]) @ w2c)
        worst_header = max(worst_header, float(np.abs(c2w - cam.c2w).max()))
        worst_header_fov = max(worst_header_fov, abs(float(header['fovY']) - cam.fov_y))
    return {'frames': count, 'previewed': len(preview),
            'c2w': worst_c2w, 'fov': worst_fov, 'header_c2w': worst_header,
            'header_fov': worst_header_fov}


def screenshot(run_dir, driver, path):
    viewer, stop, thread = serve(run_dir)
    page = Page(driver)
    driver.get(viewer.url)
    wait_for(lambda: 'Add keyframe' in page.text(), 60, 'the page')
    wait_for(lambda: refined(viewer), 60, 'a refined frame')
    from selenium.webdriver.common.by import By
    for button in driver.find_elements(By.CSS_SELECTOR, '.mantine-Notification-closeButton'):
        button.click()                  # the notice that the browser has no GPU
    time.sleep(3)
    driver.save_screenshot(path)
    finish(viewer, stop, thread)


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('run')
    ap.add_argument('--data', help="dataset of the training rounds (default: the run's)")
    ap.add_argument('--rounds', type=int, default=5)
    ap.add_argument('--steps', type=int, default=600)
    ap.add_argument('--drag', type=float, default=6.0, help='seconds of dragging')
    ap.add_argument('--screenshot', help='also save a screenshot of the page here')
    ap.add_argument('--name', default='viewer')
    a = ap.parse_args()
    data = a.data or read_meta(os.path.join(a.run, 'model.npz'))['dataset']
    driver = browser(960, 540)
    try:
        if a.screenshot:
            screenshot(a.run, driver, a.screenshot)
        first = first_frame(a.run, driver)
        print(f"first frame: on screen {first['visible']:.2f} s after opening the page "
              f"(connected {first['connected']:.2f} s, sent {first['sent']:.2f} s, render "
              f"{first['render']:.2f} s at {first['size'][0]}x{first['size'][1]})", flush=True)
        move = moving(a.run, driver, a.drag)
        print(f"moving: {move['fps']:.1f} frames/s ({move['frames']} frames in "
              f"{move['seconds']:.1f} s, sizes {move['sizes']}, median render "
              f"{move['render_ms']:.0f} ms; the page sent "
              f"{move['camera_updates_per_second']:.1f} camera updates/s)", flush=True)
        server_move = moving_camera(a.run, driver, a.drag)
        print(f"moving (camera set 20 times/s): {server_move['fps']:.1f} frames/s "
              f"({server_move['frames']} frames in {server_move['seconds']:.1f} s, sizes "
              f"{server_move['sizes']}, median render {server_move['render_ms']:.0f} ms)",
              flush=True)
        folder = tempfile.mkdtemp(prefix='viewer_path_')
        drawn = drawn_path(a.run, driver, folder)
        print(f"drawn path: {drawn['previewed']} preview frames of {drawn['frames']}; largest "
              f"difference to video's cameras: c2w {drawn['c2w']:.2e}, fov {drawn['fov']:.2e} "
              f"deg; to the EXR headers (float32): c2w {drawn['header_c2w']:.2e}, fov "
              f"{drawn['header_fov']:.2e} deg", flush=True)
        rounds = []
        if a.rounds:
            train_round(data, 30, driver, False)    # kernels compiled, dataset cached
        for r in range(a.rounds):
            order = (False, True) if r % 2 == 0 else (True, False)
            result = {}
            for view in order:
                result[view] = train_round(data, a.steps, driver, view)
            ratio = result[True]['rays_per_second'] / result[False]['rays_per_second']
            rounds.append((result[False], result[True], ratio))
            print(f"round {r + 1}: without the viewer {result[False]['rays_per_second']:,.0f} "
                  f"rays/s, with it {result[True]['rays_per_second']:,.0f} rays/s: "
                  f"{100 * ratio:.1f} % (viewer rendered {result[True]['viewer_seconds']:.2f} "
                  f"s of {result[True]['wall_seconds']:.1f} s)", flush=True)
    finally:
        driver.quit()
    ratio = float(np.median([r[2] for r in rounds])) if rounds else None
    if rounds:
        print(f'training with the viewer open: {100 * ratio:.1f} % of the rays/s without it '
              f'(median of {len(rounds)} rounds)')
    tables = [
        bench.table('Targets', ['target', 'wanted', 'measured', 'met'], [
            ['first frame on screen after opening the page (s)', '<= 3', first['visible'],
             'yes' if first['visible'] is not None and first['visible'] <= 3 else 'no'],
            ['frames/s at 320x180 while the camera moves (set 20 times/s)', '>= 5',
             server_move['fps'], 'yes' if server_move['fps'] >= 5 else 'no'],
            ['frames/s at 320x180 while the mouse drags in the page', '>= 5', move['fps'],
             'yes' if move['fps'] >= 5 else 'no'],
            ['training rays/s with the viewer open, camera still (% of without)', '>= 85',
             None if ratio is None else 100 * ratio,
             'not measured' if ratio is None else 'yes' if ratio >= 0.85 else 'no'],
            ['drawn path: preview vs video cameras, largest c2w / fov difference', '<= 1e-6',
             max(drawn['c2w'], drawn['fov']),
             'yes' if max(drawn['c2w'], drawn['fov']) <= 1e-6 else 'no']],
            note='Headless Chromium (software WebGL) runs on the same 2 cores as the viewer.'),
        bench.table('First frame (s after opening the page)',
                    ['page connected', 'first view sent', 'its render', 'on screen'],
                    [[first['connected'], first['sent'], first['render'], first['visible']]]),
        bench.table('Training side by side (rays/s of wall time)',
                    ['round', 'without the viewer', 'with it open', 'ratio',
                     'viewer render (s)', 'wall (s)'],
                    [[i + 1, r[0]['rays_per_second'], r[1]['rays_per_second'], r[2],
                      r[1]['viewer_seconds'], r[1]['wall_seconds']]
                     for i, r in enumerate(rounds)],
                    note=f'{a.steps} steps per run, rays/s over the last half (the page open and '
                         f'settled before them), the order swapped every round.'),
        bench.table('Drawn path: largest difference to the cameras video rendered',
                    ['preview frames', 'c2w (float64)', 'fov (deg, float64)',
                     'c2w (EXR header, float32)', 'fovY (EXR header, float32)'],
                    [[drawn['previewed'], drawn['c2w'], drawn['fov'], drawn['header_c2w'],
                      drawn['header_fov']]])]
    if not rounds:
        # A variant of its own: the benchmarks page keeps showing the last file with rounds.
        tables = [t for t in tables if not t['title'].startswith('Training side by side')]
    bench.write_results(
        a.name, 'The web viewer' + ('' if rounds else ' (no training rounds)'), tables,
        notes=f'Run {a.run}. Moving views with the camera set from the server 20 times a '
              f'second: {server_move["frames"]} in {server_move["seconds"]:.1f} s, median '
              f'render {server_move["render_ms"]:.0f} ms; with the mouse dragging in the page: '
              f'{move["frames"]} in {move["seconds"]:.1f} s, median render '
              f'{move["render_ms"]:.0f} ms, the page sending '
              f'{move["camera_updates_per_second"]:.1f} camera updates a second (its own frame '
              f'rate: software WebGL on the same two cores). The machine may have been doing '
              f'other work: the load average is in raw.',
        raw={'first': first, 'moving_camera': server_move, 'moving_drag': move, 'drawn': drawn,
             'load': os.getloadavg(), 'rounds': rounds},
        variant=None if rounds else 'no training rounds')


if __name__ == '__main__':
    main()
