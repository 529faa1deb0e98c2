"""Where the training rays go: a map of the training error over tiles of the training images.

instant-ngp draws part of its training pixels where the error is high instead of uniformly.
On a capture of photo size a run of this machine's minutes sees each pixel about twice
(gt_plaza 512x384: 101 views of 196,608 pixels, ~41,000 steps of 1,024 rays in 30 minutes),
so rays spent on sky and flat walls that are already right are rays not spent on the edges and
textures that are not.

:class:`ErrorMap` keeps, per tile of ``tile x tile`` pixels of each training image (at full
size), an exponential moving average of the squared error of the training rays that fell in
it. A batch draws ``share`` of its rays from the tiles by error and the rest in
proportion to the tiles' areas (uniform over pixels, as without a map); within a tile the pixel
is uniform. A tile no ray has hit yet counts as the largest error (1), so that every tile is
visited early in the run. The loss is not reweighted: as instant-ngp's, the map makes the hard
pixels count for more, which is the point of it.

The draw by error follows what one consistent scene can still explain, not all of the error.
Each image keeps its share of the rays (its area), and within an image a tile is weighted by
its error *relative to that image's median tile error*, capped at :data:`CAP` times it (the
medians are taken every :data:`REFERENCE_EVERY` updates and resume with the run). On real
photos much of the error is what no consistent scene explains: a whole view off (an exposure
the run cannot model, motion blur, a pose error) or one tile of it (a transient, a glint). A map
over absolute errors sends most rays there and trains on that noise (issue 58: -0.74 dB on a
phone capture); relative to its own image, a view that is off as a whole draws as any other,
and the cap bounds what one unexplainable tile can take.

The map is off by default (``--error-rays 0``: uniform rays). Measured alone on the machine,
10 minutes each, on the realistic stand-in of a phone capture (gt_garden at 1008x756,
``synth --realistic``), uniform rays scored 24.59 dB held out, this map with 0.8 of the rays
23.98 and the absolute map it replaced 23.86 (the phone capture of issue 58: uniform 28.03
against 27.29 with the absolute map). On clean synthetic captures of photo size the map helps
(gt_plaza 512x384: 27.57 against 27.33 dB uniform with the absolute map); there
``--error-rays 0.8`` is worth giving.
"""
from __future__ import annotations

import numpy as np

# The most a tile's error weight can be, in units of its image's median tile error.
CAP = 4.0
# Updates between two takes of the images' median tile errors (a median of every tile each step
# costs ~3 ms at 1008x756, a tenth of a step).
REFERENCE_EVERY = 32
# The squared error an unvisited tile counts with (an encoded colour error of 1 in each channel).
UNVISITED = 1.0
# Weight of a tile's newest mean error in its moving average.
RATE = 0.3


