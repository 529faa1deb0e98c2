"""Helpers of the tests: tiny models and scenes that render in milliseconds, small captures.

Imported as ``from tests.helpers import ...``; the fixtures built on them are in conftest.py.
"""
import contextlib
import os
import shutil

import mi_nerfpp  # noqa: F401  (libLLVM, variant, plugin registration)
import drjit as dr
import mitsuba as mi
import numpy as np

from mi_nerfpp.core.model import NeRFPPModel

# Optimize options of a run that trains in seconds (for the commands that read a run). Every
# grid level dense (``--grid-sparse`` alone), as runs of before the finest level moved into
# bricks: the checkpoint tests turn its files into older versions' (the default's bricks are
# trained end to end in tests/jobs/test_run.py and tests/jobs/test_capture_choices.py).
TINY_RUN = ['--iterations', '5', '--batch-rays', '256', '--samples', '8', '8', '8',
            '--checkpoint-every', '0', '--preview-every', '0', '--grid-sparse']

TINY_GRID = dict(kind='grid', resolutions=[4, 8], channels=3, hidden=8, dir_octaves=1)


class AnalyticField:
    """A closed-form field with the interface of :class:`mi_nerfpp.core.fields.Field`: ``sigma`` and
    ``rgb`` are constants or functions of the field inputs ``x`` (the point for the foreground,
    ``(x̂, s)`` for the background; ``rgb`` returns a Color3f or three Floats). ``shaded``
    counts the samples whose colour was evaluated; with ``record=True``, ``shaded_x`` keeps
    their first input (NumPy: not inside symbolic loops)."""

    params = {}
    config = {'kind': 'analytic'}

    def __init__(self, sigma, rgb, record=False):
        self.sigma, self.rgb, self.record = sigma, rgb, record
        self.shaded, self.shaded_x = 0, []

    def density(self, x):
        if callable(self.sigma):
            return self.sigma(x)
        return dr.full(mi.Float, self.sigma, dr.width(x[0]))

    def __call__(self, x, d, ray):
        n = dr.width(x[0])
        self.shaded += n
        if self.record:
            self.shaded_x.append(np.array(x[0]))
        rgb = self.rgb(x) if callable(self.rgb) else [dr.full(mi.Float, c, n) for c in self.rgb]
        return self.density(x), rgb if isinstance(rgb, mi.Color3f) else mi.Color3f(*rgb)


def blender_python() -> str:
    """The Python of Blender 4.2 as a module (pip bpy in .venv-bpy: Debian's Blender has no USD
    importer); the calling test fails, saying how to install it, where there is none."""
    import pytest
    python = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                          '.venv-bpy', 'bin', 'python')
    if not os.path.exists(python):
        pytest.fail('bpy 4.2 is not installed: run scripts/setup.sh --test (it makes .venv-bpy)')
    return python


def debian_blender() -> str:
    """Debian's Blender (3.4, the command ``blender``; scripts/setup.sh --test installs it, with
    its bundled add-ons such as Nuke .chan); the calling test fails, saying how to install it,
    where there is none, or skips where ``MI_NERFPP_NO_BLENDER`` is set."""
    import pytest
    blender = shutil.which('blender')
    if blender is None:
        if os.environ.get('MI_NERFPP_NO_BLENDER'):
            pytest.skip('blender not installed and MI_NERFPP_NO_BLENDER is set')
        pytest.fail('blender is not installed: run scripts/setup.sh --test (apt package blender), or '
                    'set MI_NERFPP_NO_BLENDER=1 to skip this check')
    return blender


def field_inputs(domain, n=256, seed=1):
    """Random field inputs of ``domain``: points in the ball, or (x̂, s) of the background."""
    rng = np.random.default_rng(seed)
    if domain == 'ball':
        return [mi.Float(v) for v in rng.uniform(-0.7, 0.7, (3, n)).astype(np.float32)]
    x = rng.normal(size=(3, n))
    x /= np.linalg.norm(x, axis=0)
    s = rng.uniform(0.05, 1.0, n)
    return [mi.Float(v.astype(np.float32)) for v in (*x, s)]


