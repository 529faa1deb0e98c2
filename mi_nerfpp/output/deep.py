"""Deep OpenEXR output: the volumes' (and objects') contributions along each pixel, so that a
compositor deep-merges CG with the reconstruction at the right depth without holdout mattes.

``python -m mi_nerfpp render SCENE -o out.exr --deep`` (:func:`render_deep_to_file`) writes one
deep scanline EXR with the channels ``R G B A Z ZBack`` (OpenEXR's deep conventions: colour
premultiplied by ``A``, ``Z``/``ZBack`` the front and back of a sample in camera-space z, world
units, as the flat ``depth.Z``; samples sorted front to back and not overlapping,
``deepImageState`` = sorted). No NeRF tool writes deep EXR.

**What a sample is.** The ``nerfpp`` integrator's quadrature gives every camera ray a list of
*events*: each foreground sample ``i`` absorbs the fraction ``w_i`` of the ray's light (its
quadrature weight), each background sample ``λ·w_k``, and a scene's shape the rest,
``1 - opacity`` at its hit; each event brings its share of the radiance the ray sees: a
volume's layer radiance split over its samples in proportion to their weights (a grid field
with *deferred* colour, the foreground's default, colours once per ray, so a sample has no
colour of its own; per-sample colours, the background's default, are split the same way), the
shapes' ``obj`` radiance at the hit, the shadow catchers' change scaling the volumes' events.
A pixel's rays (a ``k x k`` grid of positions in the pixel, ``k = round(sqrt(spp))``, the positions of
Mitsuba's ``stratified`` sampler without jitter) are merged by depth: sorted front to back,
the pixel's transmittance at depth ``z`` is the average of its rays' (``T(z) = mean_s
T_s(z)``), and consecutive events become one deep sample while they stay in the same volume
(foreground, background, shapes), in the same octave of depth and in the same step of
:data:`MERGE_OPACITY` of accumulated opacity: nearly transparent stretches merge into few
samples, surfaces keep theirs. A sample of absorbed fraction ``W`` and radiance ``C`` that
starts at pixel transmittance ``T`` has ``A = W/T`` and colour ``C/T``, so flattening (``over``,
front to back) gives back ``Σ C``, the pixel's beauty, exactly (events lighter than
:data:`DROP_WEIGHT` are left out: at most ``1e-6`` of light each).
"""
from __future__ import annotations

import os

import drjit as dr
import mitsuba as mi
import numpy as np
import OpenEXR
from tqdm import tqdm

from mi_nerfpp.core.geometry import pixel_footprint
from mi_nerfpp.core.rays import Rays
from mi_nerfpp.core.render import flat_index
from mi_nerfpp.files.atomic import atomic_write_path
from mi_nerfpp.files.exr import COMPRESSIONS
from mi_nerfpp.files.readers import FileReadError, read_exr
from mi_nerfpp.integrator import NeRFPPIntegrator
from mi_nerfpp.integrator.parameters import check_film
from mi_nerfpp.output.views import exr_attributes

# Deep samples break where the accumulated opacity of a pixel crosses a multiple of this.
MERGE_OPACITY = 0.02
# Events that absorb less than this fraction of a ray's light are left out of the deep file.
DROP_WEIGHT = 1e-6
# Events of kind: foreground volume, background volume, a scene's shape.
FOREGROUND, BACKGROUND, SHAPE = 0, 1, 2
DEEP_CHANNELS = ('R', 'G', 'B', 'A', 'Z', 'ZBack')


