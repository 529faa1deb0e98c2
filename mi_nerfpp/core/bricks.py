"""Sparse grid levels: a fine texel grid stored only in the bricks where the surfaces are.

A :class:`BrickGrid` is the texel grid of one level, ``shape = (Z, Y, X)`` texels, cut into
``blocks`` bricks per axis of ``brick = shape / blocks`` texels each (OpenVDB's leaf nodes
under a one-level index). Only *allocated* bricks hold values: a pool of
``(slots, bz, by, bx, C)`` entries, which is the learnable parameter, and a map from each
brick to its slot. The optimiser's state, the gradient sums and the Adam update therefore
scale with the allocated texels, not with the bounding grid.

A lookup is the trilinear interpolation of a ``Texture3f`` over the same texels (texel
centres at ``(i + ½)/X``, clamped at the border or periodic along x, the background's
longitude): its eight texels are read from their bricks, and a texel in a brick that is not
allocated reads 0. Where every brick is allocated, the lookup equals the dense texture's.

Which bricks to allocate comes from an occupancy mask (:func:`block_mask` maps an
:class:`~mi_nerfpp.core.occupancy.OccupancyGrid`'s cells onto the bricks, :func:`dilate` grows
it by a brick), at most ``limit`` bricks, the densest first (:func:`choose`).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

# Bricks allocated around the occupied ones, along (z, y, x), by domain: one all round in the
# ball (a surface near a brick's face interpolates into its neighbour); along s only in the
# inverted sphere, whose bricks span many texels of angle and one of depth.
DILATION = {'ball': (1, 1, 1), 'inverted_sphere': (1, 0, 0)}
# The pool's packet type by channel count: one gather reads a texel's channels together.
_PACKETS = {2: 'Array2f', 4: 'Array4f'}


class BrickGrid:
    """The brick layout of one sparse level and its slot map (see module docs)."""

    def __init__(self, shape, blocks, channels, periodic=False):
        self.shape = tuple(int(s) for s in shape)
        self.blocks = tuple(int(b) for b in blocks)
        if len(self.shape) != 3 or len(self.blocks) != 3 or min(self.blocks) < 1 \
                or any(s % b for s, b in zip(self.shape, self.blocks)):
            raise ValueError(f'a brick grid of {self.shape} texels cannot be cut into '
                             f'{self.blocks} bricks per axis (each axis must divide evenly)')
        self.brick = tuple(s // b for s, b in zip(self.shape, self.blocks))
        self.channels, self.periodic = int(channels), bool(periodic)
        self.allocate(np.zeros(0, dtype=np.int64))

    @property
    def n_blocks(self) -> int:
        return int(np.prod(self.blocks))

    @property
    def texels_per_brick(self) -> int:
        return int(np.prod(self.brick))

    @property
    def n_allocated(self) -> int:
        return len(self.allocated)

    def pool_shape(self, n=None):
        """The pool parameter's shape for ``n`` allocated bricks (default: those allocated now);
        one brick, never read, while none is (Dr.Jit arrays are not empty)."""
        n = self.n_allocated if n is None else int(n)
        return (max(n, 1),) + self.brick + (self.channels,)

    def allocate(self, bricks) -> None:
        """Allocate ``bricks`` (flat brick indices over ``blocks``, z slowest), in slot order."""
        bricks = self._checked(bricks)
        self.allocated = bricks
        slots = np.zeros(self.n_blocks, dtype=np.uint32)
        slots[bricks] = np.arange(1, bricks.size + 1, dtype=np.uint32)
        self.slots = mi.UInt32(slots)          # slot + 1 of each brick, 0: not allocated

    def _checked(self, bricks):
        """``bricks`` as flat brick indices, refused unless distinct and in range."""
        bricks = np.asarray(bricks, dtype=np.int64).ravel()
        if bricks.size and (bricks.min() < 0 or bricks.max() >= self.n_blocks
                            or np.unique(bricks).size != bricks.size):
            raise ValueError(f'brick indices must be distinct and in [0, {self.n_blocks})')
        return bricks

    def moved(self, pool, bricks, fill=None):
        """The pool (NumPy, of :meth:`pool_shape`) re-laid for an allocation of ``bricks``:
        bricks kept keep their texels; new ones take theirs from ``fill`` (an array of the new
        pool's shape: a fresh level's starting values) or start at zero."""
        pool = np.asarray(pool, dtype=np.float32).reshape(self.pool_shape())
        out = np.zeros(self.pool_shape(len(bricks)), np.float32) if fill is None \
            else np.array(fill, dtype=np.float32).reshape(self.pool_shape(len(bricks)))
        new, old = self.kept(bricks)
        out[new] = pool[old]
        return out

    def kept(self, bricks):
        """``(new slots, old slots)`` of the bricks that an allocation of ``bricks`` keeps."""
        bricks = self._checked(bricks)
        _, new, old = np.intersect1d(bricks, self.allocated, assume_unique=True,
                                     return_indices=True)
        return new, old

    def _axis(self, c, n, periodic):
        """Lower/upper texel index and weight of the upper one along an axis of ``n`` texels."""
        u = dr.fma(c, n, -0.5)
        f = dr.floor(u)
        t = u - f
        i0 = mi.Int32(f)
        i1 = i0 + 1
        if periodic:
            i0 = dr.select(i0 < 0, i0 + n, dr.select(i0 >= n, i0 - n, i0))
            i1 = dr.select(i1 < 0, i1 + n, dr.select(i1 >= n, i1 - n, i1))
        else:
            i0, i1 = dr.clip(i0, 0, n - 1), dr.clip(i1, 0, n - 1)
        return mi.UInt32(i0), mi.UInt32(i1), t

    def lookup(self, pool, coords):
        """Trilinear lookup at texture coordinates ``coords = [x, y, z]`` in ``[0, 1]`` of the
        pool ``pool`` (the flat ``Float`` of the parameter): a list of ``channels`` Floats."""
        Z, Y, X = self.shape
        BZ, BY, BX = self.blocks
        bz, by, bx = self.brick
        C = self.channels
        axes = [self._axis(coords[0], X, self.periodic), self._axis(coords[1], Y, False),
                self._axis(coords[2], Z, False)]
        # Per axis, for the lower and the upper texel: (brick coordinate, offset in the brick).
        parts = []
        for (i0, i1, _), b in zip(axes, (bx, by, bz)):
            parts.append([(i // b, i % b) for i in (i0, i1)])
        packet = getattr(mi, _PACKETS[C]) if C in _PACKETS else None
        out = [mi.Float(0.0) for _ in range(C)]
        tx, ty, tz = (a[2] for a in axes)
        for corner in range(8):
            (qx, lx), (qy, ly), (qz, lz) = (parts[a][(corner >> a) & 1] for a in range(3))
            w = ((tx if corner & 1 else 1.0 - tx) * (ty if corner & 2 else 1.0 - ty)
                 * (tz if corner & 4 else 1.0 - tz))
            slot = dr.gather(mi.UInt32, self.slots, (qz * BY + qy) * BX + qx)
            valid = slot > 0
            # (Index 0 where nothing is read: masked lanes keep in-range indices.)
            texel = dr.select(valid, (slot - 1) * (bz * by * bx) + (lz * by + ly) * bx + lx, 0)
            if packet is not None:
                values = dr.gather(packet, pool, texel, valid)
            else:
                values = [dr.gather(mi.Float, pool, texel * C + c, valid) for c in range(C)]
            out = [dr.fma(w, v, o) for o, v in zip(out, values)]
        return out


def block_max(values, blocks):
    """The maximum of ``values`` (NumPy (Z, Y, X), e.g. an occupancy grid's density) over each
    brick of a grid of ``blocks`` (each axis of one a multiple of the other's: a brick over many
    cells takes their maximum, a cell over many bricks is repeated)."""
    v = np.asarray(values, dtype=np.float32)
    for axis, (n, b) in enumerate(zip(v.shape, blocks)):
        if n % b == 0:
            v = v.reshape(v.shape[:axis] + (b, n // b) + v.shape[axis + 1:]).max(axis=axis + 1)
        elif b % n == 0:
            v = np.repeat(v, b // n, axis=axis)
        else:
            raise ValueError(f'a grid of {np.shape(values)} cells does not map onto '
                             f'{tuple(blocks)} bricks (each axis must divide the other)')
    return v


def block_mask(occupied, blocks):
    """An occupancy mask ``occupied`` (NumPy bool (Z, Y, X)) on a brick grid of ``blocks``: a
    brick is occupied when any cell it overlaps is (:func:`block_max`)."""
    return block_max(np.asarray(occupied, dtype=np.float32), blocks) > 0


def dilate(mask, steps=(1, 1, 1), periodic_x=False):
    """``mask`` (bool (Z, Y, X)) grown by ``steps`` bricks along (z, y, x), x periodic or not."""
    out = np.asarray(mask, dtype=bool).copy()
    for axis, n in zip((0, 1, 2), steps):
        base = out.copy()
        for k in range(1, int(n) + 1):
            for sign in (-1, 1):
                shifted = np.roll(base, sign * k, axis=axis)
                if not (periodic_x and axis == 2):
                    edge = [slice(None)] * 3
                    edge[axis] = slice(0, k) if sign > 0 else slice(-k, None)
                    shifted[tuple(edge)] = False
                out |= shifted
    return out


def choose(mask, score, limit):
    """The flat indices of the bricks of ``mask`` to allocate: all of them, or the ``limit``
    with the highest ``score`` (same shape), in index order."""
    index = np.flatnonzero(np.asarray(mask).ravel())
    if limit is not None and index.size > limit:
        order = np.argsort(-np.asarray(score, dtype=np.float64).ravel()[index], kind='stable')
        index = np.sort(index[order[:int(limit)]])
    return index