def tiny_model(seed=0, background=True):
    return NeRFPPModel.create(seed=seed, background=background,
                              fg_config=dict(TINY_GRID, domain='ball'),
                              bg_config=dict(TINY_GRID, domain='inverted_sphere'))


def scene_dict(width=8, height=6, origin=(0.1, 0.2, 0.6), target=(0, 0, 0), spp=1, near_clip=0.01,
               jitter=True, **integrator):
    """A nerfpp scene; ``jitter=False`` puts every ray through its pixel centre."""
    return {
        'type': 'scene',
        'integrator': dict({'type': 'nerfpp', 'fg_samples': 8, 'bg_samples': 8,
                            'fine_samples': 8}, **integrator),
        'sensor': {
            'type': 'perspective', 'fov': 60, 'near_clip': near_clip,
            'to_world': mi.ScalarTransform4f().look_at(origin=origin, target=target, up=[0, 1, 0]),
            'sampler': {'type': 'stratified', 'sample_count': spp, 'jitter': jitter},
            'film': {'type': 'hdrfilm', 'width': width, 'height': height,
                     'rfilter': {'type': 'box'}, 'pixel_format': 'rgba'},
        },
    }


def orbit_camera(angle, elevation, radius, width, height, focal=0.9):
    """An OpenCV camera on a circle around the origin, looking at it."""
    import numpy as np
    from mi_nerfpp.data import Camera
    c = radius * np.array([np.cos(angle) * np.cos(elevation), np.sin(elevation),
                           np.sin(angle) * np.cos(elevation)])
    z = -c / np.linalg.norm(c)
    x = np.cross(z, [0.0, -1.0, 0.0])
    x /= np.linalg.norm(x)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    c2w[:3, 3] = c
    f = focal * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    return Camera(K, c2w, width, height)


def make_capture(root, views=24, width=32, height=24, spp=8):
    """Render a small unbounded capture (textured ball, ground, far cube, sky) in the NeRF++ layout.

    Cameras orbit at radius 3 world units, so the reader normalizes them into the unit sphere.
    Every 6th view is held out for test, the one after it for validation. A ``capture.json``
    says, as ``synth``'s does, that the capture was rendered (one exposure, exact poses: runs on
    it learn no per-photo appearance and refine no poses unless told,
    :func:`mi_nerfpp.training.choices.choose_for_photos`).
    """
    import json
    import numpy as np
    from mi_nerfpp.data import mitsuba_sensor_dict, write_nerfpp
    from mi_nerfpp.core.color import to_srgb8
    scene = mi.load_dict({
        'type': 'scene', 'integrator': {'type': 'path', 'max_depth': 3},
        'sky': {'type': 'constant', 'radiance': {'type': 'rgb', 'value': [0.6, 0.7, 0.9]}},
        'ball': {'type': 'sphere', 'radius': 0.8, 'bsdf': {'type': 'diffuse', 'reflectance': {
            'type': 'checkerboard', 'to_uv': mi.ScalarTransform4f().scale([4, 4, 1])}}},
        'ground': {'type': 'rectangle',
                   'to_world': mi.ScalarTransform4f().translate([0, -1, 0]).rotate([1, 0, 0], -90)
                   .scale(30),
                   'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': [0.5, 0.4, 0.2]}}},
        'far': {'type': 'cube', 'to_world': mi.ScalarTransform4f().translate([8, 1, -6]).scale(2),
                'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': [0.8, 0.1, 0.1]}}},
    })
    rng = np.random.default_rng(0)
    cams, imgs = [], []
    for i in range(views):
        cam = orbit_camera(2 * np.pi * i / views, rng.uniform(0.1, 0.4), 3.0, width, height)
        img = np.array(mi.render(scene, sensor=mi.load_dict(mitsuba_sensor_dict(cam, spp=spp))))
        cams.append(cam)
        imgs.append(to_srgb8(img[..., :3], 'linear').astype(np.float32) / 255)
    idx = np.arange(views)
    test, val = idx[::6], idx[1::6]
    train = np.setdiff1d(idx, np.concatenate([test, val]))
    write_nerfpp(root, {name: ([cams[i] for i in ids], [imgs[i] for i in ids])
                        for name, ids in (('train', train), ('validation', val), ('test', test))})
    from mi_nerfpp.data.synth import CAPTURE_FILE, CAPTURE_FORMAT
    with open(os.path.join(root, CAPTURE_FILE), 'w') as f:
        json.dump({'format': CAPTURE_FORMAT, 'rendered_by': 'tests.helpers.make_capture'}, f)
    return root


