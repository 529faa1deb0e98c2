"""Synthetic captures: render posed images of a Mitsuba ground-truth scene in the NeRF++ layout.

``python -m mi_nerfpp synth SCENE.xml --out DATA`` (or :func:`synthesize`) places ``views``
pinhole cameras around the scene (see *Trajectories*), renders each with the scene's own
integrator, and writes::

    DATA/capture.json                   what was rendered, and how (see *capture.json*)
    DATA/{train,validation,test}/
        rgb/NNNNNN.png                  the render, linear RGB encoded as 8-bit sRGB (clipped)
        pose/NNNNNN.txt                 camera-to-world, OpenCV, in WORLD units of the scene
        intrinsics/NNNNNN.txt           K (top-left 3x3 of a 4x4 matrix)
        gt/NNNNNN.exr                   ground-truth layers (see *Ground truth*)

``mi_nerfpp.data.load_dataset(DATA)`` reads it like any NeRF++ dataset and normalizes the cameras
into the unit sphere itself (``gt/`` is ignored by the reader).

Trajectories
------------
``orbit``
    ``views`` cameras on a jittered band around the origin: azimuth evenly spaced (jittered by up
    to 0.3 of the spacing), elevation 5-35 degrees (a low-discrepancy sequence plus jitter),
    distance ``radius`` +-10 %, looking at the origin jittered by ~0.08 world units, up = +Y, no
    roll. Horizontal field of view ``fov`` degrees, square pixels, principal point at the image
    centre. In the ground-truth scenes (``mi_nerfpp/scenes/gt_*.xml``) every object between 1 and 5 units
    from the origin stays below y = 0 (the cameras' lowest height is ~0.1), so cameras of every
    trajectory with ``radius`` 3-4 are outside every object (checked at the default radius: every
    camera is >= 0.5 units from the nearest surface).
``truck``
    The real camera poses of the Tanks and Temples "Truck" capture as released with NeRF++
    (package data in ``mi_nerfpp/trajectories/``, BSD-2): train from its 226 train cameras,
    test from its 25 test cameras, validation from its 200 camera-path cameras, each subsampled
    (one random camera per equal stretch of the sequence). The poses are placed in the scene
    with one similarity transform computed from the train cameras: their mean up direction
    (minus the mean image-down axis) is rotated onto +Y, the point closest to all optical axes
    moves to the origin, and the scale makes the median horizontal distance of the train
    cameras from it ``radius`` (default 3.5, a factor of ~5.3; cameras then lie 1.9-4.6 units
    out horizontally and 0.1-1.1 above the origin, looking down by ~10 degrees). ``K`` is
    resampled to the requested resolution keeping the horizontal field of view (80 degrees)
    and the relative principal point; with square pixels, an aspect ratio other than the
    original 980:546 changes the vertical field of view. ``fov`` is ignored.
``hemisphere``
    ``views`` cameras at random on the upper hemisphere (for the shape-radiance ambiguity
    experiment of NeRF++ §3): azimuth uniform in [0, 360) degrees, elevation between 5 and 75
    degrees distributed so that the cameras are uniform over that band of the sphere's area
    (sin(elevation) uniform in [sin 5, sin 75]), distance exactly ``radius``, looking exactly at
    the origin, up = +Y, no roll. ``fov`` and ``K`` as for ``orbit``. The held-out views are a
    random subset of the cameras.
``arc``
    A DTU-like arc in front of the object (+Z side; for NeRF++ §3's interpolation versus
    extrapolation test), distance exactly ``radius``, looking exactly at the origin, up = +Y,
    no roll, ``fov`` and ``K`` as for ``orbit``. Azimuth is measured from +Z towards +X.
    *train*: azimuth evenly spaced from -50 to +50 degrees (jittered by up to 0.3 of the
    spacing, clipped to that range; a single train view sits at 0), elevation 10-40 degrees (a
    low-discrepancy sequence plus jitter). *validation* holds **interpolated** views: azimuth and
    elevation uniform at random inside the training ranges (|azimuth| <= 50, elevation 10-40).
    *test* holds **extrapolated** views: |azimuth| uniform in [65, 90] degrees, on alternating
    sides (+, -, +, ...), elevation uniform in 10-40 degrees. Needs ``views >= 3``. Cameras
    are named ``arc_NNN`` numbered through train, then validation, then test.

Splits: with ``views >= 3``, validation and test get ``max(1, round(0.1 * views))`` views each
and train the rest (80/10/10); 2 views are 1 train + 1 test, 1 view is train only (``arc``
refuses fewer than 3 views: it needs one view of each split). For ``orbit`` the held-out views
are spread around the ring (one random view per equal stretch of azimuth); for ``hemisphere``
they are a random subset; for ``arc`` they are the views described above.
Everything is deterministic for a given ``seed`` (which also seeds Mitsuba's sampler, per view).

Ground truth
------------
``gt/NNNNNN.exr`` (read with :func:`mi_nerfpp.exr.read_exr`). ``depth.Z`` and ``fg.A`` come from
one ray per pixel through the pixel centre (Mitsuba's ``aov`` integrator with a non-jittered
1-spp ``stratified`` sampler):

==========  ===================================================================================
``R G B``   the beauty render, linear RGB, float32, not clipped (the PNG's ``spp`` samples)
``depth.Z`` distance along the ray from the camera centre to the first surface hit, world units
            (the ``depth`` AOV plus the near-clip offset that Mitsuba's perspective sensor
            starts its rays at); 0 where the ray hits nothing (the environment at infinity)
``fg.A``    1 where the first surface hit lies inside the sphere that NeRF++'s normalization
            maps to the unit sphere (the foreground volume; centre and world radius in
            ``capture.json``), else 0 (a background surface, or no hit)
==========  ===================================================================================

``fg.A`` is a binary per-pixel mask of *where the visible surface is*, not NeRF++'s foreground
opacity: it is not antialiased, and the light arriving at a foreground surface still depends on
the background (shadows, reflections). Not produced: separate foreground/background radiance
(light transport does not split that way), opacity or depth integrated over the pixel footprint,
normals, and anything for refracted paths.

capture.json
------------
``scene`` (the XML path as given), ``scene_path`` (absolute), ``scene_sha256``, ``trajectory``,
``views`` per split and the source camera ``names``, ``resolution`` [W, H], ``spp``, ``seed``,
``fov``, ``radius``, ``layers`` (what the files hold), ``normalization`` (``center``,
``scale``: ``x_normalized = (x_world - center) * scale``, and ``world_radius = 1/scale``, the
foreground sphere of ``fg.A``), the Mitsuba and Dr.Jit versions and variant, ``params`` (what
the cache compares), the render time, and ``complete`` (false while rendering).

Caching: when ``DATA/capture.json`` is complete, its parameters (scene file contents, trajectory,
views, resolution, spp, seed, fov, radius, Mitsuba version and variant) equal the requested ones
and every file it lists exists, nothing is rendered. Files the XML references (textures,
environment maps) are not hashed: delete ``capture.json`` after changing them. Otherwise an
earlier capture in ``DATA`` (one with a ``capture.json``) is replaced: its split folders are
removed. A non-empty ``DATA`` without ``capture.json`` is refused.

Rendering speed: the scene is loaded once; each view gets its own sensor from
:func:`mi_nerfpp.data.mitsuba_sensor_dict` passed as ``sensor=`` to ``mi.render``. Updating one
sensor's ``to_world`` through ``mi.traverse`` measured the same (0.37 s per 128x96 view at 64 spp
on 2 CPU cores, both ways: the kernel is reused), so the simpler form is used.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from importlib import resources

import numpy as np

from .data.cameras import (
    Camera,
    mitsuba_sensor_dict,
    pixel_rays,
)
from .data.dataset import SPLITS
from .data.nerfpp import write_nerfpp
from .exr import write_exr
from .files import atomic_write_path
from .frame import MITSUBA_NEAR_CLIP, Normalization
from .color import srgb_eotf, to_srgb8

TRAJECTORIES = ('orbit', 'truck', 'hemisphere', 'arc')
CAPTURE_FILE = 'capture.json'
CAPTURE_FORMAT = 'mi-nerfpp-synth'
CAPTURE_VERSION = 1

# The default capture (the ``synth`` command's defaults and the embedded default of ``optimize``).
DEFAULT_SCENE = 'gt_garden.xml'
DEFAULT_TRAJECTORY = 'orbit'
DEFAULT_VIEWS = 60
DEFAULT_RES = (128, 96)
DEFAULT_SPP = 64
DEFAULT_SEED = 0
DEFAULT_FOV = 50.0
DEFAULT_RADIUS = 3.5

ORBIT_ELEVATION = (5.0, 35.0)      # degrees
ORBIT_RADIUS_JITTER = 0.1          # relative
ORBIT_AZIMUTH_JITTER = 0.3         # of the azimuth spacing
ORBIT_TARGET_JITTER = 0.08         # world units (standard deviation; half of it vertically)
HEMISPHERE_ELEVATION = (5.0, 75.0)  # degrees; uniform over the sphere's area in between
ARC_AZIMUTH = 50.0                 # degrees: train and validation azimuth in [-50, 50]
ARC_ELEVATION = (10.0, 40.0)       # degrees, all splits
ARC_EXTRAPOLATION = (65.0, 90.0)   # degrees of |azimuth|, test views
ARC_AZIMUTH_JITTER = 0.3           # of the train azimuth spacing
HELD_OUT_FRACTION = 0.1            # of the views, each for validation and test

TRUCK_FILES = {'train': 'train_cam_dict_norm.json',
               'validation': 'camera_path_cam_dict_norm.json',
               'test': 'test_cam_dict_norm.json'}


# --- parameters --------------------------------------------------------------------------------

def parse_res(value) -> tuple[int, int]:
    """``'WxH'`` (or a ``(W, H)`` pair) -> ``(W, H)`` positive integers.

    Raises:
        ValueError: anything else, with the expected form in the message.
    """
    if isinstance(value, str):
        parts = value.lower().split('x')
        try:
            if len(parts) != 2:
                raise ValueError
            width, height = int(parts[0]), int(parts[1])
        except ValueError:
            raise ValueError(f"resolution must be WxH with positive integers, e.g. 128x96, "
                             f"got '{value}'") from None
    else:
        try:
            width, height = value
        except (TypeError, ValueError):
            raise ValueError(f'resolution must be WxH or a (width, height) pair, '
                             f'got {value!r}') from None
        if int(width) != width or int(height) != height:
            raise ValueError(f'resolution must be integers, got {value!r}')
        width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise ValueError(f'resolution must be positive, got {width}x{height}')
    return width, height


def split_counts(views: int) -> dict[str, int]:
    """Number of views per split: 80/10/10 with at least one validation and test view."""
    if views >= 3:
        held = max(1, round(HELD_OUT_FRACTION * views))
        return {'train': views - 2 * held, 'validation': held, 'test': held}
    return {'train': 1, 'validation': 0, 'test': views - 1}


def _stratified_choice(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    """``k`` sorted distinct indices of ``range(n)``: one random index in each of ``k`` equal
    stretches, so that the choice covers the whole sequence."""
    if k <= 0:
        return np.zeros(0, dtype=int)
    edges = np.floor(np.linspace(0, n, k + 1)).astype(int)
    return np.array([rng.integers(lo, hi) for lo, hi in zip(edges[:-1], edges[1:])])


# --- trajectories ------------------------------------------------------------------------------

def intrinsics_from_fov(fov: float, width: int, height: int) -> np.ndarray:
    """Pinhole K with horizontal field of view ``fov`` degrees, square pixels, centred."""
    if not 0 < fov < 180:
        raise ValueError(f'fov must be in (0, 180) degrees, got {fov}')
    f = 0.5 * width / np.tan(np.radians(fov) / 2)
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """OpenCV camera-to-world (x right, y down, z forward) at ``eye`` looking at ``target``."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return c2w


