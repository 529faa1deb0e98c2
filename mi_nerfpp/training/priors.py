"""Regularizers of the radiance fields (added to the colour loss by :mod:`.train`).

* :func:`cauchy_sparsity` — Plenoxels' sparsity prior ``log(1 + 2σ²)`` of the density at
  random points (:func:`random_points`): it saturates for surfaces, so a thin opaque surface
  costs little while a volume of haze costs in every cell it fills. It removes the foreground
  veil that the background would otherwise compensate for.
* :func:`ray_distortion` — mip-NeRF 360's distortion loss (:func:`distortion`) of whole rays,
  both volumes on one axis: it gathers the weights along a ray against floaters and haze.

Each is differentiable in its inputs. The priors that were measured and not kept (total
variation, opacity entropy, far-field smoothness, the harmonic fill of unseen cells) are
recorded in docs/experiments.md.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_nerfpp.core.sampling import flat_index


def cauchy_sparsity(density):
    """Mean of ``log(1 + 2σ²)`` over density samples ``σ`` (Float)."""
    return dr.mean(dr.log(1.0 + 2.0 * dr.square(density)))


def random_points(domain, u):
    """Field inputs of uniform random points of a volume's domain from 4 uniform Floats ``u``:
    the cube ``[-1, 1]³`` around the unit ball, or a uniform direction and ``s ∈ [0, 1)``."""
    if domain == 'ball':
        return [dr.fma(c, 2.0, -1.0) for c in u[:3]]
    d = mi.warp.square_to_uniform_sphere(mi.Point2f(u[0], u[1]))
    return [d.x, d.y, d.z, u[2]]


class Sparsity:
    """The sparsity prior of both volumes: :func:`cauchy_sparsity` of each volume's density at
    random points, with a weight and a start (fraction of the run after which it applies) per
    volume, ``(foreground, background)``. It says which volumes it applies to at a point of
    the run (:meth:`active`); a step draws 4 uniform Floats per point of those
    (:meth:`draw`), and the loss reads only what was drawn (:meth:`loss`)."""

    def __init__(self, weights, starts):
        self.weights, self.starts = tuple(weights), tuple(starts)

    def active(self, fields, progress: float) -> list[bool]:
        """Per volume: whether the prior applies at ``progress`` (a field, a weight, started)."""
        return [field is not None and weight > 0 and progress >= start
                for field, weight, start in zip(fields, self.weights, self.starts)]

    def draw(self, gen, n: int, fields, progress: float):
        """Per volume, ``n`` random points as 4 uniform Floats from ``gen`` (a Dr.Jit
        generator), or None where the prior does not apply."""
        return [[gen.random(mi.Float, n) for _ in range(4)] if on else None
                for on in self.active(fields, progress)]

    def loss(self, fields, points):
        """The weighted prior of the volumes that have ``points`` (:meth:`draw`)."""
        total = mi.Float(0.0)
        for field, weight, u in zip(fields, self.weights, points):
            if u is not None:
                total += weight * cauchy_sparsity(field.density(random_points(field.domain, u)))
        return total


def distortion(w, m, n):
    """Distortion loss of mip-NeRF 360 (Barron et al. 2022, Eq. 15) per ray, in O(n).

    ``Σ_ij w_i w_j |m_i − m_j| + ⅓ Σ_i w_i² δ_i`` over sorted sample positions ``m``
    (normalized to [0, 1] along the volume) with ``δ_i = m_{i+1} − m_i``: small when
    the weight of a ray is concentrated in one compact interval, so it removes
    floaters and haze. The pairwise sum is ``2 Σ_i w_i (m_i Σ_{j<i} w_j − Σ_{j<i} w_j m_j)``.
    """
    n_rays = dr.width(w) // n
    ray, k = flat_index(n_rays, n)
    last = k == n - 1
    m_next = dr.gather(mi.Float, m, ray * n + k + 1, ~last)
    delta = dr.select(last, dr.maximum(1.0 - m, 0.0), m_next - m)
    w_before = dr.block_prefix_sum(w, n, exclusive=True)
    wm_before = dr.block_prefix_sum(w * m, n, exclusive=True)
    per_sample = 2.0 * w * (m * w_before - wm_before) + (1.0 / 3.0) * dr.square(w) * delta
    return dr.block_sum(per_sample, n)


def ray_distortion(res):
    """Distortion loss of whole rays (Float per ray): both volumes' fine samples on one axis,
    the foreground chord on ``[0, ½)`` and the background's ``v = 1 − s/s_max`` on
    ``[½, 1)``, with weights ``w_fg`` and ``λ·w_bg`` (Eq. 4's share of each volume).

    Unlike the loss of each volume on its own, it sees a ray whose weight is split between a
    surface in the foreground and another in the background as spread out (mip-NeRF 360
    applies it to the whole ray likewise), so it favours one volume owning a surface over a
    half-transparent foreground in front of a background that paints the rest."""
    fg, bg = res.fg, res.bg
    if bg is None:
        return distortion(fg.weights, fg.position, fg.n)
    if bg.rays is not None:
        raise ValueError('ray_distortion needs the background of every ray (no skip_occluded)')
    n_rays = dr.width(fg.shading.opacity)
    n = fg.n + bg.n
    ray, k = flat_index(n_rays, n)
    in_fg = k < fg.n
    i_fg, i_bg = ray * fg.n + k, ray * bg.n + (k - fg.n)
    lam = dr.gather(mi.Float, 1.0 - fg.shading.opacity, ray)
    w = dr.select(in_fg, dr.gather(mi.Float, fg.weights, i_fg, in_fg),
                  lam * dr.gather(mi.Float, bg.weights, i_bg, ~in_fg))
    m = dr.select(in_fg, 0.5 * dr.gather(mi.Float, fg.position, i_fg, in_fg),
                  dr.fma(0.5, dr.gather(mi.Float, bg.position, i_bg, ~in_fg), 0.5))
    return distortion(w, m, n)
