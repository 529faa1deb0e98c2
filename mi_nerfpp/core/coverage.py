"""The training views' coverage of the directions, and the colour painted where they saw
nothing.

A direction at infinity is *seen* by a camera when it falls in its frustum, wherever the camera
stands (distant content: :func:`views_seeing`). The background volume learns nothing in the
directions no training view looked at - the sky above a ring of cameras that look at the
horizon - and little where one view grazed them: its cells there keep their start or
stretch what a few rays showed at their edge, and a view that looks there shows rectangular
blocks of wrong colour.

:class:`CoverageFill` holds, over the background's angles (longitude x colatitude of
:func:`~mi_nerfpp.core.geometry.direction_to_equirect`, ``2N x N`` texels), the weight
``w = min(views, SEEN_BY) / SEEN_BY`` of each direction (softened by a Gaussian of
:data:`WEIGHT_BLUR` degrees) and a fill colour: the training
pixels' mean colour over coarse texels (:data:`COLOUR_RESOLUTION`) where they have one,
spread into the others by push-pull and smoothed (:func:`fill_holes`), then upsampled
bilinearly: the broad colour around an unseen direction, with no cell edges. A render paints
the background of a ray of direction ``d`` as

    C_bg' = w(d) · C_bg + (1 - w(d)) · C_fill(d),   α_bg' = w(d) · α_bg + (1 - w(d)),

both looked up bilinearly, so it is the volume's wherever two training views saw the
direction and a smooth colour where none did. Training never blends: its rays are the
training views' own. Whether a model keeps its fill is decided at the end of its run, on the
validation views (:func:`mi_nerfpp.training.evaluate.choose_coverage_fill`).
"""
from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np
from scipy.ndimage import gaussian_filter

from mi_nerfpp.core.color import srgb_eotf
from mi_nerfpp.core.geometry import direction_to_equirect

# A direction counts as seen when at least this many training views saw it.
SEEN_BY = 2
# Texels of the map along longitude (colatitude: half): 1.4 degrees.
RESOLUTION = 256
# Width (standard deviation, degrees) of the Gaussian that softens the weights, so that the
# fill fades in over a few degrees: 26.98 against 26.94 dB on the default capture's test views
# unblurred (benchmarks/coverage.py).
WEIGHT_BLUR = 2.8
# Texels of the fill colour along longitude (22.5 degrees), upsampled bilinearly to the map: only
# the broad colour of what surrounds an unseen direction carries into it. On the default
# capture's test views, its unseen pixels scored 15.70 / 18.03 dB (views 1 / 5) at 16,
# 15.24 / 17.85 at 32 and 14.08 / 16.32 at 256 (benchmarks/coverage.py).
COLOR_RESOLUTION = 16
# Training pixels read per image to average the colours of the directions (a stride over
# larger images).
PIXELS_PER_IMAGE = 65536
# Jacobi iterations that smooth the colour spread into the unseen directions.
SMOOTHING = 256


def views_seeing(directions, cameras) -> np.ndarray:
    """How many of ``cameras`` see each of the world ``directions`` (``N x 3``) at infinity:
    in front of the camera and within its image. ``cameras``: objects with ``c2w`` (OpenCV,
    +z forward), ``K``, ``width`` and ``height``."""
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    count = np.zeros(len(directions), dtype=np.int64)
    for cam in cameras:
        v = directions @ np.asarray(cam.c2w)[:3, :3]       # into the camera's axes
        ahead = v[:, 2] > 1e-9
        z = np.where(ahead, v[:, 2], 1.0)
        K = np.asarray(cam.K)
        u = K[0, 0] * v[:, 0] / z + K[0, 1] * v[:, 1] / z + K[0, 2]
        w = K[1, 1] * v[:, 1] / z + K[1, 2]
        count += ahead & (u >= 0) & (u < cam.width) & (w >= 0) & (w < cam.height)
    return count


def texel_directions(resolution=RESOLUTION) -> np.ndarray:
    """Unit directions at the centres of the ``resolution/2 x resolution`` texels
    (colatitude x longitude), the inverse of
    :func:`~mi_nerfpp.core.geometry.direction_to_equirect`."""
    width, height = resolution, resolution // 2
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    lon, colat = np.meshgrid((u - 0.5) * 2.0 * np.pi, v * np.pi)
    return np.stack([np.sin(colat) * np.cos(lon), np.sin(colat) * np.sin(lon),
                     np.cos(colat)], axis=-1)


