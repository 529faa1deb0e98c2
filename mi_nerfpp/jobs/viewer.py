"""The browser viewer: a run's model rendered through the integrator from the user's camera, the
capture's cameras, a camera-path editor, and a training run's progress, on a local web page.

    python -m mi_nerfpp view RUN [--port 8080]        # a finished, interrupted or running run
    python optimize.py DATA --view                     # while training

The page is served by `viser <https://viser.studio>`_ (an optional extra: ``pip install
'mi-nerfpp[viewer]'``; its client is a prebuilt bundle inside the wheel); everything drawn in it
is viser's (frustums, lines, the GUI), and the model's image is a background image that
:class:`Viewer` renders with :class:`~mi_nerfpp.output.views.ViewRenderer` - the integrator
itself, as ``render`` and ``video`` use it.

Rendering is progressive: while the camera moves, each new view is rendered at
:data:`MOVING_WIDTH` pixels across with the coarse samples alone (:data:`MOVING_FINE_SAMPLES`
fine samples: the render is most of what a moving frame costs); once it has stood still for
:data:`SETTLE_SECONDS` it is rendered again at each width of :data:`REFINE_WIDTHS` up to the
canvas (at most ``max_width``) with the model's own samples, and a movement between two
refinements starts over. Nothing is rendered while nothing changes.

While training (:class:`ViewerObserver`) all of it runs in the training thread between two
steps, never beside a step, and takes at most a bounded share of the wall time: after a render
of ``c`` seconds the next waits until training has had ``c·(1 - share)/share`` seconds, with
``share`` :data:`MOVING_SHARE` while the user moves the camera (until the view where it stopped
is refined) and :data:`STILL_SHARE` while it stands still (then the view is only refreshed, as
the model changes, at most every :data:`REFRESH_SECONDS`). Pause (a button) stops training between two steps and leaves the
viewer all the time.

Viewing a run folder never takes its lock (:func:`mi_nerfpp.files.atomic.lock_folder`): the
viewer only reads ``model.npz`` (written atomically) and reloads it when a training process
replaces it.
"""
from __future__ import annotations

import contextlib
import io
import math
import os
import socket
import threading
import time
import warnings
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from mi_nerfpp.core.color import to_srgb8
from mi_nerfpp.data import Camera
from mi_nerfpp.files.atomic import as_text
from mi_nerfpp.files.checkpoint import load_checkpoint
from mi_nerfpp.files.preview import depth_to_png
from mi_nerfpp.files.readers import FileReadError, read_image, read_json
from mi_nerfpp.jobs.run import RunObserver, open_run
from mi_nerfpp.output.camera_path import (CameraPath, Pose, camera_pose,
                                          intrinsics, pose_camera, read_path,
                                          write_path)
from mi_nerfpp.output.video import BUILT_IN_PATHS, built_in_path
from mi_nerfpp.output.views import ViewRenderer, rgb
from mi_nerfpp.training.config import TrainConfig, stored_config

# The layers the viewer shows, by the name in its menu.
LAYERS = ('beauty', 'foreground', 'background', 'depth', 'alpha')
# The 'Appearance' menu's first entry: the model's own colour (no training photo's).
NEUTRAL = 'neutral'
# Pixels across of a view rendered while the camera moves, and of the refinements after it
# stands still (each at most the canvas's width and the viewer's max_width).
MOVING_WIDTH = 320
REFINE_WIDTHS = (640, 1280)
DEFAULT_MAX_WIDTH = 1280
# Rays the integrator renders at once for the viewer: a moving view (320x180) in one chunk, 15 %
# faster than in the integrator's default two (2026-11-27, default capture, 2 cores).
CHUNK_RAYS = 1 << 16
# Fine samples per ray and volume of a moving view (refinements use the model's own): without
# the fine pass a 320x180 view of the default run renders in 0.63-0.70 of the time, 31-38 dB
# PSNR (median 37) from the full render over 24 views, under the model's error (27 dB held
# out); 2026-11-27, 2 cores.
MOVING_FINE_SAMPLES = 0
# Seconds a camera must stand still before its view is refined, counted from its change and
# from when its moving view was sent (during a render camera updates wait for the interpreter,
# so a camera that seemed still through a render may not be): a refinement is not interrupted,
# so a pause in a drag shorter than this keeps the moving views coming.
SETTLE_SECONDS = 0.3
# While training: the largest share of wall time the viewer renders in while the user moves the
# camera (until the view they stopped at is refined) and while it stands still (refreshes as the
# model trains), and the fewest seconds between two refreshes of a still view.
MOVING_SHARE = 0.5
STILL_SHARE = 0.05
REFRESH_SECONDS = 2.0
# Seconds a camera counts as moving after its last change.
MOVING_SECONDS = 1.0
# Seconds between two checks for a new model.npz (view of a run being trained elsewhere) and
# between two updates of the training text.
RELOAD_SECONDS = 2.0
STATS_SECONDS = 1.0
# Frustums of the capture's cameras: size in the model frame (the cameras lie inside the unit
# sphere), thumbnail width in pixels, and colours (training, held out, keyframes).
FRUSTUM_SCALE = 0.05
THUMBNAIL_WIDTH = 64
TRAIN_COLOR = (120, 120, 120)
HELD_OUT_COLOR = (230, 120, 20)
KEYFRAME_COLOR = (40, 110, 230)
JPEG_QUALITY = 85