def _camera_rays(sensor, pixels, k):
    """World rays of ``pixels`` (flat indices), ``k x k`` positions each, pixel-major, and their
    pixel footprints (:func:`~mi_nerfpp.core.geometry.pixel_footprint`)."""

    width, height = (int(v) for v in sensor.film().crop_size())
    offset = (np.arange(k) + 0.5) / k
    sub_y, sub_x = np.meshgrid(offset, offset, indexing='ij')
    px = (pixels % width)[:, None] + sub_x.ravel()[None, :]
    py = (pixels // width)[:, None] + sub_y.ravel()[None, :]
    pos = mi.Point2f(mi.Float((px / width).ravel().astype(np.float32)),
                     mi.Float((py / height).ravel().astype(np.float32)))
    ray, _ = sensor.sample_ray_differential(0.0, 0.5, pos, mi.Point2f(0.5))
    return mi.Point3f(ray.o), mi.Vector3f(ray.d), pixel_footprint(ray)


def _events(integrator, frame, o, d, seed, footprint=None):
    """Per-ray events of camera rays ``o, d`` as NumPy arrays: ``ray``, ``kind``, ``z``
    (camera-space), ``w`` (absorbed fraction of the ray's light), ``rgb`` (n x 3), and the
    rays' beauty (n x 3) and opacity (n)."""

    n = dr.width(o)
    deep = {}
    path_seed = None
    if frame.traces_paths:
        path_seed, _ = mi.sample_tea_32(dr.arange(mi.UInt32, n), mi.UInt32(seed))
    L, _ = integrator.render_rays(frame, Rays(o, d, footprint=footprint, path_seed=path_seed),
                                  record=deep)
    res, aovs = deep['res'], deep['aovs']
    norm = integrator.model.normalization
    center, axis = integrator.camera
    z0 = dr.dot(o - center, axis)
    cos = dr.dot(dr.normalize(d), axis)
    # The shadow catchers scale what the volumes show: (L0 + shadow) / L0 per channel.
    scale = mi.Color3f(1.0)
    if 'shadow' in deep:
        L0 = deep['L0']
        scale = dr.select(L0 > 0.0, (L0 + deep['shadow']) / dr.maximum(L0, 1e-30), 1.0)
    fg_alpha = aovs['fg.A']
    lam = 1.0 - fg_alpha
    seen = lam / (lam + 1e-6)        # the bg_w sample channel holds (λ + ε)·bg
    layer = {'fg': mi.Color3f(aovs['fg.R'], aovs['fg.G'], aovs['fg.B']),
             'bg': seen * mi.Color3f(aovs['bg_w.R'], aovs['bg_w.G'], aovs['bg_w.B'])}
    out = []
    for kind, volume, share in ((FOREGROUND, res.fg, 1.0), (BACKGROUND, res.bg, lam)):
        if volume is None or volume.weights is None:
            continue
        m = volume.n
        rays = (dr.arange(mi.UInt32, dr.width(volume.weights) // m) if volume.rays is None
                else volume.rays)
        count = dr.width(rays)
        _, k = flat_index(count, m)
        ray = dr.gather(mi.UInt32, rays, dr.arange(mi.UInt32, count * m) // m)
        total = dr.block_sum(volume.weights, m)
        frac = volume.weights / dr.maximum(dr.gather(mi.Float, total, dr.arange(
            mi.UInt32, count * m) // m), 1e-30)
        w = dr.gather(mi.Float, share, ray) * volume.weights if kind == BACKGROUND \
            else volume.weights
        rgb = frac * dr.gather(mi.Color3f, layer['fg' if kind == FOREGROUND else 'bg'] * scale,
                               ray)
        z = dr.gather(mi.Float, z0, ray) + norm.to_world_distance(volume.distance) \
            * dr.gather(mi.Float, cos, ray)
        keep = dr.compress(w > DROP_WEIGHT)
        out.append((kind, keep, ray, z, w, rgb))
    if deep.get('far') is not None:
        hit = deep['hit']
        rest = dr.maximum(1.0 - res.composite.opacity, 0.0)
        rays = dr.compress(hit & (rest > DROP_WEIGHT))
        z_hit = z0 + deep['far'] * cos
        out.append((SHAPE, rays, dr.arange(mi.UInt32, n), z_hit, rest, deep['surfaces']))
    arrays = {'ray': [], 'kind': [], 'z': [], 'w': [], 'rgb': []}
    for kind, keep, ray, z, w, rgb in out:
        if dr.width(keep) == 0:
            continue
        values = [dr.gather(type(a), a, keep) for a in (ray, z, w)] + [
            dr.gather(mi.Color3f, rgb, keep)]
        dr.eval(values)
        arrays['ray'].append(np.array(values[0], dtype=np.int64))
        arrays['z'].append(np.array(values[1], dtype=np.float64))
        arrays['w'].append(np.array(values[2], dtype=np.float64))
        arrays['rgb'].append(np.array(values[3], dtype=np.float64).reshape(3, -1).T)
        arrays['kind'].append(np.full(dr.width(keep), kind, dtype=np.int64))
    events = {k: np.concatenate(v) if v else np.zeros((0, 3) if k == 'rgb' else 0)
              for k, v in arrays.items()}
    beauty = np.array(L, dtype=np.float64).reshape(3, -1).T
    return events, beauty


def merge_pixel_events(pixel, kind, z, w, rgb, n_pixels):
    """Deep samples of pixels from their rays' events (module docs). ``pixel``: the pixel of
    each event (its ray's index // rays per pixel); ``w``, ``rgb``: the event's absorbed
    fraction and radiance, already divided by the rays per pixel. Returns ``(counts, samples)``:
    samples per pixel (``n_pixels``) and a dict of the :data:`DEEP_CHANNELS`, pixel-major and
    front to back."""
    order = np.lexsort((z, pixel))
    pixel, kind, z, w, rgb = pixel[order], kind[order], z[order], w[order], rgb[order]
    starts = np.r_[True, pixel[1:] != pixel[:-1]] if len(pixel) else np.zeros(0, bool)
    cum = np.cumsum(w)
    first = np.maximum.accumulate(np.where(starts, np.arange(len(w)), 0)) if len(w) else \
        np.zeros(0, np.int64)
    before = cum - w - (cum[first] - w[first])      # opacity of the pixel before the event
    step = np.floor(before / MERGE_OPACITY)
    octave = np.floor(np.log2(np.maximum(z, 1e-30)))
    new = starts.copy()
    if len(w) > 1:
        new[1:] |= (kind[1:] != kind[:-1]) | (step[1:] != step[:-1]) \
            | (octave[1:] != octave[:-1])
    group = np.cumsum(new) - 1
    n_groups = int(group[-1] + 1) if len(group) else 0
    W = np.bincount(group, weights=w, minlength=n_groups)
    C = np.stack([np.bincount(group, weights=rgb[:, c], minlength=n_groups) for c in range(3)],
                 axis=-1)
    head = np.flatnonzero(new)
    T = np.maximum(1.0 - before[head], 1e-12)
    front = np.minimum.reduceat(z, head) if n_groups else np.zeros(0)
    back = np.maximum.reduceat(z, head) if n_groups else np.zeros(0)
    alpha = np.minimum(W / T, 1.0)
    samples = {'R': C[:, 0] / T, 'G': C[:, 1] / T, 'B': C[:, 2] / T, 'A': alpha,
               'Z': front, 'ZBack': back}
    counts = np.bincount(pixel[head], minlength=n_pixels) if n_groups else \
        np.zeros(n_pixels, np.int64)
    return counts, {k: v.astype(np.float32) for k, v in samples.items()}


def render_deep(scene, spp=0, seed=0, chunk_pixels=4096, progress=False, sensor=None):
    """Deep samples of ``scene``'s first sensor, or of ``sensor`` (module docs). Returns ``(counts, samples,
    beauty)``: samples per pixel (H x W), the :data:`DEEP_CHANNELS` of all samples
    (pixel-major, front to back), and the flat beauty of the same rays (H x W x 3)."""

    integrator = scene.integrator()
    if not isinstance(integrator, NeRFPPIntegrator):
        raise ValueError("the scene's integrator is not 'nerfpp': use "
                         "<integrator type=\"nerfpp\"> for deep output")
    sensor = sensor or scene.sensors()[0]
    k = max(1, int(round(np.sqrt(spp or sensor.sampler().sample_count()))))
    width, height = (int(v) for v in sensor.film().crop_size())
    check_film((width, height), k * k, integrator.max_samples)
    integrator.look_through(sensor)
    frame = integrator.frame(scene)
    n_pixels = width * height
    chunk_pixels = max(1, min(chunk_pixels, integrator.chunk_rays // (k * k) or 1))
    counts, samples, beauty = [], [], []
    chunks = range(0, n_pixels, chunk_pixels)
    if progress:
        chunks = tqdm(chunks, desc='deep', unit='chunk', leave=False)
    with dr.suspend_grad():
        for start in chunks:
            pixels = np.arange(start, min(start + chunk_pixels, n_pixels))
            o, d, footprint = _camera_rays(sensor, pixels, k)
            events, L = _events(integrator, frame, o, d,
                                (seed * 1_000_003 + start) % 2 ** 32, footprint)
            c, s = merge_pixel_events(events['ray'] // (k * k), events['kind'], events['z'],
                                      events['w'] / (k * k), events['rgb'] / (k * k),
                                      len(pixels))
            counts.append(c)
            samples.append(s)
            beauty.append(L.reshape(len(pixels), k * k, 3).mean(axis=1))
    merged = {ch: np.concatenate([s[ch] for s in samples]) for ch in DEEP_CHANNELS}
    return (np.concatenate(counts).reshape(height, width), merged,
            np.concatenate(beauty).reshape(height, width, 3).astype(np.float32))


def write_deep_exr(path, counts, samples, attributes=None, compression='zips'):
    """Write deep samples (:func:`render_deep`'s ``counts`` and ``samples``) as a deep
    scanline EXR, atomically."""

    if compression not in ('none', 'rle', 'zips'):
        raise ValueError(f"deep EXR compression must be none, rle or zips (OpenEXR's deep "
                         f"files allow no other), got '{compression}'")
    height, width = counts.shape
    offsets = np.r_[0, np.cumsum(counts.ravel())]
    channels = {}
    for ch in DEEP_CHANNELS:
        per_pixel = np.empty((height, width), dtype=object)
        flat = per_pixel.reshape(-1)
        values = samples[ch]
        for i in range(height * width):
            flat[i] = values[offsets[i]:offsets[i + 1]]
        channels[ch] = per_pixel
    header = dict(attributes or {})
    header.update(type=OpenEXR.deepscanline, compression=COMPRESSIONS[compression])
    with atomic_write_path(path) as tmp:
        with OpenEXR.File(header, channels) as f:
            f.write(tmp)


def read_deep_exr(path):
    """``(counts, samples)`` of a deep scanline EXR written by :func:`write_deep_exr`."""
    remedy = 'write the deep EXR again'
    _, channels = read_exr(path, what='deep EXR', remedy=remedy)
    missing = [c for c in ('Z', 'ZBack') + (() if 'RGBA' in channels else tuple('RGBA'))
               if c not in channels]
    if missing:
        raise FileReadError(f'{os.fsdecode(path)}: cannot read deep EXR (no channel '
                            f'{", ".join(missing)}): {remedy}')
    if 'RGBA' in channels:
        rgba = channels['RGBA']
        per = {c: np.empty(rgba.shape, dtype=object) for c in 'RGBA'}
        for idx in np.ndindex(rgba.shape):
            block = np.asarray(rgba[idx], dtype=np.float32).reshape(-1, 4)
            for j, c in enumerate('RGBA'):
                per[c][idx] = block[:, j]
    else:
        per = {c: channels[c] for c in 'RGBA'}
    per['Z'], per['ZBack'] = channels['Z'], channels['ZBack']
    shape = per['Z'].shape
    counts = np.array([len(per['Z'][idx]) for idx in np.ndindex(shape)]).reshape(shape)
    samples = {c: np.concatenate([np.asarray(per[c][idx], np.float32).ravel()
                                  for idx in np.ndindex(shape)] or [np.zeros(0, np.float32)])
               for c in DEEP_CHANNELS}
    return counts, samples


def flatten(counts, samples):
    """``over`` of each pixel's deep samples, front to back: H x W x 4 (premultiplied RGBA)."""
    offsets = np.r_[0, np.cumsum(counts.ravel())]
    pixel = np.repeat(np.arange(counts.size), counts.ravel())
    a = samples['A'].astype(np.float64)
    log_t = np.log(np.maximum(1.0 - a, 1e-300))
    cum = np.cumsum(log_t)
    start = offsets[:-1][pixel]
    before = cum - log_t - np.where(start > 0, cum[np.maximum(start - 1, 0)], 0.0)
    T = np.exp(before)
    out = np.zeros((counts.size, 4))
    for j, c in enumerate('RGBA'):
        out[:, j] = np.bincount(pixel, weights=T * samples[c], minlength=counts.size)
    return out.reshape(*counts.shape, 4)


def render_deep_to_file(scene, out, spp=0, seed=0, progress=True, sensor=None):
    """Render ``scene``'s first sensor (or ``sensor``) and write a deep EXR (module docs) with
    the header attributes of a flat render. Returns ``(counts, samples, beauty)``
    (:func:`render_deep`)."""
    sensor = sensor or scene.sensors()[0]
    counts, samples, beauty = render_deep(scene, spp, seed, progress=progress, sensor=sensor)
    attributes = exr_attributes(sensor)
    attributes['depthConvention'] = ('Z, ZBack: camera-space z of the front and back of each '
                                     'deep sample (distance along the view axis, world units)')
    write_deep_exr(out, counts, samples, attributes)
    return counts, samples, beauty