def texel_of(directions, resolution=RESOLUTION) -> np.ndarray:
    """The flat texel index (row-major, colatitude x longitude) of unit ``directions``."""
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    u = np.arctan2(d[:, 1], d[:, 0]) / (2.0 * np.pi) + 0.5
    v = np.arccos(np.clip(d[:, 2], -1.0, 1.0)) / np.pi
    width, height = resolution, resolution // 2
    x = np.clip((u * width).astype(np.int64), 0, width - 1)
    y = np.clip((v * height).astype(np.int64), 0, height - 1)
    return y * width + x


def pixel_directions(cam, px, py) -> np.ndarray:
    """Unit world directions ``normalize(R @ K^-1 [px, py, 1])`` through ``cam``'s continuous
    pixel coordinates ``px, py`` (the centre of pixel (i, j) is (i + ½, j + ½)): ``N x 3``."""
    px, py = np.broadcast_arrays(np.asarray(px, np.float64), np.asarray(py, np.float64))
    pixels = np.stack([px.ravel(), py.ravel(), np.ones(px.size)], axis=0)
    d = (np.asarray(cam.c2w)[:3, :3] @ np.linalg.solve(np.asarray(cam.K, np.float64), pixels)).T
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _halve(a):
    """2 x 2 sums (odd sizes keep their last row/column on its own)."""
    h, w = a.shape[:2]
    a = np.pad(a, [(0, h % 2), (0, w % 2)] + [(0, 0)] * (a.ndim - 2))
    return a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]


def _double(a, shape):
    """Bilinear upsampling by two to ``shape`` (texel centres kept; periodic along x)."""
    h, w = shape[:2]

    def axis(n_out, n_in):
        x = (np.arange(n_out) + 0.5) / 2.0 - 0.5
        i0 = np.floor(x).astype(int)
        return i0, x - i0

    y0, fy = axis(h, a.shape[0])
    x0, fx = axis(w, a.shape[1])
    y1, y0 = np.clip(y0 + 1, 0, a.shape[0] - 1), np.clip(y0, 0, a.shape[0] - 1)
    x1, x0 = (x0 + 1) % a.shape[1], x0 % a.shape[1]
    fy, fx = fy[:, None, None], fx[None, :, None]
    top = a[y0][:, x0] * (1 - fx) + a[y0][:, x1] * fx
    bottom = a[y1][:, x0] * (1 - fx) + a[y1][:, x1] * fx
    return top * (1 - fy) + bottom * fy


def fill_holes(sums, counts, smoothing=SMOOTHING) -> np.ndarray:
    """Mean colour per texel (``sums / counts``) where ``counts > 0``, spread into the texels
    without samples: push-pull (each coarser level the count-weighted mean of the finer, each
    hole the bilinear upsampling of the coarser level), then ``smoothing`` Jacobi iterations
    of the Laplace equation over the holes alone (periodic in longitude), which smooths the
    levels' seams away. ``sums``: ``H x W x C``; ``counts``: ``H x W``."""
    counts = np.asarray(counts, dtype=np.float64)
    sums = np.asarray(sums, dtype=np.float64)
    known = counts > 0
    if not known.any():
        return np.zeros_like(sums)
    levels = [(sums, counts)]
    while not (levels[-1][1] > 0).all() and min(levels[-1][1].shape) > 1:
        s, c = levels[-1]
        levels.append((_halve(s), _halve(c)))
    s, c = levels[-1]
    mean = s / np.maximum(c, 1e-12)[..., None]
    if not (c > 0).all():          # holes left at the coarsest level: the overall mean
        mean[c <= 0] = s.sum(axis=(0, 1)) / c.sum()
    for s, c in reversed(levels[:-1]):
        up = _double(mean, s.shape)
        mean = np.where((c > 0)[..., None], s / np.maximum(c, 1e-12)[..., None], up)
    holes = ~known
    for _ in range(smoothing if holes.any() else 0):
        padded = np.pad(mean, [(1, 1), (0, 0), (0, 0)], mode='edge')
        neighbours = (padded[:-2] + padded[2:] + np.roll(mean, 1, axis=1)
                      + np.roll(mean, -1, axis=1)) * 0.25
        mean = np.where(holes[..., None], neighbours, mean)
    return mean


