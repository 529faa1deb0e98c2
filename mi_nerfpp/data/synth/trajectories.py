"""Camera trajectories of synthetic captures: where the cameras of each split are placed.

Every function returns ``{'train': [...], 'validation': [...], 'test': [...]}`` of
:class:`~mi_nerfpp.data.Camera` (OpenCV, world units of the scene), deterministic for a given
``seed``; :func:`make_cameras` picks one by name (:data:`TRAJECTORIES`).

``orbit``
    ``views`` cameras on a jittered band around the origin: azimuth evenly spaced (jittered by up
    to 0.3 of the spacing), elevation 5-35 degrees (a low-discrepancy sequence plus jitter),
    distance ``radius`` +-10 %, looking at the origin jittered by ~0.08 world units, up = +Y, no
    roll. Horizontal field of view ``fov`` degrees, square pixels, principal point at the image
    centre. In the ground-truth scenes (``scenes/gt_*.xml``) every object between 1 and 5 units
    from the origin stays below y = 0 (the cameras' lowest height is ~0.1), so cameras of every
    trajectory with ``radius`` 3-4 are outside every object (checked at the default radius:
    every camera is >= 0.5 units from the nearest surface).
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
"""
from __future__ import annotations

from importlib import resources

import numpy as np

from mi_nerfpp.data.cameras import Camera
from mi_nerfpp.data.dataset import SPLITS
from mi_nerfpp.files.readers import read_json

TRAJECTORIES = ('orbit', 'truck', 'hemisphere', 'arc')

# Camera placement of the default capture (:mod:`mi_nerfpp.data.synth.capture`).
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
    resource = resources.files('mi_nerfpp') / 'trajectories' / TRUCK_FILES[split]
    with resources.as_file(resource) as path:
        data = read_json(path, what='camera file of the package',
                         remedy='install mi-nerfpp again')
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