def orbit_cameras(views: int, res, seed: int = DEFAULT_SEED, fov: float = DEFAULT_FOV,
                  radius: float = DEFAULT_RADIUS) -> dict[str, list[Camera]]:
    """The ``orbit`` trajectory (see the module docstring), split into train/validation/test."""
    width, height = parse_res(res)
    K = intrinsics_from_fov(fov, width, height)
    rng = np.random.default_rng([seed, 1])
    golden = (np.sqrt(5.0) - 1.0) / 2.0
    lo, hi = np.radians(ORBIT_ELEVATION)
    cameras = []
    for i in range(views):
        azimuth = 2 * np.pi * (i + rng.uniform(-ORBIT_AZIMUTH_JITTER, ORBIT_AZIMUTH_JITTER)) / views
        u = (0.5 + i * golden + rng.uniform(-0.05, 0.05)) % 1.0
        elevation = lo + (hi - lo) * u
        r = radius * (1.0 + rng.uniform(-ORBIT_RADIUS_JITTER, ORBIT_RADIUS_JITTER))
        eye = r * np.array([np.cos(elevation) * np.sin(azimuth), np.sin(elevation),
                            np.cos(elevation) * np.cos(azimuth)])
        target = rng.normal(0.0, ORBIT_TARGET_JITTER, 3) * np.array([1.0, 0.5, 1.0])
        cameras.append(Camera(K, look_at(eye, target), width, height, name=f'orbit_{i:03d}'))
    counts = split_counts(views)
    held = _stratified_choice(rng, views, counts['validation'] + counts['test'])
    order = rng.permutation(len(held))
    validation = set(held[order[:counts['validation']]].tolist())
    test = set(held[order[counts['validation']:]].tolist())
    return {
        'train': [c for i, c in enumerate(cameras) if i not in validation and i not in test],
        'validation': [c for i, c in enumerate(cameras) if i in validation],
        'test': [c for i, c in enumerate(cameras) if i in test],
    }