def mean_colors(cameras, images, color_space, resolution, weights=None) -> np.ndarray:
    """The training pixels' mean linear colour over the ``resolution/2 x resolution`` texels
    of their directions, the texels none falls in filled (:func:`fill_holes`). ``weights``:
    per image an ``H x W`` weight of its pixels in [0, 1] (None: all count)."""
    shape = (resolution // 2, resolution)
    sums = np.zeros((shape[0] * shape[1], 3))
    counts = np.zeros(len(sums))
    for k, (cam, image) in enumerate(zip(cameras, images)):
        stride = max(1, int(np.ceil(np.sqrt(cam.width * cam.height / PIXELS_PER_IMAGE))))
        py, px = np.mgrid[0:cam.height:stride, 0:cam.width:stride]
        d = pixel_directions(cam, px + 0.5, py + 0.5)
        rgb = np.asarray(image, dtype=np.float64)[py.ravel(), px.ravel(), :3]
        if color_space == 'srgb':
            rgb = srgb_eotf(rgb)
        weight = (np.ones(len(rgb)) if weights is None or weights[k] is None
                  else np.asarray(weights[k], dtype=np.float64)[py.ravel(), px.ravel()])
        texel = texel_of(d, resolution)
        for c in range(3):
            sums[:, c] += np.bincount(texel, weight * rgb[:, c], minlength=len(sums))
        counts += np.bincount(texel, weight, minlength=len(sums))
    return fill_holes(sums.reshape(shape + (3,)), counts.reshape(shape))


class CoverageFill:
    """The training views' coverage of the directions and the colour painted where they saw
    nothing (module docs). ``seen``: ``H x W`` weights in [0, 1]; ``colour``: ``H x W x 3``
    linear RGB; ``H = W / 2`` (colatitude x longitude)."""

    def __init__(self, seen, color):
        seen = np.asarray(seen, dtype=np.float32)
        color = np.asarray(color, dtype=np.float32)
        if seen.ndim != 2 or seen.shape[1] != 2 * seen.shape[0] \
                or color.shape != seen.shape + (3,):
            raise ValueError(f'a coverage fill needs seen weights of H x 2H and colours of '
                             f'H x 2H x 3, got {seen.shape} and {colour.shape}')
        self.seen, self.color = seen, color
        # One texture of (w, r, g, b), a texel of longitude wrapped onto each side (periodic
        # there, clamped at the poles).
        texels = np.concatenate([seen[..., None], color], axis=-1)
        texels = np.concatenate([texels[:, -1:], texels, texels[:, :1]], axis=1)
        self.texture = mi.Texture2f(mi.TensorXf(np.ascontiguousarray(texels)),
                                    wrap_mode=dr.WrapMode.Clamp)

    @classmethod
    def of_views(cls, cameras, images, color_space='linear', resolution=RESOLUTION,
                 color_resolution=COLOR_RESOLUTION, weights=None):
        """From the training ``cameras`` and their ``images`` (``H x W x 3`` each, in
        ``color_space``: sRGB images are decoded to linear light, as the model renders);
        ``weights``: how much each pixel counts in the colours (:func:`mean_colours`)."""
        dirs = texel_directions(resolution)
        views = views_seeing(dirs.reshape(-1, 3), cameras).reshape(dirs.shape[:2])
        seen = gaussian_filter(np.minimum(views, SEEN_BY) / SEEN_BY,
                               WEIGHT_BLUR * resolution / 360.0, mode=['nearest', 'wrap'])
        color = mean_colors(cameras, images, color_space, min(color_resolution, resolution),
                              weights)
        while color.shape[1] < resolution:
            color = _double(color, (2 * color.shape[0], 2 * color.shape[1]))
        return cls(seen, color)

    def arrays(self) -> dict:
        """What a checkpoint stores (``coverage/<name>``)."""
        return {'seen': self.seen, 'colour': self.color}

    @classmethod
    def from_arrays(cls, arrays: dict):
        return cls(arrays['seen'], arrays['colour'])

    def lookup(self, d):
        """``(w, C_fill)`` of unit model-frame directions ``d``, bilinear."""
        u, v = direction_to_equirect(d)
        width = self.seen.shape[1]
        texel = self.texture.eval(mi.Point2f((u * width + 1.0) / (width + 2.0), v))
        return texel[0], mi.Color3f(texel[1], texel[2], texel[3])

    def blend(self, d, shading, far=None):
        """The background ``shading`` of rays of direction ``d`` with the fill painted in
        where the training views did not see (module docs); not on rays that end at a finite
        ``far`` (a surface in front of the distance: what it shows is not at infinity)."""
        w, fill = self.lookup(d)
        if far is not None:
            w = dr.select(dr.isinf(far), w, 1.0)
        return dataclasses.replace(shading, rgb=w * shading.rgb + (1.0 - w) * fill,
                                   opacity=w * shading.opacity + (1.0 - w))

