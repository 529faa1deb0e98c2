"""Regularizers of the radiance fields (added to the colour loss by :mod:`.train`).

* :func:`cauchy_sparsity` — Plenoxels' sparsity prior ``log(1 + 2σ²)`` of the density at
  random points: it saturates for surfaces, so a thin opaque surface costs little while a
  volume of haze costs in every cell it fills. It removes the foreground veil that the
  background would otherwise compensate for (see the README's tuning table).
* :func:`opacity_entropy` — binary entropy of a ray's foreground opacity, minimal at 0 and 1.
* :func:`grid_tv` — total variation of a feature grid on random cells.
* :func:`far_field_smoothness` — smoothness of the background's far slice (``s = 0``), which
  directions no training view saw show.

Each returns a scalar Float (a mean), differentiable in its inputs.

Cells that no training sample reaches get no gradient from any of these: they keep what they
started with. :func:`unseen_fill` moves them instead, one step of descent on
:func:`dirichlet_energy` restricted to them (a harmonic fill, as inpainting does), so that
places and directions no photo constrains continue their surroundings smoothly.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

ENTROPY_EPSILON = 1e-4


def cauchy_sparsity(density):
    """Mean of ``log(1 + 2σ²)`` over density samples ``σ`` (Float)."""
    return dr.mean(dr.log(1.0 + 2.0 * dr.square(density)))


def opacity_entropy(opacity):
    """Mean binary entropy ``-(a log a + (1 - a) log(1 - a))`` of opacities, clamped away from 0
    and 1 by ENTROPY_EPSILON."""
    a = dr.clip(opacity, ENTROPY_EPSILON, 1.0 - ENTROPY_EPSILON)
    return dr.mean(-(a * dr.log(a) + (1.0 - a) * dr.log(1.0 - a)))


def grid_tv(grid, cells):
    """Mean squared difference between cells and their +x, +y, +z neighbours (clamped at the
    border), over the cell indices ``cells`` (UInt32) of a (Z, Y, X, C) grid tensor, averaged
    over the channels."""
    Z, Y, X, C = grid.shape
    x = cells % X
    y = (cells // X) % Y
    z = cells // (X * Y)
    total = mi.Float(0.0)
    for c in range(C):
        def at(zz, yy, xx):
            return dr.gather(mi.Float, grid.array, ((zz * Y + yy) * X + xx) * C + c)
        v = at(z, y, x)
        for n in (at(z, y, dr.minimum(x + 1, X - 1)), at(z, dr.minimum(y + 1, Y - 1), x),
                  at(dr.minimum(z + 1, Z - 1), y, x)):
            total += dr.mean(dr.square(n - v))
    return total / C


def far_field_smoothness(grid):
    """Mean squared difference of neighbouring cells (longitude, periodic, and colatitude) in
    the far slice ``s = 0`` of a background grid tensor of shape (S, colatitude, longitude, C),
    over its feature channels (1..C-1).

    What a ray sees where the background holds no surface is the far slice: the infinite last
    interval takes all the light left. Directions no training view saw leave their cells there
    as they were initialized, and render as blocks of arbitrary colour; this prior diffuses the
    neighbours' features into them (a smooth continuation). Adam rescales each cell's gradient,
    so a small weight moves unconstrained cells as fast as any, while the cells the photos
    constrain hardly notice it."""
    S, Y, X, C = grid.shape
    i = dr.arange(mi.UInt32, Y * X)
    y, x = i // X, i % X

    def at(yy, xx, c):
        return dr.gather(mi.Float, grid.array, (yy * X + xx) * C + c)

    total = mi.Float(0.0)
    for c in range(1, C):
        v = at(y, x, c)
        east = at(y, dr.select(x + 1 == X, 0, x + 1), c)
        south = at(dr.minimum(y + 1, Y - 1), x, c)
        total += dr.mean(dr.square(east - v)) + dr.mean(dr.square(south - v))
    return total / (C - 1)


def _neighbours(shape, periodic):
    """For each entry of a (Z, Y, X, C) grid tensor: the flat indices of the same channel in
    the six neighbouring cells (-x, +x, -y, +y, -z, +z), periodic along X when
    ``periodic`` (the background's longitude), the entry itself past a clamped border."""
    Z, Y, X, C = shape
    i = dr.arange(mi.UInt32, Z * Y * X * C)
    c, cell = i % C, i // C
    x, y, z = cell % X, (cell // X) % Y, cell // (X * Y)

    def step(v, n, up, wrap):
        edge, beyond = (n - 1, 0) if up else (0, n - 1)
        return dr.select(v == edge, beyond if wrap else edge, v + 1 if up else v - 1)

    def at(zz, yy, xx):
        return ((zz * Y + yy) * X + xx) * C + c

    return [at(z, y, step(x, X, False, periodic)), at(z, y, step(x, X, True, periodic)),
            at(z, step(y, Y, False, False), x), at(z, step(y, Y, True, False), x),
            at(step(z, Z, False, False), y, x), at(step(z, Z, True, False), y, x)]


def dirichlet_energy(grid, periodic=False):
    """``E = Σ (g[n] − g[i])²`` over every entry ``i`` of a (Z, Y, X, C) grid tensor and its
    +x, +y, +z neighbour ``n`` (each pair of neighbouring cells once; periodic along X when
    ``periodic``, no term past a clamped border): the smoothness that :func:`unseen_fill`
    descends on."""
    n = _neighbours(grid.shape, periodic)
    v = grid.array
    total = mi.Float(0.0)
    for j in n[1::2]:
        total += dr.sum(dr.square(dr.gather(mi.Float, v, j) - v))
    return total


def unseen_fill(grid, free, periodic=False):
    """One Jacobi step of the harmonic fill of the entries ``free`` (a Bool per entry) of a
    (Z, Y, X, C) grid tensor: each free entry takes the mean of its six neighbours (see
    :func:`_neighbours`), every other entry stays. That is ``g − ∇E/12`` on the free entries
    (``E``: :func:`dirichlet_energy`), gradient descent on the grid's roughness where nothing
    else pulls, with the constrained entries as the boundary; repeated, it converges to the
    smooth (harmonic) continuation of the constrained cells into the free ones. Returns a new
    tensor."""
    n = _neighbours(grid.shape, periodic)
    v = grid.array
    mean = sum(dr.gather(mi.Float, v, j, free) for j in n) * (1.0 / 6.0)
    return mi.TensorXf(dr.select(free, mean, v), grid.shape)


def random_points(domain, u):
    """Field inputs of uniform random points of a volume's domain from 4 uniform Floats ``u``:
    the cube ``[-1, 1]³`` around the unit ball, or a uniform direction and ``s ∈ [0, 1)``."""
    if domain == 'ball':
        return [dr.fma(c, 2.0, -1.0) for c in u[:3]]
    d = mi.warp.square_to_uniform_sphere(mi.Point2f(u[0], u[1]))
    return [d.x, d.y, d.z, u[2]]
