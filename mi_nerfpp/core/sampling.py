"""Sample placement along rays: stratified samples, inverse-CDF fine samples, merging.

All arrays use one flat layout: sample ``k`` of ray ``r`` (of ``n`` per ray)
sits at index ``r·n + k``. Samples are positions ``v`` along a per-ray
parameter that increases along the ray (``t`` for the foreground; for the
background ``v = 1 - s/s_max``, so that the far end comes last). Sample
positions carry no derivatives: gradients flow through the fields only.
"""
from __future__ import annotations

from typing import NamedTuple

import drjit as dr
import mitsuba as mi

# Added to every coarse weight before building the PDF, so that rays with no
# weight at all still get (uniform) fine samples.
PDF_EPSILON = 1e-5


def flat_index(n_rays, n):
    """``(ray, k)`` index arrays of the flat layout with ``n`` samples per ray."""
    i = dr.arange(mi.UInt32, n_rays * n)
    ray = i // n
    return ray, i - ray * n


def uniforms(seed, n, stream):
    """``n`` uniform variates per ray from per-ray ``seed`` (UInt32), independent per ``stream``.

    Returns None when ``seed`` is None (deterministic placement).
    """
    if seed is None:
        return None
    ray, k = flat_index(dr.width(seed), n)
    # Seeded explicitly: PCG32's constructor would add each lane's index to the state and
    # sequence, so a ray's samples would depend on its place in the batch (on render chunks).
    rng = mi.PCG32(size=dr.width(ray))
    rng.seed(mi.UInt64(dr.gather(mi.UInt32, seed, ray)), mi.UInt64(k * 16 + stream))
    return rng.next_float32()


def per_ray(n_rays, n, count, sample):
    """``count`` per-sample Floats ``sample(ray, k)`` for the samples ``k < n`` of every ray,
    computed in one symbolic loop per ray and written in the flat layout.

    ``ray`` is the identity index there, so the per-ray arrays that ``sample`` gathers with it
    are read directly, once per ray: a per-sample wavefront gathers each of them at every
    sample (the occupied-length inverse reads ten per-ray arrays)."""
    ray = dr.arange(mi.UInt32, n_rays)
    out = [dr.empty(mi.Float, n_rays * n) for _ in range(count)]

    def body(k):
        for array, value in zip(out, sample(ray, k)):
            dr.scatter(array, value, ray * n + k)
        return (k + 1,)
    with dr.suspend_grad():          # sample positions carry no derivatives
        dr.while_loop((dr.zeros(mi.UInt32, n_rays),), lambda k: k < n, body, label='per_ray')
    return out


def stratified_sample(lo, hi, ray, k, n, xi=None):
    """Sample ``k`` of ``n`` stratified samples on ``[lo, hi]`` of rays ``ray`` (see
    :func:`stratified`; ``xi`` per sample in the flat layout, or None)."""
    jitter = 0.5 if xi is None else dr.gather(mi.Float, xi, ray * n + k)
    u = (mi.Float(k) + jitter) * (1.0 / n)
    a, b = dr.gather(mi.Float, lo, ray), dr.gather(mi.Float, hi, ray)
    return dr.fma(u, b - a, a)


def stratified(lo, hi, n, xi=None):
    """``n`` stratified samples per ray on ``[lo, hi]``, sorted along the ray.

    Sample ``k`` lies in the ``k``-th of ``n`` equal strata, at its midpoint when
    ``xi`` is None, else at fraction ``xi`` (Float of size ``rays·n``) within it.
    """
    ray, k = flat_index(dr.width(lo), n)
    return stratified_sample(lo, hi, ray, k, n, xi)


def bin_edges(v, lo, hi, n):
    """Edges ``(e_k, e_{k+1})`` of the bin around each coarse sample ``v_k``.

    Interior edges are midpoints between neighbouring samples; the first and
    last bins reach ``lo`` and ``hi``, so the bins tile the whole segment.
    """
    ray, k = flat_index(dr.width(lo), n)
    i = ray * n + k
    prev = dr.gather(mi.Float, v, i - 1, k > 0)
    nxt = dr.gather(mi.Float, v, i + 1, k < n - 1)
    left = dr.select(k > 0, 0.5 * (prev + v), dr.gather(mi.Float, lo, ray))
    right = dr.select(k < n - 1, 0.5 * (v + nxt), dr.gather(mi.Float, hi, ray))
    return left, right


def cdf_bin(cdf, base, n, value):
    """Flat index of the bin that holds ``value`` in per-ray exclusive CDFs of ``n`` bins
    starting at flat index ``base`` (a vectorized binary search)."""
    # (binary_search also probes index n: the masks keep those reads in bounds.)
    # First bin whose CDF exceeds the value, minus one: the bin that contains it.
    first_above = dr.binary_search(0, n, lambda k: dr.gather(mi.Float, cdf, base + k, k < n) <= value)
    return base + mi.UInt32(dr.maximum(mi.Int32(first_above) - 1, 0))