TRUCK_FIXTURE = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'data', 'fixtures',
                             'truck_cams_subset.json')


def truck_fixture_cameras():
    """Five cameras of the NeRF++ Truck release (already normalized into the unit sphere)."""
    import json

    import numpy as np
    from mi_nerfpp.data import Camera
    with open(TRUCK_FIXTURE) as f:
        cam_dict = json.load(f)
    result = []
    for name, entry in sorted(cam_dict.items()):
        K = np.array(entry['K']).reshape(4, 4)[:3, :3]
        w2c = np.array(entry['W2C']).reshape(4, 4)
        width, height = entry['img_size']
        result.append(Camera(K=K, c2w=np.linalg.inv(w2c), width=width, height=height, name=name))
    return result


@contextlib.contextmanager
def one_thread():
    """Dr.Jit's LLVM backend on one thread inside the block. The reverse of every gather is a
    scatter-add whose float additions run in thread order, so with the default thread pool two
    runs of the same training steps differ in the last bits, and Adam's normalization grows
    that into visible updates on cells that get no other gradient. On one thread two runs agree
    bit for bit, so a resumed run can be compared exactly with a straight one."""
    threads = dr.thread_count()
    dr.set_thread_count(1)
    try:
        yield
    finally:
        dr.set_thread_count(threads)


def straight_and_resumed(dataset, tmp_path, config, stop_at):
    """Train ``config`` straight in ``tmp_path/a``, and in ``tmp_path/b`` interrupted after step
    ``stop_at`` and resumed (:func:`interrupted_then_resumed`), both on one thread (see
    :func:`one_thread`); returns the two Trainers."""
    from mi_nerfpp.training.train import Trainer
    with one_thread():
        straight = Trainer(dataset, str(tmp_path / 'a'), config)
        straight.run()
        resumed = interrupted_then_resumed(dataset, str(tmp_path / 'b'), config, stop_at)
    return straight, resumed


def interrupted_then_resumed(dataset, out, config, stop_at):
    """Train ``config`` in ``out``, interrupted after step ``stop_at`` as by Ctrl-C, then resume
    it in a new Trainer to the end; returns that Trainer."""
    from mi_nerfpp.training.train import Trainer

    def interrupt(trainer, loss, psnr):
        if trainer.iteration == stop_at:
            raise KeyboardInterrupt

    assert Trainer(dataset, out, config).run(on_step=interrupt) is False
    resumed = Trainer(dataset, out, config, resume=True)
    assert resumed.iteration == stop_at
    resumed.run()
    return resumed


def per_image_parameters_resume_exactly(dataset, tmp_path, exact, plain, name, flag):
    """Train ``exact`` (TrainConfig options with a per-image parameter ``name``, e.g.
    ``'poses'``) 10 steps straight, and again interrupted at step 5 and resumed, on one thread
    (:func:`straight_and_resumed`): the checkpoint holds the parameter and its Adam state, the
    resumed run ends bit for bit where the straight one did, and resuming with ``plain``
    options is refused naming ``flag``. Returns the parameter as saved."""
    import numpy as np
    import pytest

    from mi_nerfpp.files.checkpoint import load_checkpoint
    from mi_nerfpp.training.config import TrainConfig
    from mi_nerfpp.training.train import Trainer
    straight, resumed = straight_and_resumed(dataset, tmp_path,
                                             TrainConfig.from_options(iterations=10, **exact),
                                             stop_at=5)
    model, _, state = load_checkpoint(tmp_path / 'a' / 'model.npz')
    saved = getattr(model, name).numpy()
    np.testing.assert_array_equal(saved, getattr(straight.model, name).numpy())
    assert saved.shape[0] == len(dataset.train) and f'adam.m/{name}' in state
    np.testing.assert_array_equal(getattr(resumed.model, name).numpy(), saved)
    with pytest.raises(Exception, match=flag):
        Trainer(dataset, str(tmp_path / 'b'), TrainConfig.from_options(iterations=12, **plain),
                resume=True)
    return saved