def require_viser():
    """The viser module, or a RuntimeError that says how to install it."""
    try:
        import viser  # deferred: the optional extra [viewer]
    except ImportError:
        raise RuntimeError("the viewer needs viser: pip install 'mi-nerfpp[viewer]' (or pip "
                           "install viser)") from None
    return viser


def check_port(host, port):
    """Refuse a port another program listens on (viser would take the next free one, and the
    URL the user was told would show something else)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host or '0.0.0.0', port))
        except OSError as e:
            raise OSError(e.errno, f'cannot serve the viewer on {host}:{port} ({e.strerror}): '
                          f'choose another --port') from None


# ------------------------------------------------------------------------------- cameras

def viewer_camera(position, wxyz, fov, aspect, width) -> Camera:
    """The model-frame camera of a viser view (``position``, orientation ``wxyz`` of the
    OpenCV camera-to-world, vertical ``fov`` in radians, canvas ``aspect`` = width / height)
    with an image ``width`` pixels across."""
    height = max(1, int(round(width / aspect)))
    c2w = np.eye(4)
    w, x, y, z = (float(v) for v in wxyz)
    c2w[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    c2w[:3, 3] = np.asarray(position, dtype=np.float64)
    return Camera(intrinsics(math.degrees(fov), width, height), c2w, width, height, 'viewer')


def wxyz_of(c2w) -> np.ndarray:
    """viser's orientation (w, x, y, z) of a camera-to-world matrix."""
    x, y, z, w = Rotation.from_matrix(np.asarray(c2w)[:3, :3]).as_quat()
    return np.array([w, x, y, z])


def capture_up(cameras) -> np.ndarray:
    """The capture's up direction: the mean of the cameras' up vectors (-y in OpenCV)."""
    up = -np.mean([c.c2w[:3, 1] for c in cameras], axis=0)
    norm = np.linalg.norm(up)
    return up / norm if norm > 0 else np.array([0.0, 0.0, 1.0])