def _read_truck(split: str) -> list[tuple[str, np.ndarray, np.ndarray, tuple[int, int]]]:
    """(name, K 3x3, c2w 4x4 OpenCV, (W, H)) of one Truck camera file, sorted by name."""
    path = resources.files(__package__) / 'trajectories' / TRUCK_FILES[split]
    data = json.loads(path.read_text())
    out = []
    for name in sorted(data):
        entry = data[name]
        K = np.asarray(entry['K'], float).reshape(4, 4)[:3, :3]
        c2w = np.linalg.inv(np.asarray(entry['W2C'], float).reshape(4, 4))
        out.append((name, K, c2w, tuple(int(v) for v in entry['img_size'])))
    return out


def _rotation_onto(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` onto unit vector ``b`` (Rodrigues)."""
    v, c = np.cross(a, b), float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-12:
        if c > 0:
            return np.eye(3)
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def truck_alignment(radius: float = DEFAULT_RADIUS) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R, focus, scale)`` placing Truck poses in a scene: ``x_scene = scale·R(x − focus)``.

    Computed from the train cameras: R turns their mean up direction (minus the mean image-down
    axis) onto +Y; ``focus`` is the point closest to all their optical axes (least squares);
    ``scale`` makes their median horizontal distance from ``focus`` equal ``radius``.
    """
    train = _read_truck('train')
    c2w = np.stack([cam[2] for cam in train])
    centers, down, forward = c2w[:, :3, 3], c2w[:, :3, 1], c2w[:, :3, 2]
    up = -down.mean(axis=0)
    up /= np.linalg.norm(up)
    R = _rotation_onto(up, np.array([0.0, 1.0, 0.0]))
    projectors = np.eye(3)[None] - forward[:, :, None] * forward[:, None, :]
    focus = np.linalg.solve(projectors.sum(axis=0), np.einsum('nij,nj->i', projectors, centers))
    rel = (centers - focus) @ R.T
    horizontal = np.linalg.norm(rel[:, [0, 2]], axis=1)
    return R, focus, float(radius / np.median(horizontal))


def truck_cameras(views: int, res, seed: int = DEFAULT_SEED,
                  radius: float = DEFAULT_RADIUS) -> dict[str, list[Camera]]:
    """The ``truck`` trajectory (see the module docstring), split into train/validation/test."""
    width, height = parse_res(res)
    R, focus, scale = truck_alignment(radius)
    counts = split_counts(views)
    rng = np.random.default_rng([seed, 2])
    splits = {}
    for split in SPLITS:
        source = _read_truck(split)
        if counts[split] > len(source):
            sizes = {s: len(_read_truck(s)) for s in SPLITS}
            limit = max(v for v in range(1, 2000)
                        if all(split_counts(v)[s] <= sizes[s] for s in SPLITS))
            raise ValueError(f'the truck trajectory has {len(source)} {split} cameras but '
                             f'{views} views need {counts[split]}: ask for at most {limit} views')
        cameras = []
        for index in _stratified_choice(rng, len(source), counts[split]):
            name, K0, c2w0, (w0, h0) = source[index]
            sx = width / w0
            K = np.array([[K0[0, 0] * sx, 0.0, K0[0, 2] * sx],
                          [0.0, K0[0, 0] * sx, K0[1, 2] * height / h0],
                          [0.0, 0.0, 1.0]])
            c2w = np.eye(4)
            c2w[:3, :3] = R @ c2w0[:3, :3]
            c2w[:3, 3] = scale * R @ (c2w0[:3, 3] - focus)
            cameras.append(Camera(K, c2w, width, height, name=f'truck_{split}_{name}'))
        splits[split] = cameras
    return splits


def _sphere_point(radius: float, azimuth: float, elevation: float) -> np.ndarray:
    """The point at ``radius`` from the origin with ``azimuth`` (from +Z towards +X) and
    ``elevation`` (above the XZ plane), radians."""
    return radius * np.array([np.cos(elevation) * np.sin(azimuth), np.sin(elevation),
                              np.cos(elevation) * np.cos(azimuth)])


def hemisphere_cameras(views: int, res, seed: int = DEFAULT_SEED, fov: float = DEFAULT_FOV,
                       radius: float = DEFAULT_RADIUS) -> dict[str, list[Camera]]:
    """The ``hemisphere`` trajectory (see the module docstring), split into
    train/validation/test."""
    width, height = parse_res(res)
    K = intrinsics_from_fov(fov, width, height)
    rng = np.random.default_rng([seed, 3])
    lo, hi = np.sin(np.radians(HEMISPHERE_ELEVATION))
    cameras = []
    for i in range(views):
        azimuth = rng.uniform(0.0, 2 * np.pi)
        elevation = np.arcsin(rng.uniform(lo, hi))
        eye = _sphere_point(radius, azimuth, elevation)
        cameras.append(Camera(K, look_at(eye, np.zeros(3)), width, height,
                              name=f'hemisphere_{i:03d}'))
    counts = split_counts(views)
    held = rng.permutation(views)[:counts['validation'] + counts['test']]
    validation = set(held[:counts['validation']].tolist())
    test = set(held[counts['validation']:].tolist())
    return {
        'train': [c for i, c in enumerate(cameras) if i not in validation and i not in test],
        'validation': [c for i, c in enumerate(cameras) if i in validation],
        'test': [c for i, c in enumerate(cameras) if i in test],
    }


def arc_cameras(views: int, res, seed: int = DEFAULT_SEED, fov: float = DEFAULT_FOV,
                radius: float = DEFAULT_RADIUS) -> dict[str, list[Camera]]:
    """The ``arc`` trajectory (see the module docstring): train on an arc in front of the
    object, validation = interpolated views, test = extrapolated views.

    Raises:
        ValueError: ``views < 3``.
    """
    if views < 3:
        raise ValueError(f'the arc trajectory needs at least 3 views (one train, one '
                         f'interpolation and one extrapolation view), got {views}')
    width, height = parse_res(res)
    K = intrinsics_from_fov(fov, width, height)
    rng = np.random.default_rng([seed, 4])
    held = max(1, round(HELD_OUT_FRACTION * views))
    n_train = views - 2 * held
    span = np.radians(ARC_AZIMUTH)
    el_lo, el_hi = np.radians(ARC_ELEVATION)
    ex_lo, ex_hi = np.radians(ARC_EXTRAPOLATION)
    golden = (np.sqrt(5.0) - 1.0) / 2.0

    angles = {'train': [], 'validation': [], 'test': []}
    spacing = 2 * span / (n_train - 1) if n_train > 1 else 0.0
    for i in range(n_train):
        azimuth = -span + i * spacing if n_train > 1 else 0.0
        azimuth += spacing * rng.uniform(-ARC_AZIMUTH_JITTER, ARC_AZIMUTH_JITTER)
        u = (0.5 + i * golden + rng.uniform(-0.05, 0.05)) % 1.0
        angles['train'].append((np.clip(azimuth, -span, span), el_lo + (el_hi - el_lo) * u))
    for _ in range(held):
        angles['validation'].append((rng.uniform(-span, span), rng.uniform(el_lo, el_hi)))
    for j in range(held):
        side = 1.0 if j % 2 == 0 else -1.0
        angles['test'].append((side * rng.uniform(ex_lo, ex_hi), rng.uniform(el_lo, el_hi)))

    splits, k = {}, 0
    for split in SPLITS:
        splits[split] = []
        for azimuth, elevation in angles[split]:
            eye = _sphere_point(radius, azimuth, elevation)
            splits[split].append(Camera(K, look_at(eye, np.zeros(3)), width, height,
                                        name=f'arc_{k:03d}'))
            k += 1
    return splits


def make_cameras(trajectory: str, views: int, res, seed: int = DEFAULT_SEED,
                 fov: float = DEFAULT_FOV, radius: float = DEFAULT_RADIUS) -> dict[str, list[Camera]]:
    """Cameras of a trajectory, split into train/validation/test (world units of the scene)."""
    if trajectory == 'orbit':
        return orbit_cameras(views, res, seed, fov, radius)
    if trajectory == 'truck':
        return truck_cameras(views, res, seed, radius)
    if trajectory == 'hemisphere':
        return hemisphere_cameras(views, res, seed, fov, radius)
    if trajectory == 'arc':
        return arc_cameras(views, res, seed, fov, radius)
    raise ValueError(f"unknown trajectory '{trajectory}': use one of {', '.join(TRAJECTORIES)}")


def scene_file(name: str) -> str:
    """Path of a ground-truth scene shipped with the package (``mi_nerfpp/scenes/NAME``)."""
    return str(resources.files(__package__) / 'scenes' / name)


def cache_dir() -> str:
    """Where generated captures are cached: ``$MI_NERFPP_CACHE``, else
    ``$XDG_CACHE_HOME/mi-nerfpp``, else ``~/.cache/mi-nerfpp``."""
    if os.environ.get('MI_NERFPP_CACHE'):
        return os.environ['MI_NERFPP_CACHE']
    base = os.environ.get('XDG_CACHE_HOME') or os.path.join(os.path.expanduser('~'), '.cache')
    return os.path.join(base, 'mi-nerfpp')


def default_capture(progress: bool = True) -> str:
    """Synthesize (once, cached under :func:`cache_dir`) the embedded default capture of
    :data:`DEFAULT_SCENE` with the default parameters, and return its folder."""
    out = os.path.join(cache_dir(), 'default')
    synthesize(scene_file(DEFAULT_SCENE), out, progress=progress)
    return out


# --- rendering ---------------------------------------------------------------------------------

def _sensor(camera: Camera, spp: int, centre_rays: bool = False):
    """A Mitsuba perspective sensor for ``camera``; ``centre_rays``: 1 ray per pixel centre."""
    import mitsuba as mi

    desc = mitsuba_sensor_dict(camera, spp=spp, pixel_format='rgb')
    desc['near_clip'] = MITSUBA_NEAR_CLIP
    if centre_rays:
        desc['sampler'] = {'type': 'stratified', 'sample_count': 1, 'jitter': False}
    return mi.load_dict(desc)


def render_ground_truth(scene, camera: Camera, center, world_radius: float,
                        aov_integrator=None) -> dict[str, np.ndarray]:
    """``depth.Z`` and ``fg.A`` of one view (see the module docstring), H x W float32 each."""
    import mitsuba as mi

    if aov_integrator is None:
        aov_integrator = mi.load_dict({'type': 'aov', 'aovs': 'dd.y:depth,pp:position'})
    image = np.array(mi.render(scene, sensor=_sensor(camera, 1, centre_rays=True),
                               integrator=aov_integrator, spp=1), dtype=np.float64)
    names = list(aov_integrator.aov_names())
    depth = image[..., names.index('dd.y.T')]
    position = image[..., [names.index(f'pp.{c}') for c in 'XYZ']]
    hit = depth > 0
    # Mitsuba's perspective rays start on the near plane, at MITSUBA_NEAR_CLIP / cos(angle to
    # the axis) from the camera centre; the depth AOV counts from there.
    px, py = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    _, dirs = pixel_rays(camera, px, py)
    cos_axis = (dirs @ camera.c2w[:3, 2]).reshape(camera.height, camera.width)
    depth = np.where(hit, depth + MITSUBA_NEAR_CLIP / cos_axis, 0.0)
    inside = np.linalg.norm(position - np.asarray(center), axis=-1) <= world_radius
    return {'depth.Z': depth.astype(np.float32),
            'fg.A': (hit & inside).astype(np.float32)}


def _file_sha256(path: str) -> str:
    with open(path, 'rb') as f:
        return hashlib.sha256(f.read()).hexdigest()


def _expected_files(out: str, counts: dict[str, int]) -> list[str]:
    files = []
    for split, n in counts.items():
        for i in range(n):
            stem = f'{i:06d}'
            files += [os.path.join(out, split, 'rgb', stem + '.png'),
                      os.path.join(out, split, 'pose', stem + '.txt'),
                      os.path.join(out, split, 'intrinsics', stem + '.txt'),
                      os.path.join(out, split, 'gt', stem + '.exr')]
    return files


def _read_capture(out: str) -> dict | None:
    try:
        with open(os.path.join(out, CAPTURE_FILE)) as f:
            info = json.load(f)
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) and info.get('format') == CAPTURE_FORMAT else None


def _write_capture(out: str, info: dict) -> None:
    with atomic_write_path(os.path.join(out, CAPTURE_FILE)) as tmp:
        with open(tmp, 'w') as f:
            json.dump(info, f, indent=2)
            f.write('\n')


def _prepare_output(out: str) -> None:
    """Make ``out`` an empty place to write: create it, or clear an earlier capture in it."""
    if os.path.exists(out) and not os.path.isdir(out):
        raise FileExistsError(f'{out}: exists and is not a folder; choose another --out')
    if not os.path.isdir(out):
        os.makedirs(out)
        return
    if os.path.isfile(os.path.join(out, CAPTURE_FILE)):
        os.remove(os.path.join(out, CAPTURE_FILE))
        for split in SPLITS:
            shutil.rmtree(os.path.join(out, split), ignore_errors=True)
    elif os.listdir(out):
        raise FileExistsError(f'{out}: folder is not empty and holds no {CAPTURE_FILE}; synth '
                              f'writes to an empty folder or over its own earlier capture')


def synthesize(scene_xml, out, views: int = DEFAULT_VIEWS, res=DEFAULT_RES,
               spp: int = DEFAULT_SPP, trajectory: str = DEFAULT_TRAJECTORY,
               seed: int = DEFAULT_SEED,
               fov: float = DEFAULT_FOV, radius: float = DEFAULT_RADIUS,
               progress: bool = True) -> dict:
    """Render a synthetic NeRF++ capture of a Mitsuba scene (see the module docstring).

    Args:
        scene_xml: Mitsuba scene file (its integrator and emitters are used; sensors ignored).
        out: output folder (created; an earlier capture there is replaced or reused).
        views: total number of cameras over all splits.
        res: image size, ``(W, H)`` or ``'WxH'``.
        spp: samples per pixel of the rendered images.
        trajectory: 'orbit', 'truck', 'hemisphere' or 'arc'.
        seed: seeds the camera jitter, the split choice and Mitsuba's sampler.
        fov: horizontal field of view in degrees (ignored by 'truck').
        radius: camera distance from the origin in world units (the orbit's mean radius; for
            'truck' the median horizontal distance of the train cameras).
        progress: show a progress bar and messages.

    Returns:
        The contents of ``capture.json``, plus ``'cached': True`` when nothing was rendered.

    Raises:
        FileNotFoundError: the scene file does not exist.
        ValueError: unknown trajectory, malformed resolution, non-positive views/spp/radius,
            more truck views than the Truck capture has, fewer than 3 arc views.
        FileExistsError: ``out`` is a non-empty folder that holds no earlier capture.
        RuntimeError: Mitsuba cannot load the scene (its message included).
    """
    import drjit as dr
    import mitsuba as mi

    scene_xml, out = os.fspath(scene_xml), os.fspath(out)
    if not os.path.isfile(scene_xml):
        raise FileNotFoundError(f'{scene_xml}: scene file not found')
    if trajectory not in TRAJECTORIES:
        raise ValueError(f"unknown trajectory '{trajectory}': use one of "
                         f"{', '.join(TRAJECTORIES)}")
    width, height = parse_res(res)
    for name, value in (('views', views), ('spp', spp)):
        if int(value) != value or value < 1:
            raise ValueError(f'{name} must be a positive integer, got {value!r}')
    if not radius > 0:
        raise ValueError(f'radius must be positive, got {radius!r}')
    if int(seed) != seed or not 0 <= seed < 2**31:
        raise ValueError(f'seed must be an integer in [0, 2^31), got {seed!r}')
    views, spp, seed = int(views), int(spp), int(seed)

    params = {
        'scene_sha256': _file_sha256(scene_xml), 'trajectory': trajectory, 'views': views,
        'resolution': [width, height], 'spp': spp, 'seed': seed, 'fov': float(fov),
        'radius': float(radius), 'mitsuba': mi.__version__, 'variant': mi.variant(),
        'version': CAPTURE_VERSION,
    }
    cameras = make_cameras(trajectory, views, (width, height), seed, fov, radius)
    counts = {split: len(cameras[split]) for split in SPLITS}

    previous = _read_capture(out)
    if (previous is not None and previous.get('complete') and previous.get('params') == params
            and all(os.path.isfile(f) for f in _expected_files(out, counts))):
        if progress:
            print(f'{out}: capture up to date (same scene file and parameters, all files '
                  f'present); skipping rendering')
        return dict(previous, cached=True)

    _prepare_output(out)
    try:
        scene = mi.load_file(scene_xml)
    except RuntimeError as e:
        raise RuntimeError(f'{scene_xml}: Mitsuba cannot load the scene: {e}') from e

    all_cameras = [cam for split in SPLITS for cam in cameras[split]]
    # The normalization the dataset reader will apply: its unit sphere is the foreground.
    norm = Normalization.for_cameras(all_cameras)
    center, world_radius = norm.center_array, norm.to_world_distance(1.0)
    info = {
        'format': CAPTURE_FORMAT, 'version': CAPTURE_VERSION, 'complete': False,
        'scene': scene_xml, 'scene_path': os.path.abspath(scene_xml),
        'scene_sha256': params['scene_sha256'],
        'trajectory': trajectory,
        'views': counts,
        'names': {split: [cam.name for cam in cameras[split]] for split in SPLITS},
        'resolution': [width, height], 'spp': spp, 'seed': seed, 'fov': float(fov),
        'radius': float(radius),
        'normalization': dict(norm.to_config(), world_radius=float(world_radius)),
        'layers': {
            'rgb/*.png': '8-bit sRGB encoding of the linear render (clipped to [0, 1])',
            'gt/*.exr': {
                'R G B': 'the linear render, float32',
                'depth.Z': 'distance from the camera centre to the first surface hit by the '
                           'ray through the pixel centre, world units (0: no hit)',
                'fg.A': '1 where that hit lies within normalization.world_radius of '
                        'normalization.center (the foreground sphere), else 0'}},
        'mitsuba': mi.__version__, 'drjit': dr.__version__, 'variant': mi.variant(),
        'params': params,
    }
    _write_capture(out, info)

    from tqdm import tqdm

    aov_integrator = mi.load_dict({'type': 'aov', 'aovs': 'dd.y:depth,pp:position'})
    t0 = time.perf_counter()
    bar = tqdm(total=views, desc=f'synth {os.path.basename(scene_xml)}', unit='view',
               disable=not progress)
    k = 0
    for split in SPLITS:
        images = []
        for i, camera in enumerate(cameras[split]):
            render_seed = (seed * 1_000_003 + k) % 2**32
            rgb = np.array(mi.render(scene, sensor=_sensor(camera, spp), spp=spp,
                                     seed=render_seed), dtype=np.float32)[..., :3]
            rgb = np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0)
            images.append(to_srgb8(rgb))
            layers = {'R': rgb[..., 0], 'G': rgb[..., 1], 'B': rgb[..., 2]}
            layers.update(render_ground_truth(scene, camera, center, world_radius,
                                              aov_integrator))
            write_exr(os.path.join(out, split, 'gt', f'{i:06d}.exr'), layers)
            k += 1
            bar.update(1)
        write_nerfpp(out, {split: (cameras[split],
                                   [img.astype(np.float32) / 255.0 for img in images])})
    bar.close()
    info['render_seconds'] = round(time.perf_counter() - t0, 2)
    info['complete'] = True
    _write_capture(out, info)
    if progress:
        print(f'wrote {views} views ({counts["train"]} train, {counts["validation"]} validation, '
              f'{counts["test"]} test) to {out} in {info["render_seconds"]:.1f} s')
    return dict(info, cached=False)


# --- per-image appearance ----------------------------------------------------------------------

APPEARANCE_FILE = 'appearance.json'


def _capture_copy_paths(src, out, needs: str, writer: str) -> tuple[str, str]:
    """``(src, out)`` as strings for a modified copy of a NeRF++ capture; refuses a source
    without ``train/<needs>`` and an ``out`` that already exists."""
    src, out = os.fspath(src), os.fspath(out)
    if not os.path.isdir(os.path.join(src, 'train', needs)):
        raise FileNotFoundError(f'{src}: not a NeRF++ capture (no train/{needs} folder)')
    if os.path.exists(out):
        raise FileExistsError(f'{out}: already exists; {writer} writes a new folder')
    return src, out


def vary_exposure(src, out, stops: float = 0.5, white_balance: float = 0.1, seed: int = 0,
                  splits=('train', 'test')) -> dict:
    """Copy the NeRF++-layout capture ``src`` to ``out`` with a different exposure and white
    balance per image, as a camera on auto-exposure would record it.

    Each image of ``splits`` gets per-channel gains ``2^(e + w_c)`` (``e`` uniform in
    ``±stops``, ``w_c`` uniform in ``±white_balance`` stops), applied in linear light, then
    clipped and sRGB-encoded to 8 bits again. Training image 0 keeps gain 1: it is the
    reference of the learned transforms (:mod:`mi_nerfpp.appearance`), so the learned gains
    estimate the applied ones directly. The true gains are written to ``out/appearance.json``
    (``{split: [[r, g, b], ...]}`` in file order) and returned.
    """
    import imageio.v3 as iio

    src, out = _capture_copy_paths(src, out, 'rgb', 'vary_exposure')
    if not (stops >= 0 and white_balance >= 0):
        raise ValueError(f'stops and white_balance must be >= 0, got {stops}, {white_balance}')
    shutil.copytree(src, out)
    rng = np.random.default_rng(seed)
    gains = {}
    for split in splits:
        folder = os.path.join(out, split, 'rgb')
        names = sorted(os.listdir(folder)) if os.path.isdir(folder) else []
        gains[split] = []
        for i, name in enumerate(names):
            g = 2.0 ** (rng.uniform(-stops, stops) + rng.uniform(-white_balance, white_balance, 3))
            if split == 'train' and i == 0:
                g = np.ones(3)
            path = os.path.join(folder, name)
            image = iio.imread(path)[..., :3].astype(np.float64) / 255.0
            iio.imwrite(path, to_srgb8(np.clip(srgb_eotf(image) * g, 0.0, 1.0)))
            gains[split].append([float(v) for v in g])
    with atomic_write_path(os.path.join(out, APPEARANCE_FILE)) as tmp, open(tmp, 'w') as f:
        json.dump({'gains': gains, 'stops': stops, 'white_balance': white_balance,
                   'seed': seed}, f, indent=2)
    return gains


POSES_FILE = 'poses.json'


def perturb_poses(src, out, degrees: float = 1.0, fraction: float = 0.01, seed: int = 0) -> dict:
    """Copy the NeRF++-layout capture ``src`` to ``out`` with perturbed *training* poses, as an
    imperfect structure-from-motion would give them (the test of ``--refine-poses``).

    Every training camera but image 0 (the reference of the learned corrections,
    :mod:`mi_nerfpp.poses`) is rotated about its centre by ``degrees`` about a random axis and
    its centre moved by ``fraction`` of the scene radius (the largest distance of a training
    camera from their mean centre) in a random direction. Images and held-out poses are
    unchanged. ``out/poses.json`` records ``{'true': [4x4 c2w, ...], 'given': [...],
    'radius': r, ...}`` (training cameras in file order, world frame), which is returned.
    """
    from .data.nerfpp import _read_matrix, _write_matrix
    from .poses import corrected_c2w

    src, out = _capture_copy_paths(src, out, 'pose', 'perturb_poses')
    if not (degrees >= 0 and fraction >= 0):
        raise ValueError(f'degrees and fraction must be >= 0, got {degrees}, {fraction}')
    shutil.copytree(src, out)
    folder = os.path.join(out, 'train', 'pose')
    names = sorted(n for n in os.listdir(folder) if n.lower().endswith('.txt'))
    true = [_read_matrix(os.path.join(folder, n)) for n in names]
    centers = np.stack([c[:3, 3] for c in true])
    radius = float(np.max(np.linalg.norm(centers - centers.mean(axis=0), axis=1)))
    rng = np.random.default_rng(seed)

    def unit():
        v = rng.normal(size=3)
        return v / np.linalg.norm(v)

    given = []
    for i, (name, c2w) in enumerate(zip(names, true)):
        if i > 0:
            c2w = corrected_c2w(c2w, np.concatenate([np.radians(degrees) * unit(),
                                                     fraction * radius * unit()]))
            _write_matrix(os.path.join(folder, name), c2w)
        given.append(c2w)
    record = {'true': [m.tolist() for m in true], 'given': [m.tolist() for m in given],
              'radius': radius, 'degrees': degrees, 'fraction': fraction, 'seed': seed}
    with atomic_write_path(os.path.join(out, POSES_FILE)) as tmp, open(tmp, 'w') as f:
        json.dump(record, f)
    return record
