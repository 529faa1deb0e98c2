"""Transients without masks: what only one photo shows gets a small weight in the colour loss.

A passer-by, a car or a bird in one photo of a collection is content no consistent scene
explains; trained on, it is painted into the volumes as fog or floaters and shows in renders
from near that photo. NeRF-W learns a transient volume per photo; RobustNeRF trims the pixels
whose residual is high against the batch's, smoothed over patches. The criterion here is the
one that separates a transient from content that is merely hard (fine texture, an edge): **a
transient is high error in one photo at a point where the other photos that see the same point
are fitted well; hard content is high error in every photo that sees it.** (A weight from the
error of a tile against the other tiles of its own photo alone, tried before this, also left
out hard texture in every view: docs/experiments.md, "Photo collections in the wild".)

:class:`TransientWeights` keeps per tile of ``tile x tile`` pixels of each training photo an
exponential moving average of the training rays' squared error and of their distance along the
ray (in the model's frame), and per photo the median of its tile errors (so that a photo that
is off as a whole - an exposure the run does not model - is compared on its own scale). A
training ray of photo ``i`` in tile ``t`` gets the weight

    r = (e_i,t / m_i) / median_j (e_j,t_j / m_j),      w = clip(2 - r / RATIO, 0, 1)

where ``e`` are tile errors, ``m`` the photos' medians, and ``j`` runs over the other photos in
which the tile's point (its centre's ray at the tile's distance) lands inside the frame, in
front of the camera, in a visited tile ``t_j``: ``w`` is 1 up to ``RATIO`` times the error of
the same point elsewhere and falls to 0 at twice that. Occlusion puts some ``j`` on other
content; the median over the photos that see the point keeps that from deciding. Weights are
1 until :data:`START` of the run (the tiles' errors and distances are first learned), and a
tile with fewer than :data:`MIN_VIEWS` other photos is kept whole.

The run reports the share of the training pixels it weighed below one half and writes those
masks (``RUN/transients/<photo>.png``, white where kept) for inspection.
"""
from __future__ import annotations

import numpy as np

# Side in pixels of the tiles (of the full-size training photos).
TILE = 8
# The fraction of the run from which the weights apply (before: 1, the statistics are learned).
START = 0.2
# Weight of a tile's newest mean in its moving averages (as the error map's).
RATE = 0.3
# A tile's point must land in at least this many other photos' visited tiles to be judged.
MIN_VIEWS = 2
# The photos' median tile errors are taken again every this many updates.
REFERENCE_EVERY = 32
# A pixel weighed below this counts as treated as transient (the share reported, the masks).
TRANSIENT_BELOW = 0.5


