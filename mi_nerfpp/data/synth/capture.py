"""Synthetic captures: render posed images of a Mitsuba ground-truth scene in the NeRF++ layout.

``python -m mi_nerfpp synth SCENE.xml --out DATA`` (or :func:`synthesize`) places ``views``
pinhole cameras around the scene (:mod:`mi_nerfpp.data.synth.trajectories`), renders each with the
scene's own integrator, and writes::

    DATA/capture.json                   what was rendered, and how (see *capture.json*)
    DATA/{train,validation,test}/
        rgb/NNNNNN.png                  the render, linear RGB encoded as 8-bit sRGB (clipped)
        pose/NNNNNN.txt                 camera-to-world, OpenCV, in WORLD units of the scene
        intrinsics/NNNNNN.txt           K (top-left 3x3 of a 4x4 matrix)
        gt/NNNNNN.exr                   ground-truth layers (see *Ground truth*)

``mi_nerfpp.data.load_dataset(DATA)`` reads it like any NeRF++ dataset and normalizes the cameras
into the unit sphere itself (``gt/`` is ignored by the reader).

Ground truth
------------
``gt/NNNNNN.exr`` (read with :func:`mi_nerfpp.files.exr.read_exr`). ``depth.Z`` and ``fg.A`` come from
one ray per pixel through the pixel centre (Mitsuba's ``aov`` integrator with a non-jittered
1-spp ``stratified`` sampler):

==========  ===================================================================================
``R G B``   the beauty render, linear RGB, float32, not clipped (the PNG's ``spp`` samples)
``depth.Z`` camera-space z of the first surface hit (distance along the view axis, world
            units, as in every render's ``depth.Z``): the ``depth`` AOV (ray distance from
            the near plane, where Mitsuba's perspective sensor starts its rays) times the
            cosine to the axis, plus the near clip; 0 where the ray hits nothing (the
            environment at infinity)
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

import drjit as dr
import imageio.v3 as iio
import mitsuba as mi
import numpy as np
from tqdm import tqdm

from mi_nerfpp.core import budget as sizing
from mi_nerfpp.core.color import to_srgb8
from mi_nerfpp.core.frame import MITSUBA_NEAR_CLIP, Normalization
from mi_nerfpp.data import masks
from mi_nerfpp.data.cameras import Camera, mitsuba_sensor_dict, pixel_rays
from mi_nerfpp.data.dataset import SPLITS
from mi_nerfpp.data.nerfpp import write_nerfpp
from mi_nerfpp.data.synth.trajectories import (DEFAULT_FOV, DEFAULT_RADIUS,
                                               DEFAULT_SEED, TRAJECTORIES,
                                               make_cameras, parse_res)
from mi_nerfpp.files.atomic import atomic_write_path, readable_path
from mi_nerfpp.files.exr import read_exr, write_exr
from mi_nerfpp.files.readers import FileReadError, read_json

CAPTURE_FILE = 'capture.json'
CAPTURE_FORMAT = 'mi-nerfpp-synth'
CAPTURE_VERSION = 1

# The default capture (the ``synth`` command's defaults and the embedded default of
# ``optimize``; its camera placement defaults are those of :mod:`.trajectories`).
DEFAULT_SCENE = 'gt_garden.xml'
DEFAULT_TRAJECTORY = 'orbit'
DEFAULT_VIEWS = 60
DEFAULT_RES = (128, 96)
DEFAULT_SPP = 64


def scenes_dir() -> str:
    """The folder of the scenes that come with mi-nerfpp (the ground-truth scenes, the objects
    example, render templates): ``mi_nerfpp/scenes/`` in an installed wheel (package data,
    mapped from the repository's ``scenes/`` by pyproject.toml), else the top-level ``scenes/``
    of the source tree the package is imported from (a checkout or an editable install)."""
    package = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    packaged = os.path.join(package, 'scenes')
    if os.path.isfile(os.path.join(packaged, DEFAULT_SCENE)):
        return packaged
    return os.path.join(os.path.dirname(package), 'scenes')


def scene_file(name: str) -> str:
    """Path of a scene that comes with mi-nerfpp (``scenes/NAME``, :func:`scenes_dir`)."""
    return os.path.join(scenes_dir(), name)


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

    desc = mitsuba_sensor_dict(camera, spp=spp, pixel_format='rgb')
    desc['near_clip'] = MITSUBA_NEAR_CLIP
    if centre_rays:
        desc['sampler'] = {'type': 'stratified', 'sample_count': 1, 'jitter': False}
    return mi.load_dict(desc)


def render_ground_truth(scene, camera: Camera, center, world_radius: float,
                        aov_integrator=None) -> dict[str, np.ndarray]:
    """``depth.Z`` and ``fg.A`` of one view (see the module docstring), H x W float32 each."""

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
    # Camera-space z: the ray distance from the centre, depth + near/cos, times cos.
    depth = np.where(hit, depth * cos_axis + MITSUBA_NEAR_CLIP, 0.0)
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
        info = read_json(os.path.join(out, CAPTURE_FILE), what='capture description')
    except FileReadError:       # none, or damaged: not a capture
        return None
    return info if info.get('format') == CAPTURE_FORMAT else None


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


def check_capture_size(views: int, width: int, height: int, spp: int, budget=None):
    """Refuse a capture whose renders Dr.Jit cannot hold (a view traces ``width x height x
    spp`` rays in one wavefront of at most 2^32 - 1 entries) or whose images do not fit in
    memory while they are written (:mod:`mi_nerfpp.core.budget`), naming the option and the
    largest value that fits (ValueError)."""
    budget = sizing.memory_bytes() if budget is None else budget
    pixels = width * height
    per_pixel = sizing.CAPTURE_BYTES_PER_PIXEL
    if not sizing.fits(1, pixels, pixels * per_pixel, budget):
        raise ValueError(f'resolution {width}x{height} is too large: {pixels:,} pixels per '
                         f'image, more than one Dr.Jit array or {sizing.memory_text(budget)} '
                         f'of memory hold; at most {sizing.largest(1, per_pixel, budget):,} '
                         f'pixels fit')
    if pixels * spp > sizing.MAX_ARRAY_ENTRIES:
        raise ValueError(f'spp {spp} is too large at {width}x{height}: a view traces '
                         f'{pixels * spp:,} rays, more than one Dr.Jit array holds (2^32 - 1); '
                         f'at most spp {sizing.MAX_ARRAY_ENTRIES // pixels:,} fits at this '
                         f'resolution')
    if views * pixels * per_pixel > budget:
        raise ValueError(f'views {views} are too many at {width}x{height}: their images take '
                         f'about {sizing.memory_text(views * pixels * per_pixel)} while they '
                         f'are written, more than this machine\'s '
                         f'{sizing.memory_text(budget)}; at most '
                         f'{sizing.largest(1, pixels * per_pixel, budget):,} views fit at this '
                         f'resolution')


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
    check_capture_size(views, width, height, spp)

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
        with readable_path(scene_xml) as readable:      # Mitsuba takes UTF-8 names only
            scene = mi.load_file(readable)
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
                'depth.Z': 'camera-space z (along the view axis) of the first surface hit by '
                           'the ray through the pixel centre, world units (0: no hit)',
                'fg.A': '1 where that hit lies within normalization.world_radius of '
                        'normalization.center (the foreground sphere), else 0'}},
        'mitsuba': mi.__version__, 'drjit': dr.__version__, 'variant': mi.variant(),
        'params': params,
    }
    _write_capture(out, info)


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


def write_object_masks(out: str) -> int:
    """Write the object masks of capture ``out``: ``SPLIT/mask/NNNNNN.png``, white where the
    ground truth's ``fg.A`` is 1 (the first surface a pixel's centre sees lies in the
    foreground sphere), black elsewhere: the silhouettes ``--masks object`` fits the
    foreground to (:mod:`mi_nerfpp.data.masks`). Returns the number of masks written."""
    written = 0
    for split in SPLITS:
        gt_folder = os.path.join(out, split, 'gt')
        if not os.path.isdir(gt_folder):
            continue
        os.makedirs(os.path.join(out, split, masks.SPLIT_FOLDER), exist_ok=True)
        for name in sorted(os.listdir(gt_folder)):
            if not name.endswith('.exr'):
                continue
            alpha = read_exr(os.path.join(gt_folder, name))['fg.A']
            path = os.path.join(out, split, masks.SPLIT_FOLDER,
                                os.path.splitext(name)[0] + '.png')
            with atomic_write_path(path) as tmp:
                iio.imwrite(tmp, np.where(alpha > 0.5, 255, 0).astype(np.uint8),
                            extension='.png')
            written += 1
    return written