def thumbnail(image, color_space, width=THUMBNAIL_WIDTH) -> np.ndarray:
    """An 8-bit sRGB thumbnail of a dataset image, about ``width`` pixels across."""
    image = np.asarray(image)
    step = max(1, image.shape[1] // width)
    return to_srgb8(image[::step, ::step], color_space)


def display(layers, layer: str) -> np.ndarray:
    """The 8-bit sRGB image of one layer of a render (``LAYERS``): the beauty, the foreground
    (premultiplied, over black), the background as seen through it, inverse depth in grey,
    the foreground's alpha in grey."""
    if layer == 'foreground':
        return to_srgb8(np.stack([layers[f'fg.{c}'] for c in 'RGB'], -1))
    if layer == 'background':
        return to_srgb8(np.stack([layers[f'bg.{c}'] for c in 'RGB'], -1))
    if layer == 'depth':
        return depth_to_png(layers['depth.Z'])
    if layer == 'alpha':
        a = np.round(np.clip(np.nan_to_num(layers['fg.A']), 0, 1) * 255).astype(np.uint8)
        return np.repeat(a[..., None], 3, axis=-1)
    return to_srgb8(rgb(layers))


def letterbox(image, aspect) -> np.ndarray:
    """``image`` padded with black to the canvas ``aspect`` (a path's frame shown in a canvas of
    another shape is shown whole, as the video will have it)."""
    h, w = image.shape[:2]
    if abs(w / h - aspect) < 1e-3:
        return image
    if w / h > aspect:          # wider than the canvas: bars above and below
        pad = int(round(w / aspect)) - h
        return np.pad(image, ((pad // 2, pad - pad // 2), (0, 0), (0, 0)))
    pad = int(round(h * aspect)) - w
    return np.pad(image, ((0, 0), (pad // 2, pad - pad // 2), (0, 0)))


def render_widths(canvas_width, max_width):
    """The widths of the progressive renders of a still view: :data:`MOVING_WIDTH`, then the
    refinements up to the canvas (at most ``max_width``)."""
    top = max(MOVING_WIDTH, min(int(canvas_width), int(max_width)))
    return [MOVING_WIDTH] + [w for w in REFINE_WIDTHS if MOVING_WIDTH < w < top] + \
        ([top] if top > MOVING_WIDTH else [])


# ------------------------------------------------------------------------------- state

@dataclass
class View:
    """What the viewer knows of one browser tab: its camera when it last changed, when that
    was, and what was rendered of it."""
    client: object
    key: tuple | None = None          # the camera (position, wxyz, fov, aspect) last seen
    changed: float = 0.0              # time.monotonic() of its last change
    stage: int = -1                   # the last progressive stage rendered of this camera
    model_version: int = -1           # the model version that render showed
    rendered_at: float = 0.0
    moving_sent: float = 0.0          # time.monotonic() when its first stage was sent
    layer: str = 'beauty'
    last_camera: Camera | None = None  # the camera of the last render (model frame)


@dataclass
class TrainingStats:
    """What the viewer shows of a run's training."""
    iteration: int = 0
    elapsed: float = 0.0
    batch_psnr: float = float('nan')
    rays_per_second: float = float('nan')
    # [(iteration, psnr, kind)]: kind 'all' (an evaluation of every held-out view) or 'preview'
    # (the preview view alone)
    held_out: list = field(default_factory=list)
    state: str = ''


class Viewer:
    """A viser server showing ``model`` (model frame), the cameras of ``splits`` (a dataset with
    ``train``, ``validation`` and ``test`` in the model frame) and a camera-path editor; for a
    run folder ``run_dir``. ``training``: a trainer drives it (:class:`ViewerObserver`: pause
    button, live statistics); otherwise :meth:`serve` does, and reloads ``RUN/model.npz`` when
    it changes. ``host``/``port``: where it listens (a busy port is refused)."""

    def __init__(self, model, splits, run_dir=None, host='127.0.0.1', port=8080,
                 training=False, max_width=DEFAULT_MAX_WIDTH, color_space='srgb'):
        viser = require_viser()
        # A page that closes while its view renders: the image is dropped, which viser says.
        warnings.filterwarnings('ignore', message='Queued a .* on a closed connection')
        self.model, self.splits, self.run_dir = model, splits, run_dir
        self.training, self.max_width = training, int(max_width)
        self.color_space = color_space
        self.normalization = model.normalization
        self.appearance_image = -1      # the training photo whose appearance is shown (-1: neutral)
        self._make_renderers(model)
        self.lock = threading.RLock()
        self.wake = threading.Event()
        self.views: dict[int, View] = {}
        self.model_version = 0
        self.paused = False
        self.stopped = False
        self.stats = TrainingStats()
        self.path = CameraPath()
        self.preview_cameras: list = []     # cameras the last path preview rendered (model frame)
        self.last_render_seconds = 0.0
        # What was sent to the pages, newest last: (time.monotonic() when sent, width, height,
        # seconds it took, stage); and the last image sent (the benchmark reads them).
        self.sent = deque(maxlen=4096)
        self.last_image = None
        self._stats_shown = self._status_shown = 0.0
        self._model_mtime = self._mtime()
        self._checked = time.monotonic()
        check_port(host, port)
        with contextlib.redirect_stdout(io.StringIO()):     # viser's banner: we print the URL
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port = self.server.get_port()
        self.host = host
        self._build_scene(splits, color_space)
        self._warm_up(splits.train.cameras[0])
        self._build_gui()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    # ------------------------------------------------------------------ set-up
    @property
    def url(self) -> str:
        host = '127.0.0.1' if self.host in ('0.0.0.0', '') else self.host
        return f'http://{host}:{self.port}'

    def _mtime(self):
        if self.run_dir is None:
            return None
        try:
            return os.stat(os.path.join(self.run_dir, 'model.npz')).st_mtime_ns
        except OSError:
            return None

    def _build_scene(self, splits, color_space):
        scene = self.server.scene
        train = splits.train.cameras
        up = capture_up(train)
        scene.set_up_direction(tuple(up))
        # The first view: from behind the first training camera and above the ring of cameras,
        # looking at the middle of the sphere (the cameras in front of it, not around it).
        first = train[0]
        outward = first.center - np.dot(first.center, up) * up
        outward = outward / np.linalg.norm(outward) if np.linalg.norm(outward) > 1e-6 else \
            -first.c2w[:3, 2]
        position = first.center + 0.9 * outward + 0.45 * up
        self.server.initial_camera.position = tuple(position)
        self.server.initial_camera.look_at = (0.0, 0.0, 0.0)
        self.server.initial_camera.up = tuple(up)
        self.server.initial_camera.fov = math.radians(max(first.fov_y, 50.0))
        self.server.initial_camera.near = 0.01
        self.frustums = []
        for name, split, color in (('train', splits.train, TRAIN_COLOR),
                                   ('validation', splits.validation, HELD_OUT_COLOR),
                                   ('test', splits.test, HELD_OUT_COLOR)):
            for i, cam in enumerate(split.cameras):
                image = thumbnail(split.images[i], color_space) if split.images is not None \
                    and len(split.images) > i else None
                handle = scene.add_camera_frustum(
                    f'/cameras/{name}/{i:04d}', fov=math.radians(cam.fov_y),
                    aspect=cam.width / cam.height, scale=FRUSTUM_SCALE, thickness=0.003,
                    color=color, image=image, format='jpeg', jpeg_quality=80,
                    wxyz=wxyz_of(cam.c2w), position=tuple(cam.center))
                handle.on_click(self._go_to(cam))
                self.frustums.append(handle)
        # The unit sphere: three great circles and the capture's horizon.
        segments = []
        t = np.linspace(0, 2 * np.pi, 97)
        e1 = np.cross(up, [1.0, 0, 0] if abs(up[0]) < 0.9 else [0, 1.0, 0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(up, e1)
        for a, b in ((e1, e2), (e1, up), (e2, up)):
            ring = np.cos(t)[:, None] * a + np.sin(t)[:, None] * b
            segments.append(np.stack([ring[:-1], ring[1:]], axis=1))
        self.sphere = scene.add_line_segments('/unit_sphere', np.concatenate(segments),
                                              colors=(90, 160, 90), thickness=1.5,
                                              thickness_units='screen')
        self.path_line = None
        self.key_handles = []

    def _make_renderers(self, model):
        """The renderers of ``model``: :attr:`renderer` with its own samples (refinements, and
        a view with no refinement to come) and :attr:`moving_renderer` for moving views
        (:data:`MOVING_FINE_SAMPLES`)."""
        image = self.appearance_image
        if image >= max(model.appearance_images, model.embedding_images):
            image = self.appearance_image = -1      # a reloaded model without that photo's
        self.renderer = ViewRenderer(model, chunk_rays=CHUNK_RAYS, appearance_image=image)
        sampling = replace(model.render_settings.sampling, fine_samples=MOVING_FINE_SAMPLES)
        self.moving_renderer = ViewRenderer(model, sampling=sampling, chunk_rays=CHUNK_RAYS,
                                            appearance_image=image)

    def appearance_choices(self) -> list[str]:
        """What the 'Appearance' menu offers: 'neutral', then each training photo that has an
        appearance of its own (``--appearance``, ``--appearance-embedding``) by its name."""
        n = max(self.model.appearance_images, self.model.embedding_images)
        names = [as_text(os.path.basename(p)) for p in self.splits.train.image_paths][:n]
        names += [f'photo {i}' for i in range(len(names), n)]
        return [NEUTRAL] + [f'{i}: {name}' for i, name in enumerate(names)]

    def show_appearance(self, choice: str):
        """Render with the appearance of a choice of :meth:`appearance_choices`."""
        image = -1 if choice == NEUTRAL else int(choice.split(':', 1)[0])
        with self.lock:
            self.appearance_image = image
            self._make_renderers(self.model)
        self._invalidate()

    def _warm_up(self, camera):
        """Render the first camera once at :data:`MOVING_WIDTH` with both renderers (the
        integrator's kernels loaded before the first page asks for a view)."""
        width = MOVING_WIDTH
        height = max(1, int(round(width * camera.height / camera.width)))
        for renderer in (self.moving_renderer, self.renderer):
            renderer.render(pose_camera(camera_pose(camera), width, height))

    def _go_to(self, cam):
        def go(event):
            client = event.client
            if client is None:
                return
            with client.atomic():
                client.camera.position = tuple(cam.center)
                client.camera.wxyz = wxyz_of(cam.c2w)
                client.camera.fov = math.radians(cam.fov_y)
        return go

    def _build_gui(self):
        gui = self.server.gui
        with gui.add_folder('View'):
            self.layer = gui.add_dropdown('Layer', LAYERS, initial_value='beauty')
            self.show_cameras = gui.add_checkbox('Cameras', True)
            self.show_sphere = gui.add_checkbox('Unit sphere', True)
            choices = self.appearance_choices()
            self.appearance = (gui.add_dropdown('Appearance', choices, initial_value=NEUTRAL)
                               if len(choices) > 1 else None)
            self.status = gui.add_markdown('waiting for the page')
        if self.appearance is not None:
            self.appearance.on_update(lambda _: self.show_appearance(self.appearance.value))
        self.layer.on_update(lambda _: self._invalidate())
        self.show_cameras.on_update(self._toggle_cameras)
        self.show_sphere.on_update(lambda e: setattr(self.sphere, 'visible',
                                                     self.show_sphere.value))
        with gui.add_folder('Training'):
            self.stats_text = gui.add_markdown('')
            self.psnr_plots, self._plot_folder = {}, None
            if self.training:
                self.pause = gui.add_button('Pause training')
                self.pause.on_click(lambda _: self._toggle_pause())
        self._plot_gui = gui
        with gui.add_folder('Camera path'):
            self.add_key = gui.add_button('Add keyframe')
            self.remove_key = gui.add_button('Remove last keyframe')
            self.clear_keys = gui.add_button('Clear keyframes')
            self.seconds = gui.add_number('Seconds', 4.0, min=0.1, step=0.1)
            self.fps = gui.add_number('FPS', 24, min=1, step=1)
            self.width = gui.add_number('Width', 640, min=16, step=1)
            self.height = gui.add_number('Height', 360, min=16, step=1)
            self.loop = gui.add_checkbox('Loop', False)
            self.preview = gui.add_checkbox('Preview', False)
            self.frame = gui.add_slider('Frame', min=0, max=1, step=1, initial_value=0)
            self.play = gui.add_button('Play')
            self.builtin = gui.add_dropdown('Built-in path', BUILT_IN_PATHS)
            self.load_builtin = gui.add_button('Load built-in path')
            default = os.path.join(self.run_dir, 'camera_path.json') if self.run_dir else \
                'camera_path.json'
            self.file = gui.add_text('File', default)
            self.save = gui.add_button('Save path')
            self.load = gui.add_button('Load path')
            self.path_status = gui.add_markdown('no keyframes')
        self.add_key.on_click(self._add_keyframe)
        self.remove_key.on_click(lambda _: self._edit_keys(lambda k: k[:-1]))
        self.clear_keys.on_click(lambda _: self._edit_keys(lambda k: []))
        for handle in (self.seconds, self.fps, self.width, self.height, self.loop):
            handle.on_update(lambda _: self._path_changed(resample=True))
        self.preview.on_update(lambda _: self._invalidate())
        self.frame.on_update(lambda _: self._invalidate() if self.preview.value else None)
        self.play.on_click(lambda _: setattr(self, '_playing', time.monotonic()))
        self.load_builtin.on_click(lambda _: self._load_builtin())
        self.save.on_click(lambda event: self._save_path(event))
        self.load.on_click(lambda event: self._load_path(event))
        self._playing = None
        self._loading = False

    def _toggle_cameras(self, _):
        for handle in self.frustums:
            handle.visible = self.show_cameras.value

    def _toggle_pause(self):
        self.paused = not self.paused
        self.pause.label = 'Resume training' if self.paused else 'Pause training'
        self.stats.state = 'paused' if self.paused else 'training'
        self.show_stats(force=True)
        self.wake.set()

    # ------------------------------------------------------------------ clients
    def _connect(self, client):
        with self.lock:
            view = View(client)
            self.views[client.client_id] = view
        client.camera.on_update(lambda cam: self._camera_moved(client.client_id))
        self.wake.set()

    def _disconnect(self, client):
        with self.lock:
            self.views.pop(client.client_id, None)

    def _camera_moved(self, client_id):
        self.wake.set()

    def _invalidate(self):
        with self.lock:
            for view in self.views.values():
                view.stage = -1
        self.wake.set()

    # ------------------------------------------------------------------ rendering
    def _camera_key(self, client):
        cam = client.camera
        try:
            return (tuple(np.round(cam.position, 9)), tuple(np.round(cam.wxyz, 9)),
                    round(float(cam.fov), 9), round(float(cam.aspect), 6),
                    int(cam.image_width))
        except (AssertionError, ZeroDivisionError):
            return None         # no camera message from this client yet

    def pending(self, now=None):
        """The view to render next and the width to render it at, or None: a view whose
        camera changed (at :data:`MOVING_WIDTH`), else a still view not refined yet, else (with
        a newer model) a view not refreshed for :data:`REFRESH_SECONDS`."""
        now = time.monotonic() if now is None else now
        refresh = None
        with self.lock:
            views = list(self.views.values())
        for view in views:
            key = self._camera_key(view.client)
            if key is None:
                continue
            layer = self.layer.value
            if self.preview.value:
                key = ('preview', self._frame_index(), len(self.path.frames), key[3], key[4])
            if key != view.key or layer != view.layer:
                if key != view.key:
                    view.changed = now
                view.key, view.layer, view.stage = key, layer, -1
            widths = render_widths(key[4], self.max_width)
            if view.stage < 0:
                return view, widths[0], 0
            if view.stage < len(widths) - 1 and \
                    now - max(view.changed, view.moving_sent) >= SETTLE_SECONDS:
                return view, widths[view.stage + 1], view.stage + 1
            if (view.model_version < self.model_version
                    and now - view.rendered_at >= REFRESH_SECONDS and refresh is None):
                refresh = (view, widths[view.stage], view.stage)
        return refresh

    def moving(self, now=None) -> bool:
        """Whether a user is moving a camera now, or waits for the refinements of the view
        they stopped at (or plays a path): the viewer's interactive share of the time while
        training."""
        now = time.monotonic() if now is None else now
        with self.lock:
            views = list(self.views.values())
        for view in views:
            if now - view.changed < MOVING_SECONDS:
                return True
            if view.key is not None and \
                    view.stage < len(render_widths(view.key[4], self.max_width)) - 1:
                return True
        return self._playing is not None

    def _frame_index(self):
        if not self.path.frames:
            return 0
        return int(min(max(self.frame.value, 0), len(self.path.frames) - 1))

    def work(self) -> float:
        """Render what is pending (:meth:`pending`), one render; the seconds it took (0: nothing
        to do)."""
        self._advance_playback()
        job = self.pending()
        if job is None:
            return 0.0
        view, width, stage = job
        t0 = time.perf_counter()
        client = view.client
        version = self.model_version
        # A moving view (stage 0 of a view refined later) without fine samples; the
        # refinements, and a view whose only stage is the first, with the model's.
        refined_later = len(render_widths(view.key[4], self.max_width)) > 1
        renderer = self.moving_renderer if stage == 0 and refined_later else self.renderer
        try:
            cam = client.camera
            if self.preview.value and self.path.frames:
                frame = self.path.frames[self._frame_index()]
                w, h = self.path.resolution
                height = max(1, int(round(width * h / w)))
                camera = pose_camera(frame, width, height, self.normalization)
                image = display(renderer.render(camera), view.layer)
                image = letterbox(image, cam.aspect)
                self.preview_cameras.append(camera)
            else:
                camera = viewer_camera(cam.position, cam.wxyz, cam.fov, cam.aspect, width)
                image = display(renderer.render(camera), view.layer)
            client.scene.set_background_image(image, format='jpeg', jpeg_quality=JPEG_QUALITY)
            client.flush()
        except (AssertionError, ZeroDivisionError):      # the page went away meanwhile
            return time.perf_counter() - t0
        seconds = time.perf_counter() - t0
        self.sent.append((time.monotonic(), camera.width, camera.height, seconds, stage))
        self.last_image = image
        view.stage, view.model_version = stage, version
        view.rendered_at, view.last_camera = time.monotonic(), camera
        if stage == 0:
            view.moving_sent = view.rendered_at
        self.last_render_seconds = seconds
        if stage > 0 or time.monotonic() - self._status_shown > STATS_SECONDS:
            # Not at every moving view: each update redraws the page's panel too.
            self._status_shown = time.monotonic()
            self.status.content = (f'{view.layer}, {camera.width}x{camera.height}: '
                                   f'{seconds * 1000:.0f} ms')
        return seconds

    def _advance_playback(self):
        if self._playing is None or not self.path.frames:
            self._playing = None
            return
        index = int((time.monotonic() - self._playing) * self.path.fps)
        if index >= len(self.path.frames):
            self._playing = None
            return
        if not self.preview.value:
            self.preview.value = True
        if self.frame.value != index:
            self.frame.value = index

    # ------------------------------------------------------------------ camera path
    def _current_pose(self, client) -> Pose:
        cam = client.camera
        camera = viewer_camera(cam.position, cam.wxyz, cam.fov, cam.aspect, 64)
        return camera_pose(camera, self.normalization)

    def _add_keyframe(self, event):
        client = event.client
        if client is None:
            return
        pose = self._current_pose(client)
        self._edit_keys(lambda keys: keys + [pose])

    def _edit_keys(self, edit):
        with self.lock:
            self.path.keyframes = edit(list(self.path.keyframes))
        self._path_changed(resample=True)

    def _path_settings(self):
        self.path.seconds = max(float(self.seconds.value), 0.1)
        self.path.fps = max(float(self.fps.value), 1.0)
        self.path.resolution = (max(int(self.width.value), 16), max(int(self.height.value), 16))
        self.path.loop = bool(self.loop.value)

    def _path_changed(self, resample):
        if self._loading:       # set_path shows a path's settings: its frames stay as they are
            return
        with self.lock:
            if resample:
                self._path_settings()
                self.path.resample()
            self._draw_path()
        self._invalidate()

    def _draw_path(self):
        scene = self.server.scene
        for handle in self.key_handles:
            handle.remove()
        self.key_handles = []
        if self.path_line is not None:
            self.path_line.remove()
            self.path_line = None
        norm = self.normalization
        w, h = self.path.resolution
        for i, key in enumerate(self.path.keyframes):
            cam = pose_camera(key, w, h, norm)
            self.key_handles.append(scene.add_camera_frustum(
                f'/path/key_{i:03d}', fov=math.radians(key.fov_y), aspect=w / h,
                scale=FRUSTUM_SCALE * 1.5, thickness=0.004, color=KEYFRAME_COLOR,
                wxyz=wxyz_of(cam.c2w), position=tuple(cam.center)))
        points = np.array([norm.to_model_point(f.c2w[:3, 3]) for f in self.path.frames])
        if len(points) > 1:
            self.path_line = scene.add_line_segments(
                '/path/line', np.stack([points[:-1], points[1:]], axis=1),
                colors=KEYFRAME_COLOR, thickness=2.0, thickness_units='screen')
        frames = len(self.path.frames)
        self.frame.max = max(frames - 1, 1)
        self.path_status.content = (f'{len(self.path.keyframes)} keyframes, {frames} frames of '
                                    f'{w}x{h} at {self.path.fps:g} fps')

    def set_path(self, path: CameraPath):
        """Show ``path`` in the editor (its keyframes and frames as they are)."""
        with self.lock:
            self._loading = True
            try:
                self.path = path
                self.seconds.value = round(path.seconds, 3)
                self.fps.value = path.fps
                self.width.value, self.height.value = path.resolution
                self.loop.value = path.loop
            finally:
                self._loading = False
            self._draw_path()
        self._invalidate()

    def _load_builtin(self):
        name = self.builtin.value
        try:
            path = built_in_path(name, self.splits, self.normalization,
                                 res=(int(self.width.value), int(self.height.value)),
                                 fps=float(self.fps.value))
        except ValueError as e:
            self.path_status.content = f'**{e}**'
            return
        self.set_path(path)

    def save_path(self, filename) -> str:
        """Write the editor's path to ``filename``; the command that renders it."""
        with self.lock:
            write_path(filename, self.path)
        run = self.run_dir or 'RUN'
        return f'python -m mi_nerfpp video {run} --path {filename}'

    def _save_path(self, event):
        if not self.path.frames:
            self.path_status.content = '**add keyframes first**'
            return
        try:
            command = self.save_path(self.file.value)
        except OSError as e:
            self.path_status.content = f'**cannot write {self.file.value}: {e.strerror}**'
            return
        self.path_status.content = f'saved {self.file.value}; render it with `{command}`'

    def _load_path(self, event):
        try:
            path = read_path(self.file.value)
        except (OSError, ValueError) as e:
            self.path_status.content = f'**{getattr(e, "strerror", None) or e}**'
            return
        self.set_path(path)

    # ------------------------------------------------------------------ training
    def model_updated(self):
        """The model changed (a training step, a reloaded checkpoint): still views are refreshed
        (at most every :data:`REFRESH_SECONDS`)."""
        self.model_version += 1

    def show_stats(self, force=False):
        now = time.monotonic()
        if not force and now - self._stats_shown < STATS_SECONDS:
            return
        self._stats_shown = now
        s = self.stats
        lines = [f'**{s.state or "model"}**, step {s.iteration}']
        if s.elapsed:
            lines.append(f'{s.elapsed / 60:.1f} min of training')
        if math.isfinite(s.rays_per_second):
            lines.append(f'{s.rays_per_second:,.0f} rays/s')
        if math.isfinite(s.batch_psnr):
            lines.append(f'batch PSNR {s.batch_psnr:.2f} dB')
        for kind, what in (('all', 'held-out PSNR'), ('preview', 'preview view PSNR')):
            points = [p for p in s.held_out if p[2] == kind]
            if points:
                lines.append(f'{what} {points[-1][1]:.2f} dB (step {points[-1][0]})')
        self.stats_text.content = '  \n'.join(lines)
        self._plot_held_out()

    def _plot_held_out(self):
        """One plot per kind of held-out point, PSNR against step (uPlot draws nothing of a
        series with gaps as viser sends them, so the kinds are not put on one x axis)."""
        for kind, label, color in (('all', 'all held-out views', 'orange'),
                                    ('preview', 'the preview view', 'steelblue')):
            points = [p for p in self.stats.held_out if p[2] == kind]
            if not points:
                continue
            data = (np.array([p[0] for p in points], dtype=np.float64),
                    np.array([p[1] for p in points], dtype=np.float64))
            if kind in self.psnr_plots:
                self.psnr_plots[kind].data = data
                continue
            if self._plot_folder is None:
                self._plot_folder = self._plot_gui.add_folder('Held-out PSNR (dB)')
            with self._plot_folder:
                self.psnr_plots[kind] = self._plot_gui.add_uplot(
                    data=data, series=({'label': 'step'},
                                       {'label': label, 'stroke': color, 'width': 2,
                                        'points': {'show': True}}),
                    scales={'x': {'time': False}}, aspect=2.0)

    def add_held_out(self, iteration, psnr, kind='all'):
        """A point of the held-out curve: ``kind`` 'all' (every held-out view) or 'preview'."""
        self.stats.held_out.append((int(iteration), float(psnr), kind))
        self.stats.held_out.sort()
        self.show_stats(force=True)

    def check_model_file(self):
        """Reload ``RUN/model.npz`` when a training process replaced it."""
        now = time.monotonic()
        if self.run_dir is None or now - self._checked < RELOAD_SECONDS:
            return False
        self._checked = now
        mtime = self._mtime()
        if mtime is None or mtime == self._model_mtime:
            return False
        try:
            path = os.path.join(self.run_dir, 'model.npz')
            model, meta, _ = load_checkpoint(path)
            stored_config(meta, path)
        except (OSError, ValueError):
            return False        # being replaced: next time
        self._model_mtime = mtime
        self.model = model
        self._make_renderers(model)
        self.model_updated()
        self.stats_from_meta(meta)
        return True

    def stats_from_meta(self, meta, metrics=None):
        """Training statistics of a checkpoint's metadata (a run trained elsewhere)."""
        s = self.stats
        s.iteration, s.elapsed = int(meta.get('iteration', 0)), float(meta.get('elapsed', 0))
        history = meta.get('history') or []
        if history:
            s.batch_psnr = float(history[-1][3])
        batch = TrainConfig.stored_options(meta.get('config') or {}).get('batch_rays')
        if batch and s.elapsed > 0:
            s.rays_per_second = s.iteration * batch / s.elapsed
        s.state = 'model.npz'
        if metrics and 'test' in metrics and metrics.get('iterations') == s.iteration:
            s.state = 'finished run'
        if metrics:
            for p in metrics.get('progress', []):
                s.held_out.append((int(p['iteration']), float(p['psnr']), 'all'))
            if 'test' in metrics:
                s.held_out.append((int(metrics.get('iterations', s.iteration)),
                                   float(metrics['test']['psnr']), 'all'))
            s.held_out.sort()
        self.show_stats(force=True)

    # ------------------------------------------------------------------ loops
    def serve(self, stop: threading.Event | None = None):
        """Render for the connected pages until ``stop`` is set or :meth:`close` (a
        KeyboardInterrupt goes to the caller)."""
        while not self.stopped and not (stop is not None and stop.is_set()):
            if self.work():
                continue
            self.check_model_file()
            self.wake.wait(0.05)
            self.wake.clear()

    def close(self):
        """Stop the server (idempotent)."""
        if not self.stopped:
            self.stopped = True
            with contextlib.redirect_stdout(io.StringIO()):     # viser's "Server stopped"
                self.server.stop()


def open_viewer(run_dir, host='127.0.0.1', port=8080, max_width=DEFAULT_MAX_WIDTH) -> Viewer:
    """A :class:`Viewer` of a run folder (finished, interrupted or being trained): its model,
    the cameras of its dataset, its statistics."""
    model, meta, _, splits = open_run(run_dir)
    viewer = Viewer(model, splits, run_dir, host, port, max_width=max_width,
                    color_space=splits.color_space)
    try:
        metrics = read_json(os.path.join(run_dir, 'metrics.json'), what='metrics file')
    except FileReadError:       # none yet (a run being trained), or damaged: not shown
        metrics = None
    viewer.stats_from_meta(meta, metrics)
    return viewer


# ------------------------------------------------------------------------------- training

class ViewerObserver(RunObserver):
    """Shows a training run in the viewer, and reports to ``inner`` (the terminal's observer)
    as well: the viewer starts with training (its URL is a notice) and renders between steps
    at a bounded share of the time (module docs); its pause button holds training between two
    steps. :meth:`close` stops it."""

    def __init__(self, inner: RunObserver | None = None, host='127.0.0.1', port=8080,
                 max_width=DEFAULT_MAX_WIDTH):
        self.inner = inner or RunObserver()
        self.shows_progress = self.inner.shows_progress
        self.host, self.port, self.max_width = host, port, max_width
        self.viewer: Viewer | None = None
        self._next = 0.0            # time.monotonic() before which the viewer waits
        self._window = []           # (time, iteration) of recent steps, for rays/s
        self.render_seconds = 0.0   # time spent rendering for the viewer

    def notice(self, text):
        self.inner.notice(text)

    def planned(self, plan):
        self.inner.planned(plan)

    def track(self, iterable, desc='', unit='it', leave=True):
        return self.inner.track(iterable, desc=desc, unit=unit, leave=leave)

    def started(self, trainer, inputs):
        require_viser()
        splits = _Splits(trainer.train, trainer.validation, trainer.test,
                         inputs.dataset.color_space)
        self.viewer = Viewer(trainer.model, splits, trainer.out, self.host, self.port,
                             training=True, max_width=self.max_width,
                             color_space=splits.color_space)
        self.viewer.stats.state = 'training'
        self.batch = trainer.cfg.schedule.batch_rays
        self.inner.notice(f'viewer: {self.viewer.url} (open it in a browser)')
        self.inner.started(trainer, inputs)

    def step(self, trainer, loss, psnr):
        self.inner.step(trainer, loss, psnr)
        viewer = self.viewer
        if viewer is None:
            return
        now = time.monotonic()
        self._window.append((now, trainer.iteration))
        while len(self._window) > 2 and now - self._window[0][0] > 5.0:
            self._window.pop(0)
        s = viewer.stats
        s.iteration, s.elapsed, s.batch_psnr = trainer.iteration, trainer.elapsed, psnr
        (t0, i0), (t1, i1) = self._window[0], self._window[-1]
        if t1 > t0:
            s.rays_per_second = (i1 - i0) * self.batch / (t1 - t0)
        viewer.model_updated()
        viewer.show_stats()
        self.between_steps()
        while viewer.paused and not viewer.stopped:      # Ctrl-C still ends training
            t0 = time.perf_counter()
            if not viewer.work():
                viewer.wake.wait(0.05)
                viewer.wake.clear()
            self.render_seconds += time.perf_counter() - t0
            self._window.clear()

    def between_steps(self):
        """Render for the viewer if its share of the time allows (module docs)."""
        viewer = self.viewer
        now = time.monotonic()
        if now < self._next:
            return
        share = MOVING_SHARE if viewer.moving(now) else STILL_SHARE
        t0 = time.perf_counter()
        spent = viewer.work()
        if spent:
            spent = time.perf_counter() - t0
            self.render_seconds += spent
            self._next = time.monotonic() + spent * (1 - share) / share

    def evaluated(self, point):
        self.inner.evaluated(point)
        if self.viewer is not None:
            self.viewer.add_held_out(point['iteration'], point['psnr'], 'all')

    def preview(self, trainer, path):
        """A held-out preview was written: its PSNR against its photo is a point of the
        held-out curve (one view, between the evaluations of all of them)."""
        self.inner.preview(trainer, path)
        held_out = trainer.validation if len(trainer.validation) else trainer.test
        if self.viewer is None or not len(held_out):
            return
        shown = read_image(path, what='preview', remedy=None)[..., :3].astype(np.float64) / 255
        photo = to_srgb8(held_out.images[0], self.viewer.color_space).astype(np.float64) / 255
        if shown.shape == photo.shape:
            mse = float(np.mean((shown - photo) ** 2))
            self.viewer.add_held_out(trainer.iteration, -10 * math.log10(max(mse, 1e-10)),
                                     'preview')

    def trained(self, trainer, finished):
        self.inner.trained(trainer, finished)
        if self.viewer is not None:
            self.viewer.stats.state = {True: 'finished', False: 'interrupted',
                                       None: 'failed'}[finished]
            self.viewer.show_stats(force=True)

    def close(self):
        if self.viewer is not None:
            self.viewer.close()


@dataclass
class _Splits:
    train: object
    validation: object
    test: object
    color_space: str = 'srgb'