class TransientWeights:
    """Per-ray weights of the colour loss against transients (see the module docstring) for
    ``cameras`` (the training photos' :class:`~mi_nerfpp.data.Camera` in the model's frame, all
    ``height x width``), tiles of ``tile`` pixels and the threshold ``ratio`` (> 1)."""

    def __init__(self, cameras, height: int, width: int, tile: int, ratio: float):
        if tile < 1:
            raise ValueError(f'transients: tile of {tile} pixels (at least 1)')
        if not ratio > 1:
            raise ValueError(f'transients: ratio {ratio} (a number above 1)')
        n = len(cameras)
        self.shape = (n, int(height), int(width))
        self.tile, self.ratio = int(tile), float(ratio)
        self.rows, self.cols = -(-height // tile), -(-width // tile)
        tiles = n * self.rows * self.cols
        self.error = np.zeros(tiles)
        self.distance = np.zeros(tiles)
        self.visited = np.zeros(tiles, bool)
        self.reference = np.ones(n)
        self.updates = 0
        self.K = np.array([c.K for c in cameras], np.float64)
        self.R = np.array([c.c2w[:3, :3] for c in cameras], np.float64)
        self.center = np.array([c.c2w[:3, 3] for c in cameras], np.float64)
        # Each photo's projection ``K [Rᵀ | -Rᵀc]`` (n, 3, 4), for points in homogeneous form.
        rt = self.R.transpose(0, 2, 1)
        self.projection = self.K @ np.concatenate([rt, -rt @ self.center[:, :, None]], axis=2)
        # Each tile's centre ray (unit direction, model frame), for its point.
        ty = np.minimum((np.arange(self.rows) + 0.5) * tile, height - 0.5)
        tx = np.minimum((np.arange(self.cols) + 0.5) * tile, width - 0.5)
        px, py = np.meshgrid(tx, ty)
        uv1 = np.stack([px.ravel(), py.ravel(), np.ones(px.size)], axis=0)      # (3, T)
        d = np.einsum('nij,njk,nkt->nti', self.R, np.linalg.inv(self.K),
                      np.broadcast_to(uv1, (n,) + uv1.shape))
        self.direction = (d / np.linalg.norm(d, axis=-1, keepdims=True)).reshape(-1, 3)

    # ------------------------------------------------------------------ rays and tiles
    def tiles(self, index: np.ndarray, factor: int = 1) -> np.ndarray:
        """The tile of each ray ``index`` of a ray bank's pyramid level ``factor`` (the tile
        holding the centre of the ray's block of full-size pixels)."""
        n, h, w = self.shape
        f = int(factor)
        hf, wf = h // f, w // f
        index = np.asarray(index, np.int64)
        image, within = np.divmod(index, hf * wf)
        y, x = np.divmod(within, wf)
        row = np.minimum((y * f + f // 2) // self.tile, self.rows - 1)
        col = np.minimum((x * f + f // 2) // self.tile, self.cols - 1)
        return (image * self.rows + row) * self.cols + col

    def update(self, tiles: np.ndarray, squared_error: np.ndarray, distance: np.ndarray):
        """Fold one batch's squared errors (per ray, mean over channels) and distances (model
        frame, finite) into their tiles."""
        count = np.bincount(tiles, minlength=len(self.error))
        hit = count > 0
        for values, ema in ((squared_error, self.error), (distance, self.distance)):
            values = np.nan_to_num(np.asarray(values, np.float64), nan=0.0, posinf=0.0)
            mean = np.bincount(tiles, weights=values, minlength=len(ema))[hit] / count[hit]
            ema[hit] = np.where(self.visited[hit], (1.0 - RATE) * ema[hit] + RATE * mean, mean)
        self.visited |= hit
        if self.updates % REFERENCE_EVERY == 0:
            self._take_reference()
        self.updates += 1

    def _take_reference(self):
        n = self.shape[0]
        error = np.where(self.visited, self.error, np.nan).reshape(n, -1)
        with np.errstate(all='ignore'):
            median = np.nanmedian(np.where(np.isnan(error).all(axis=1, keepdims=True), 1.0,
                                           error), axis=1)
        self.reference = np.maximum(np.nan_to_num(median, nan=1.0), 1e-12)

    # ------------------------------------------------------------------ weights
    def tile_weights(self, tiles: np.ndarray) -> np.ndarray:
        """The weight (float32) of each tile of ``tiles`` (see the module docstring)."""
        tiles = np.asarray(tiles, np.int64)
        n = self.shape[0]
        per_image = self.rows * self.cols
        image = tiles // per_image
        relative = self.error / np.repeat(self.reference, per_image)
        point = (self.center[image] + self.direction[tiles]
                 * np.maximum(self.distance[tiles], 0.0)[:, None])             # (B, 3)
        # The point in every photo: (u·z, v·z, z) = K [Rᵀ | -Rᵀc] (p, 1), as (n, B, 3).
        uvz = np.matmul(np.concatenate([point, np.ones((len(point), 1))], axis=1),
                        self.projection.transpose(0, 2, 1))
        z = uvz[..., 2]
        with np.errstate(all='ignore'):
            u, v = uvz[..., 0] / z, uvz[..., 1] / z
        _, h, w = self.shape
        inside = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        inside &= np.arange(n)[:, None] != image[None, :]
        row = np.clip(np.nan_to_num(v, nan=0.0) // self.tile, 0, self.rows - 1).astype(np.int64)
        col = np.clip(np.nan_to_num(u, nan=0.0) // self.tile, 0, self.cols - 1).astype(np.int64)
        seen = (np.arange(n)[:, None] * self.rows + row) * self.cols + col
        inside &= self.visited[seen]
        # The median of each point's judged photos (a sort with the others last).
        others = np.sort(np.where(inside, relative[seen], np.inf), axis=0)
        count = inside.sum(axis=0)
        enough = count >= MIN_VIEWS
        rays, lo, hi = np.arange(len(tiles)), np.maximum((count - 1) // 2, 0), count // 2
        elsewhere = np.where(enough, 0.5 * (others[lo, rays] + others[hi, rays]), 1.0)
        r = relative[tiles] / np.maximum(elsewhere, 1e-12)
        weight = np.clip(2.0 - r / self.ratio, 0.0, 1.0)
        return np.where(enough & self.visited[tiles], weight, 1.0).astype(np.float32)

    def weights(self, tiles: np.ndarray, progress: float) -> np.ndarray:
        """The weight (float32) of rays in ``tiles`` (:meth:`tiles`) at ``progress`` (the
        fraction of the run done): 1 before :data:`START`."""
        if progress < START:
            return np.ones(len(tiles), np.float32)
        return self.tile_weights(tiles)

    # ------------------------------------------------------------------ what it found
    def masks(self, chunk: int = 4096) -> np.ndarray:
        """Per photo its tiles' weights, ``(n, rows, cols)`` float32 (1: kept)."""
        tiles = np.arange(len(self.error))
        out = np.concatenate([self.tile_weights(tiles[i:i + chunk])
                              for i in range(0, len(tiles), chunk)])
        return out.reshape(self.shape[0], self.rows, self.cols)

    def transient_share(self, masks: np.ndarray | None = None) -> float:
        """The share of the training pixels whose tile weighs below :data:`TRANSIENT_BELOW`."""
        masks = self.masks() if masks is None else masks
        return float(np.mean(masks < TRANSIENT_BELOW))

    def pixel_masks(self, masks: np.ndarray | None = None) -> np.ndarray:
        """The tiles' weights at the photos' size, ``(n, height, width)`` uint8 (255: kept)."""
        masks = self.masks() if masks is None else masks
        _, h, w = self.shape
        full = np.repeat(np.repeat(masks, self.tile, axis=1), self.tile, axis=2)[:, :h, :w]
        return np.round(full * 255).astype(np.uint8)

    # ------------------------------------------------------------------ checkpoints
    def state(self) -> dict:
        return {'transients.error': self.error.copy(), 'transients.distance': self.distance.copy(),
                'transients.visited': self.visited.copy(),
                'transients.updates': np.int64(self.updates)}

    def restore(self, state: dict):
        """Take the statistics of a checkpoint's ``state`` if it has this layout's tiles (a run
        resumed with other tiles starts them anew). Raises ValueError for damaged ones."""
        stored = state.get('transients.error')
        if stored is None:
            return
        arrays = [np.asarray(state.get(k, np.zeros(0))) for k in
                  ('transients.error', 'transients.distance', 'transients.visited')]
        if any(a.dtype.kind not in 'biuf' or a.ndim != 1 for a in arrays) or \
                len({a.size for a in arrays}) != 1:
            raise ValueError('its transient statistics are damaged: state/transients.error, '
                             '.distance and .visited are not lists of numbers of one length')
        if arrays[0].size != self.error.size:
            return
        error, distance, visited = (a.astype(np.float64) for a in arrays)
        if not (np.all(np.isfinite(error)) and np.all(error >= 0) and np.all(np.isfinite(distance))
                and np.all((visited == 0) | (visited == 1))):
            raise ValueError('its transient statistics are damaged: negative or non-finite '
                             'errors or distances, or flags other than 0 and 1')
        self.error[:], self.distance[:], self.visited[:] = error, distance, visited.astype(bool)
        updates = np.asarray(state.get('transients.updates', 0))
        self.updates = int(updates) if updates.shape == () and updates.dtype.kind in 'iu' else 0
        self._take_reference()
