"""Ray geometry of NeRF++ (paper §4): the unit sphere and the inverted sphere.

Pure functions on Dr.Jit arrays. Rays are ``r(t) = o + t·d`` with ``|d| = 1``.

Foreground: the part of the ray inside the unit sphere.
Background: the part outside it, parametrized by the inverse radius ``s = 1/r``
(``s = 1`` on the sphere, ``s -> 0`` at infinity). A point of the background is
described by ``(x̂, s)``: its direction ``x̂ = p/|p|`` on the unit sphere and ``s``.

Rays whose origin is outside the unit sphere (any Mitsuba sensor may place one
there) are handled as follows, and tested:

* foreground: the chord inside the sphere in front of the origin, if any;
* background: the *outgoing* part of the ray, ``t >= max(t_b, 0)`` beyond the
  sphere, i.e. ``s ∈ (0, s_max]`` with ``s_max = 1 / max(1, r_start)`` where
  ``r_start`` is the radius at which that part starts. The incoming part of a
  ray that approaches the origin from outside the sphere is not integrated.
For origins inside the sphere this reduces to NeRF++ exactly (``s_max = 1``).
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np


def closest_approach(o, d):
    """Closest approach of the ray to the origin.

    Returns ``(t_b, p_m, b)``: the ray distance ``t_b = -(o·d)``, the point
    ``p_m = o + t_b·d`` (the chord midpoint, the paper's **b**) and its norm ``b``.
    """
    t_b = -dr.dot(o, d)
    p_m = dr.fma(d, t_b, o)
    return t_b, p_m, dr.norm(p_m)


def unit_sphere_chord(o, d):
    """Ray distances ``(t_in, t_out, hit)`` where the ray enters and leaves the unit sphere.

    ``t_out = t_b + sqrt(1 - b²)`` is the exit distance ``t'`` of the paper.
    ``hit`` is False when the line misses the sphere (``b >= 1``).
    """
    t_b, _, b = closest_approach(o, d)
    half = dr.safe_sqrt(1.0 - b * b)
    return t_b - half, t_b + half, b < 1.0


def foreground_interval(o, d, near=0.0):
    """Distances ``(t0, t1)`` of the foreground segment: the ray inside the unit sphere.

    ``t0 = max(t_in, near)``, ``t1 = t_out``; an empty segment (a miss, or a sphere
    behind the origin) has ``t1 == t0``, so it contributes nothing.
    """
    t_in, t_out, hit = unit_sphere_chord(o, d)
    t0 = dr.maximum(t_in, near)
    t1 = dr.select(hit, dr.maximum(t_out, t0), t0)
    return t0, t1


def background_s_max(o, d):
    """Largest inverse radius ``s_max`` on the outgoing part of the ray outside the sphere.

    1 for origins inside the unit sphere (and for outside origins whose ray
    still crosses the sphere ahead of them); ``1/|o|`` for an outside origin
    moving away; ``1/b`` for an outside origin whose ray misses the sphere.
    """
    t_b, _, b = closest_approach(o, d)
    behind = dr.maximum(-t_b, 0.0)
    r_start = dr.sqrt(dr.fma(b, b, behind * behind))
    return dr.rcp(dr.maximum(r_start, 1.0))


def inverted_sphere_direction(p_m, b, d, s):
    """Direction ``x̂ = p/|p|`` of the ray point at inverse radius ``s`` (closed form).

    ``x̂ = s·p_m + sqrt(1 - b²s²)·d``. Equal to the paper's construction (rotate
    the exit point about ``b × d`` by ``ω = asin(b) - asin(b·s)``, see
    :func:`inverted_sphere_direction_by_rotation`) but cheaper and without a
    singularity for rays through the origin. ``|x̂| = 1``; ``s = 1`` gives the
    exit point; ``s -> 0`` gives ``d``.
    """
    return dr.fma(p_m, s, dr.safe_sqrt(1.0 - dr.square(b * s)) * d)


def inverted_sphere_distance(t_b, b, s):
    """Ray distance ``t(s) = t_b + sqrt(1/s² - b²)`` of the point at inverse radius ``s``."""
    return t_b + dr.safe_sqrt(dr.rcp(dr.square(s)) - b * b)


def inverted_sphere_direction_by_rotation(o, d, s):
    """The paper's construction of ``x̂`` (§4), kept as an independent check.

    Rotate the exit point ``a`` about the axis ``b × d`` by
    ``ω = asin|b| - asin(|b|·s)`` (Rodrigues; ``a ⟂ axis``). Undefined when the ray
    passes through the origin (``b = 0``), where the closed form is used instead.
    """
    t_b, p_m, b = closest_approach(o, d)
    _, t_out, _ = unit_sphere_chord(o, d)
    a = dr.fma(d, t_out, o)
    axis = dr.normalize(dr.cross(p_m, d))
    omega = dr.asin(b) - dr.asin(b * s)
    sin_w, cos_w = dr.sincos(omega)
    return a * cos_w + dr.cross(axis, a) * sin_w


def direction_to_equirect(x):
    """Unit vector -> ``(u, v) ∈ [0,1]²``: longitude ``atan2(y, x)/2π + ½``, colatitude ``acos(z)/π``."""
    u = dr.fma(dr.atan2(x.y, x.x), 0.5 / dr.pi, 0.5)
    v = dr.acos(dr.clip(x.z, -1.0, 1.0)) * (1.0 / dr.pi)
    return u, v


# Share of the foreground grid's radius that :func:`ball_warp` gives to the inner ball.
BALL_WARP_SHARE = 0.5


def ball_warp(p, inner_radius):
    """Radial, piecewise-linear warp of the unit ball onto itself that magnifies the inner ball.

    Points within ``inner_radius`` are scaled by ``BALL_WARP_SHARE / inner_radius`` (the inner
    ball fills that share of the radius); the shell beyond is mapped linearly in radius onto the
    rest. Continuous and monotonic, so a grid indexed by the warped point spends more cells on
    the centre of a 360° capture, where its cameras look, and fewer near the cameras.
    ``inner_radius = 0`` is the identity.
    """
    if inner_radius <= 0:
        return list(p)
    r = dr.norm(mi.Vector3f(*p))
    k = BALL_WARP_SHARE
    outer = k + (1.0 - k) * (r - inner_radius) / (1.0 - inner_radius)
    scale = dr.select(r <= inner_radius, k / inner_radius, outer / dr.maximum(r, 1e-12))
    return [c * scale for c in p]


def grid_coordinates(domain, x):
    """A volume's field inputs -> grid coordinates in ``[0, 1]³``, ordered (x, y, z) of a texture:
    the ball ``[-1, 1]³`` scaled to the unit cube; the inverted sphere ``(x̂, s)`` as
    (longitude, colatitude, s) of :func:`direction_to_equirect`."""
    if domain == 'ball':
        return [dr.fma(c, 0.5, 0.5) for c in x]
    u, v = direction_to_equirect(mi.Vector3f(x[0], x[1], x[2]))
    return [u, v, x[3]]


__all__ = [
    'closest_approach', 'unit_sphere_chord', 'foreground_interval', 'background_s_max',
    'inverted_sphere_direction', 'inverted_sphere_distance',
    'inverted_sphere_direction_by_rotation', 'direction_to_equirect', 'grid_coordinates',
    'ball_warp', 'BALL_WARP_SHARE',
]


def pixel_footprint(ray):
    """The pixel footprint of camera rays (Mitsuba ``RayDifferential3f``): the width of a pixel
    per unit distance, ``sqrt(|(d_x − d) × (d_y − d)|)`` with ``d_x, d_y`` the directions
    through the neighbouring pixels (the square root of the pixel's solid angle); None for
    rays without differentials. Per ray, whatever the samples per pixel: a pixel's samples
    together cover the pixel."""
    if not getattr(ray, 'has_differentials', False):
        return None
    d = dr.normalize(mi.Vector3f(dr.detach(ray.d)))
    dx = dr.normalize(mi.Vector3f(dr.detach(ray.d_x))) - d
    dy = dr.normalize(mi.Vector3f(dr.detach(ray.d_y))) - d
    return dr.sqrt(dr.norm(dr.cross(dx, dy)))


# ----------------------------------------------------------------------------- Nuke

def nuke_rotation(c2w_gl):
    """Euler angles (degrees) of a camera-to-world rotation for Nuke's rotation order ZXY
    (``R = Ry·Rx·Rz``, column vectors)."""
    R = np.asarray(c2w_gl, dtype=np.float64)[:3, :3]
    rx = math.asin(max(-1.0, min(1.0, -R[1, 2])))
    ry = math.atan2(R[0, 2], R[2, 2])
    rz = math.atan2(R[1, 0], R[1, 1])
    return np.degrees([rx, ry, rz])


def rotation_zxy(rx, ry, rz):
    """The rotation matrix of Nuke's ZXY order from degrees (the inverse of
    :func:`nuke_rotation`)."""
    x, y, z = np.radians([rx, ry, rz])
    Rx = np.array([[1, 0, 0], [0, math.cos(x), -math.sin(x)], [0, math.sin(x), math.cos(x)]])
    Ry = np.array([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    Rz = np.array([[math.cos(z), -math.sin(z), 0], [math.sin(z), math.cos(z), 0], [0, 0, 1]])
    return Ry @ Rx @ Rz