class FineSampler:
    """Fine samples from the piecewise-constant PDF of the coarse weights (see
    :func:`inverse_cdf`): the per-ray CDF once, then any fine sample ``j`` of any ray
    (:meth:`sample`), in a wavefront or in a loop per ray (:func:`per_ray`)."""

    def __init__(self, v, weights, lo, hi, n_coarse, n_fine, xi=None):
        self.n_coarse, self.n_fine, self.xi = n_coarse, n_fine, xi
        v, weights = dr.detach(v), dr.detach(weights)
        self.p = weights + PDF_EPSILON
        self.total = dr.block_sum(self.p, n_coarse)
        self.cdf = dr.block_prefix_sum(self.p, n_coarse, exclusive=True)     # per-ray, from 0
        self.left, self.right = bin_edges(v, lo, hi, n_coarse)
        dr.eval(self.p, self.total, self.cdf, self.left, self.right)

    def sample(self, ray, j):
        """Fine sample ``j`` of rays ``ray``: the stratified uniform ``u_j = (j + ξ_j)/n_fine``
        through the inverse CDF."""
        n = self.n_fine
        jitter = 0.5 if self.xi is None else dr.gather(mi.Float, self.xi, ray * n + j)
        u = (mi.Float(j) + jitter) * (1.0 / n)
        u_scaled = u * dr.gather(mi.Float, self.total, ray)
        b = cdf_bin(self.cdf, ray * self.n_coarse, self.n_coarse, u_scaled)
        frac = (u_scaled - dr.gather(mi.Float, self.cdf, b)) / dr.gather(mi.Float, self.p, b)
        e0, e1 = dr.gather(mi.Float, self.left, b), dr.gather(mi.Float, self.right, b)
        return dr.fma(dr.clip(frac, 0.0, 1.0), e1 - e0, e0)


def inverse_cdf(v, weights, lo, hi, n_coarse, n_fine, xi=None):
    """Draw ``n_fine`` samples per ray from the piecewise-constant PDF of the coarse weights.

    Bin ``k`` (see :func:`bin_edges`) has probability ``∝ weights_k + ε``.
    Stratified uniforms ``u_j = (j + ξ_j)/n_fine`` are pushed through the
    inverse CDF, so the result is sorted along each ray, and it concentrates
    where the coarse weights are (in the direction of the ray for both volumes:
    no mirrored PDF).
    """
    ray, j = flat_index(dr.width(lo), n_fine)
    return FineSampler(v, weights, lo, hi, n_coarse, n_fine, xi).sample(ray, j)


class MergeOrder(NamedTuple):
    """The merge of two per-ray sorted sample sets (:func:`merge_order`): for every merged slot,
    whether it comes from ``b`` and its flat index there or in ``a``; for every element of ``a``
    and of ``b``, the merged slot it lands in."""
    from_b: object
    index: object
    slot_a: object
    slot_b: object


def merge_order(a, n_a, b, n_b):
    """Merge two per-ray sorted sample sets into one sorted set of ``n_a + n_b`` per ray.

    Returns a :class:`MergeOrder`. Use :func:`gather_merged` to assemble any per-sample
    quantity (differentiably) in merged order, and :func:`split_merged` to take a merged
    quantity back to the elements of ``a`` and ``b``.
    Each element's merged position is its rank: its index in its own set plus
    the number of elements of the other set before it (ties put ``a`` first).
    """
    n_rays = dr.width(a) // n_a
    m = n_a + n_b
    ray_a, k_a = flat_index(n_rays, n_a)
    ray_b, k_b = flat_index(n_rays, n_b)
    before_a = dr.binary_search(0, n_b, lambda k: dr.gather(mi.Float, b, ray_a * n_b + k, k < n_b) < a)
    before_b = dr.binary_search(0, n_a, lambda k: dr.gather(mi.Float, a, ray_b * n_a + k, k < n_a) <= b)
    slot_a, slot_b = ray_a * m + k_a + before_a, ray_b * m + k_b + before_b
    dr.eval(slot_a, slot_b)          # (each later gather would search anew)
    FROM_B = 1 << 31
    source = dr.empty(mi.UInt32, n_rays * m)
    dr.scatter(source, dr.arange(mi.UInt32, n_rays * n_a), slot_a)
    dr.scatter(source, dr.arange(mi.UInt32, n_rays * n_b) | FROM_B, slot_b)
    from_b = (source & FROM_B) != 0
    return MergeOrder(from_b, source & (FROM_B - 1), slot_a, slot_b)


def gather_merged(order, a, b, at=None):
    """Values of ``a`` and ``b`` (same type) in the merged order from :func:`merge_order`, or
    at the merged slots ``at`` (UInt32) only.

    Every element of ``a`` and ``b`` lands in exactly one merged slot, so the gathers of all
    slots are permutations and their reverse-mode derivatives plain scatters
    (``ReduceMode.Permute``: no atomics, no per-thread copies; a training step measured ~18 %
    faster); those of some slots are plain gathers."""
    from_b, index = order.from_b, order.index
    mode = dr.ReduceMode.Permute
    if at is not None:
        from_b, index = dr.gather(mi.Bool, from_b, at), dr.gather(mi.UInt32, index, at)
        mode = dr.ReduceMode.Auto
    tp = type(a)
    return dr.select(from_b, dr.gather(tp, b, index, from_b, mode=mode),
                     dr.gather(tp, a, index, ~from_b, mode=mode))


def split_merged(order, x):
    """A per-sample quantity ``x`` in merged order (:func:`merge_order`) at the elements of ``a``
    and of ``b``: ``(x_a, x_b)``, the inverse of :func:`gather_merged`. (Plain gathers: the
    reverse pass of a ``ReduceMode.Permute`` gather stores its gradient rather than adding it,
    and ``x``, unlike the inputs of :func:`gather_merged`, has other uses.)"""
    tp = type(x)
    return dr.gather(tp, x, order.slot_a), dr.gather(tp, x, order.slot_b)