class ErrorMap:
    """Per-tile moving average of the training error of ``n`` images of ``height x width``
    pixels; draws ray indices of a :class:`~mi_nerfpp.training.raybank.RayBank` level."""

    def __init__(self, n: int, height: int, width: int, tile: int, share: float):
        if tile < 1:
            raise ValueError(f'error map: tile of {tile} pixels (at least 1)')
        if not 0.0 <= share <= 1.0:
            raise ValueError(f'error map: share {share} of the rays (a fraction in [0, 1])')
        self.shape = (int(n), int(height), int(width))
        self.tile, self.share = int(tile), float(share)
        self.rows, self.cols = -(-height // tile), -(-width // tile)
        self.error = np.full(n * self.rows * self.cols, UNVISITED)
        self.visited = np.zeros(len(self.error), bool)
        self.reference = np.full(n, UNVISITED)      # each image's median tile error
        self.updates = 0
        ys = np.minimum((np.arange(self.rows) + 1) * tile, height) - np.arange(self.rows) * tile
        xs = np.minimum((np.arange(self.cols) + 1) * tile, width) - np.arange(self.cols) * tile
        area = np.tile(np.outer(ys, xs).ravel(), n).astype(np.float64)
        self._area = area / area.sum()

    def probabilities(self) -> np.ndarray:
        """The chance of each tile for one ray of a batch: ``share`` by the error relative to
        its image's (capped, see the module docstring), the rest by area."""
        n = self.shape[0]
        area = self._area.reshape(n, -1)
        error = self.error.reshape(n, -1)
        image_area = area.sum(axis=1, keepdims=True)
        weight = area * np.minimum(error / self.reference[:, None], CAP)
        by_error = weight / weight.sum(axis=1, keepdims=True) * image_area
        return (self.share * by_error + (1.0 - self.share) * area).ravel()

    def draw(self, rng: np.random.Generator, count: int, factor: int = 1):
        """``(indices, tiles)``: ``count`` ray indices of the bank's pyramid level ``factor``
        (``(image · H/F + y) · W/F + x``, UInt32-ready) and the tile each was drawn from."""
        n, h, w = self.shape
        cdf = np.cumsum(self.probabilities())
        tiles = np.minimum(np.searchsorted(cdf, rng.random(count) * cdf[-1], side='right'),
                           len(cdf) - 1)
        image, within = np.divmod(tiles, self.rows * self.cols)
        row, col = np.divmod(within, self.cols)
        f, t = int(factor), self.tile
        hf, wf = h // f, w // f
        y0, y1 = _span(row, t, f, hf)
        x0, x1 = _span(col, t, f, wf)
        y = y0 + (rng.random(count) * (y1 - y0)).astype(np.int64)
        x = x0 + (rng.random(count) * (x1 - x0)).astype(np.int64)
        return ((image * hf + y) * wf + x).astype(np.uint32), tiles

    def update(self, tiles: np.ndarray, errors: np.ndarray):
        """Fold one batch's squared errors (per ray, mean over channels) into their tiles."""
        total = np.bincount(tiles, weights=np.asarray(errors, np.float64),
                            minlength=len(self.error))
        count = np.bincount(tiles, minlength=len(self.error))
        hit = count > 0
        mean = total[hit] / count[hit]
        old = self.error[hit]
        # A tile fitted exactly keeps a little weight (and the sum stays positive).
        self.error[hit] = np.maximum(
            np.where(self.visited[hit], (1.0 - RATE) * old + RATE * mean, mean), 1e-12)
        self.visited |= hit
        if self.updates % REFERENCE_EVERY == 0:
            self._take_reference()
        self.updates += 1

    def _take_reference(self):
        self.reference = np.maximum(np.median(self.error.reshape(self.shape[0], -1), axis=1),
                                    1e-12)

    def unexplained_share(self) -> float:
        """The share of the pixels in visited tiles whose error is above :data:`CAP` times their
        image's median: what the draw caps, and what no consistent scene explains."""
        n = self.shape[0]
        above = ((self.error.reshape(n, -1) > CAP * self.reference[:, None])
                 & self.visited.reshape(n, -1))
        return float(self._area.reshape(n, -1)[above].sum())

    def state(self) -> dict:
        return {'error_map': self.error.copy(), 'error_map.visited': self.visited.copy(),
                'error_map.reference': self.reference.copy(),
                'error_map.updates': np.int64(self.updates)}

    def restore(self, state: dict):
        """Take the map of a checkpoint's ``state`` if it has one of this map's tiles (a run
        resumed with another ``--error-tile`` starts its map anew)."""
        stored = state.get('error_map')
        if stored is None:
            return
        damage = _damage(state)
        if damage:
            raise ValueError(f'its error map is damaged: {damage}')
        if np.size(stored) != self.error.size:
            return
        self.error[:] = np.asarray(stored, np.float64).ravel()
        self.visited[:] = np.asarray(state['error_map.visited'], bool).ravel()
        reference = state.get('error_map.reference')
        if reference is not None and np.size(reference) == self.shape[0]:
            self.reference = np.asarray(reference, np.float64).ravel().copy()
            self.updates = int(state['error_map.updates'])
        else:       # a map from before the medians (a checkpoint of 54450a8 or older)
            self._take_reference()
            self.updates = 1


def _number_array(value) -> np.ndarray | None:
    """``value`` as a float64 array when it holds real numbers (booleans, integers, floats)."""
    value = np.asarray(value)
    return value.astype(np.float64) if value.dtype.kind in 'biuf' else None


def _damage(state: dict) -> str:
    """What is wrong with the error map stored in a checkpoint's ``state`` ('' when nothing):
    the arrays :meth:`ErrorMap.state` writes, of real numbers, the tiles' errors and the
    images' medians finite and above 0, as many visited flags as tiles, a whole count of
    updates."""
    error = _number_array(state['error_map'])
    if error is None or error.ndim != 1 or error.size == 0:
        return f'state/error_map is not a list of numbers (shape {np.shape(state["error_map"])}, ' \
               f'{np.asarray(state["error_map"]).dtype})'
    if not np.all(np.isfinite(error) & (error > 0)):
        return 'state/error_map holds NaN, infinite, zero or negative tile errors'
    visited = _number_array(state.get('error_map.visited', np.zeros(0)))
    if visited is None or visited.ndim != 1 or visited.size != error.size or \
            not np.all((visited == 0) | (visited == 1)):
        return (f'state/error_map.visited is not {error.size} flags, one per tile of '
                f'state/error_map')
    reference = state.get('error_map.reference')
    if reference is not None:
        reference = _number_array(reference)
        if reference is None or reference.ndim != 1 or \
                not np.all(np.isfinite(reference) & (reference > 0)):
            return 'state/error_map.reference is not a list of positive finite numbers'
        updates = np.asarray(state.get('error_map.updates', -1))
        if updates.shape != () or updates.dtype.kind not in 'iu' or int(updates) < 0:
            return 'state/error_map.updates is not a whole number of 0 or more'
    return ''


def _span(tile_index, tile, factor, size):
    """``[first, end)`` of the pixels of a pyramid level (``factor`` F, ``size`` pixels) whose
    F-pixel block starts in tile ``tile_index``; where none does (tiles narrower than F), the
    pixel holding the tile's first pixel."""
    first = -(-tile_index * tile // factor)
    end = np.minimum(-(-(tile_index + 1) * tile // factor), size)
    empty = end <= first
    first = np.where(empty, np.minimum(tile_index * tile // factor, size - 1), first)
    end = np.where(empty, first + 1, end)
    return first, end
