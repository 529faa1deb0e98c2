"""Tests for the ray geometry of NeRF++ (mi_nerfpp.core.geometry), against closed forms in float64."""
from __future__ import annotations

import numpy as np
import pytest

import mi_nerfpp  # noqa: F401  (sets up libLLVM and the llvm_ad_rgb variant)
import drjit as dr
import mitsuba as mi

from mi_nerfpp.core import geometry as geo

N_RAYS = 300


# ----------------------------------------------------------------------------- helpers

def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def random_rays(n=N_RAYS, r_max=0.95, seed=0):
    """Origins uniform in the ball |o| < r_max, unit directions; float32-exact float64 arrays."""
    rng = np.random.default_rng(seed)
    o = unit(rng.normal(size=(n, 3))) * (r_max * rng.uniform(size=(n, 1)) ** (1 / 3))
    d = unit(rng.normal(size=(n, 3)))
    return o.astype(np.float32).astype(np.float64), d.astype(np.float32).astype(np.float64)


def P(a):
    a = np.asarray(a, dtype=np.float32).reshape(-1, 3)
    return mi.Point3f(mi.Float(a[:, 0]), mi.Float(a[:, 1]), mi.Float(a[:, 2]))


def V(a):
    a = np.asarray(a, dtype=np.float32).reshape(-1, 3)
    return mi.Vector3f(mi.Float(a[:, 0]), mi.Float(a[:, 1]), mi.Float(a[:, 2]))


def F(a):
    return mi.Float(np.asarray(a, dtype=np.float32).ravel())


def np3(x):
    """A Dr.Jit 3-vector array as an (N, 3) float64 numpy array."""
    return np.asarray(x, dtype=np.float64).reshape(3, -1).T


def np1(x):
    return np.asarray(x, dtype=np.float64).ravel()


def reference(o, d):
    """float64 closed forms: t_b, p_m, b, t_in, t_out."""
    t_b = -np.sum(o * d, axis=1)
    p_m = o + t_b[:, None] * d
    b = np.linalg.norm(p_m, axis=1)
    half = np.sqrt(np.maximum(1 - b * b, 0.0))
    return t_b, p_m, b, t_b - half, t_b + half


@pytest.fixture(scope='module')
def rays():
    return random_rays()


# ----------------------------------------------------------------------------- sphere chord

def test_closest_approach_matches_closed_form(rays):
    o, d = rays
    t_b, p_m, b = geo.closest_approach(P(o), V(d))
    rt_b, rp_m, rb, _, _ = reference(o, d)
    np.testing.assert_allclose(np1(t_b), rt_b, atol=1e-6)
    np.testing.assert_allclose(np3(p_m), rp_m, atol=1e-6)
    np.testing.assert_allclose(np1(b), rb, atol=1e-6)
    # p_m is the point of closest approach: perpendicular to the ray, no farther than o.
    np.testing.assert_allclose(np.sum(np3(p_m) * d, axis=1), 0.0, atol=1e-6)
    assert np.all(np1(b) <= np.linalg.norm(o, axis=1) + 1e-6)


def test_unit_sphere_chord_points_are_on_the_sphere(rays):
    o, d = rays
    t_in, t_out, hit = geo.unit_sphere_chord(P(o), V(d))
    t_in, t_out, hit = np1(t_in), np1(t_out), np.asarray(hit)
    assert hit.all()
    assert np.all(t_out > 0) and np.all(t_in < 0)
    for t in (t_in, t_out):
        np.testing.assert_allclose(np.linalg.norm(o + t[:, None] * d, axis=1), 1.0, atol=2e-6)
    _, _, _, rt_in, rt_out = reference(o, d)
    np.testing.assert_allclose(t_out, rt_out, atol=2e-6)
    np.testing.assert_allclose(t_in, rt_in, atol=2e-6)


def test_unit_sphere_chord_reports_a_miss():
    o = np.array([[0.0, 1.5, -3.0], [0.0, 0.5, -3.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    t_in, t_out, hit = geo.unit_sphere_chord(P(o), V(d))
    assert list(np.asarray(hit)) == [False, True]
    h = np.sqrt(1 - 0.25)
    np.testing.assert_allclose(np1(t_in)[1], 3 - h, atol=1e-6)
    np.testing.assert_allclose(np1(t_out)[1], 3 + h, atol=1e-6)


# ----------------------------------------------------------------------------- inverted sphere

def test_direction_closed_form_equals_paper_rotation(rays):
    o, d = rays
    rng = np.random.default_rng(1)
    s = 1.0 - rng.uniform(size=len(o))                  # (0, 1]
    _, p_m, b = geo.closest_approach(P(o), V(d))
    x_closed = np3(geo.inverted_sphere_direction(p_m, b, V(d), F(s)))
    x_rot = np3(geo.inverted_sphere_direction_by_rotation(P(o), V(d), F(s)))
    # The rotation axis b x d is ill-conditioned as b -> 0 (the paper's singularity).
    ok = np1(b) > 1e-2
    assert ok.sum() > 0.9 * len(o)
    np.testing.assert_allclose(x_closed[ok], x_rot[ok], atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(x_closed, axis=1), 1.0, atol=1e-6)


def test_inverted_sphere_point_has_radius_one_over_s_and_direction_x_hat(rays):
    o, d = rays
    rng = np.random.default_rng(2)
    s = np.concatenate([1.0 - rng.uniform(size=len(o)),              # (0, 1]
                        10.0 ** rng.uniform(-3, 0, size=len(o))])    # log-spread down to 1e-3
    o2, d2 = np.concatenate([o, o]), np.concatenate([d, d])
    t_b, p_m, b = geo.closest_approach(P(o2), V(d2))
    t = np1(geo.inverted_sphere_distance(t_b, b, F(s)))
    x_hat = np3(geo.inverted_sphere_direction(p_m, b, V(d2), F(s)))
    s32 = s.astype(np.float32).astype(np.float64)
    p = o2 + t[:, None] * d2                                      # float64
    r = np.linalg.norm(p, axis=1)
    np.testing.assert_allclose(r * s32, 1.0, rtol=2e-6, atol=0)
    np.testing.assert_allclose(x_hat, p / r[:, None], atol=3e-6)
    # The outgoing root: the point lies beyond the sphere exit.
    _, _, _, _, t_out = reference(o2, d2)
    assert np.all(t >= t_out - 1e-5)


def test_s_one_gives_exit_point_and_s_to_zero_gives_direction(rays):
    o, d = rays
    n = len(o)
    t_b, p_m, b = geo.closest_approach(P(o), V(d))
    _, _, _, _, t_out = reference(o, d)
    exit_point = o + t_out[:, None] * d
    x1 = np3(geo.inverted_sphere_direction(p_m, b, V(d), F(np.ones(n))))
    np.testing.assert_allclose(x1, exit_point, atol=2e-6)
    np.testing.assert_allclose(np1(geo.inverted_sphere_distance(t_b, b, F(np.ones(n)))), t_out,
                               atol=2e-6)
    x0 = np3(geo.inverted_sphere_direction(p_m, b, V(d), F(np.full(n, 1e-7))))
    np.testing.assert_allclose(x0, d, atol=1e-6)
    # The paper's rotation agrees at both ends too (rays with b well away from 0).
    ok = np1(b) > 1e-2
    xr1 = np3(geo.inverted_sphere_direction_by_rotation(P(o), V(d), F(np.ones(n))))
    xr0 = np3(geo.inverted_sphere_direction_by_rotation(P(o), V(d), F(np.full(n, 1e-7))))
    np.testing.assert_allclose(xr1[ok], exit_point[ok], atol=1e-5)
    np.testing.assert_allclose(xr0[ok], d[ok], atol=1e-5)


def test_distance_increases_strictly_as_s_falls(rays):
    o, d = rays
    n = len(o)
    s_grid = np.geomspace(1.0, 1e-3, 48)                           # decreasing
    t_b, _, b = geo.closest_approach(P(o), V(d))
    idx = mi.UInt32(np.repeat(np.arange(n), len(s_grid)).astype(np.uint32))
    t = geo.inverted_sphere_distance(dr.gather(mi.Float, t_b, idx), dr.gather(mi.Float, b, idx),
                                     F(np.tile(s_grid, n)))
    t = np1(t).reshape(n, len(s_grid))
    assert np.all(np.diff(t, axis=1) > 0)
    # And it grows like 1/s far away.
    np.testing.assert_allclose(t[:, -1], 1e3 + np1(t_b), rtol=1e-5)


@pytest.mark.parametrize('o', [[0.0, 0.0, 0.0], [0.0, 0.0, -0.5], [0.3, -0.2, 0.6]])
def test_ray_through_the_origin(o):
    """b = 0: the closed form is regular, x̂ = d for every s, |t(s)·d + o| = 1/s."""
    o = np.array(o, dtype=np.float64)
    d = unit(o) if np.any(o) else np.array([0.0, 0.0, 1.0])
    d = d.astype(np.float32).astype(np.float64)
    o = o.astype(np.float32).astype(np.float64)
    s = np.array([1.0, 0.7, 0.3, 0.05, 1e-3])
    m = len(s)
    t_b, p_m, b = geo.closest_approach(P(np.tile(o, (m, 1))), V(np.tile(d, (m, 1))))
    x = np3(geo.inverted_sphere_direction(p_m, b, V(np.tile(d, (m, 1))), F(s)))
    t = np1(geo.inverted_sphere_distance(t_b, b, F(s)))
    assert np.all(np.isfinite(x)) and np.all(np.isfinite(t))
    assert np.all(np1(b) < 1e-6)
    np.testing.assert_allclose(x, np.tile(d, (m, 1)), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(o + t[:, None] * d, axis=1) * s, 1.0, rtol=2e-6)


# ----------------------------------------------------------------------------- intervals

def test_inside_origins_interval_and_s_max(rays):
    o, d = rays
    _, _, _, _, t_out = reference(o, d)
    t0, t1 = geo.foreground_interval(P(o), V(d))
    np.testing.assert_array_equal(np1(t0), 0.0)
    np.testing.assert_allclose(np1(t1), t_out, atol=2e-6)
    t0, t1 = geo.foreground_interval(P(o), V(d), near=0.02)
    np.testing.assert_array_equal(np1(t0), np.float32(0.02))
    np.testing.assert_allclose(np1(t1), t_out, atol=2e-6)
    np.testing.assert_array_equal(np1(geo.background_s_max(P(o), V(d))), 1.0)


def test_near_beyond_the_sphere_gives_an_empty_segment():
    o, d = np.array([[0.0, 0.0, 0.5]]), np.array([[0.0, 0.0, 1.0]])
    t0, t1 = geo.foreground_interval(P(o), V(d), near=2.0)
    assert np1(t0)[0] == np1(t1)[0] == 2.0


def outside_rays(seed):
    rng = np.random.default_rng(seed)
    n = 200
    o = unit(rng.normal(size=(n, 3))) * rng.uniform(1.2, 5.0, size=(n, 1))
    return o, rng


def test_outside_origin_moving_away():
    o, rng = outside_rays(3)
    # Directions with o·d > 0: the ray only recedes from the sphere.
    d = unit(rng.normal(size=o.shape))
    d = np.where(np.sum(o * d, axis=1, keepdims=True) < 0, -d, d)
    o, d = o.astype(np.float32).astype(np.float64), d.astype(np.float32).astype(np.float64)
    t0, t1 = geo.foreground_interval(P(o), V(d))
    assert np.all(np1(t1) == np1(t0))
    s_max = np1(geo.background_s_max(P(o), V(d)))
    np.testing.assert_allclose(s_max, 1.0 / np.linalg.norm(o, axis=1), rtol=2e-6)
    # The outgoing part starts at the origin itself: t(s_max) = 0 (float32 sqrt(1/s² - b²)
    # cancels for rays nearly tangent to the radius sphere: absolute error ~ sqrt(eps)·|o|).
    t_b, _, b = geo.closest_approach(P(o), V(d))
    t_start = np1(geo.inverted_sphere_distance(t_b, b, F(s_max)))
    np.testing.assert_allclose(t_start, 0.0, atol=3e-3)
    assert np.median(np.abs(t_start)) < 1e-5


def test_outside_origin_hitting_the_sphere():
    o, rng = outside_rays(4)
    # Aim at a random point inside the sphere: the ray crosses it ahead of the origin.
    target = unit(rng.normal(size=o.shape)) * 0.9 * rng.uniform(size=(len(o), 1))
    d = unit(target - o)
    o, d = o.astype(np.float32).astype(np.float64), d.astype(np.float32).astype(np.float64)
    _, _, b, t_in, t_out = reference(o, d)
    assert np.all(b < 0.9 + 1e-6) and np.all(t_in > 0)
    t0, t1 = geo.foreground_interval(P(o), V(d))
    np.testing.assert_allclose(np1(t0), t_in, atol=5e-6)
    np.testing.assert_allclose(np1(t1), t_out, atol=5e-6)
    np.testing.assert_array_equal(np1(geo.background_s_max(P(o), V(d))), 1.0)


def test_outside_origin_missing_the_sphere():
    o, rng = outside_rays(5)
    # Build rays by their closest point: p_m at radius b > 1, reached at t_b > 0.
    n = len(o)
    u = unit(rng.normal(size=(n, 3)))
    dd = unit(np.cross(u, unit(rng.normal(size=(n, 3)))))        # perpendicular to u
    b_true = rng.uniform(1.05, 3.0, size=n)
    t_b_true = rng.uniform(0.1, 4.0, size=n)
    o = b_true[:, None] * u - t_b_true[:, None] * dd
    o, d = o.astype(np.float32).astype(np.float64), dd.astype(np.float32).astype(np.float64)
    t_b, _, b, _, _ = reference(o, d)
    t0, t1 = geo.foreground_interval(P(o), V(d))
    _, _, hit = geo.unit_sphere_chord(P(o), V(d))
    assert not np.asarray(hit).any()
    assert np.all(np1(t1) == np1(t0))
    s_max = np1(geo.background_s_max(P(o), V(d)))
    np.testing.assert_allclose(s_max, 1.0 / b, rtol=3e-6)
    # The outgoing part starts at the closest approach: t(s_max) = t_b.
    mt_b, _, mb = geo.closest_approach(P(o), V(d))
    np.testing.assert_allclose(np1(geo.inverted_sphere_distance(mt_b, mb, F(s_max))), t_b,
                               atol=5e-3)


# ----------------------------------------------------------------------------- equirect

@pytest.mark.parametrize('x, uv', [
    ([1, 0, 0], (0.5, 0.5)),
    ([0, 1, 0], (0.75, 0.5)),
    ([0, -1, 0], (0.25, 0.5)),
    ([-1, 0, 0], (1.0, 0.5)),
])
def test_equirect_on_the_equator(x, uv):
    u, v = geo.direction_to_equirect(V(np.array(x, dtype=np.float64)))
    assert np1(u)[0] == pytest.approx(uv[0], abs=1e-6)
    assert np1(v)[0] == pytest.approx(uv[1], abs=1e-6)


def test_equirect_poles():
    _, v = geo.direction_to_equirect(V(np.array([[0, 0, 1], [0, 0, -1], [0.6, 0, 0.8]])))
    np.testing.assert_allclose(np1(v), [0.0, 1.0, np.arccos(0.8) / np.pi], atol=1e-6)


def test_equirect_range_and_round_trip():
    rng = np.random.default_rng(6)
    x = unit(rng.normal(size=(500, 3))).astype(np.float32).astype(np.float64)
    u, v = geo.direction_to_equirect(V(x))
    u, v = np1(u), np1(v)
    assert np.all((u >= 0) & (u <= 1) & (v >= 0) & (v <= 1))
    phi, theta = (u - 0.5) * 2 * np.pi, v * np.pi
    back = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)
    np.testing.assert_allclose(back, x, atol=2e-6)
    # Slightly non-unit inputs (float rounding) must not produce NaN at the poles.
    _, v = geo.direction_to_equirect(V(np.array([[0, 0, 1.0000001], [0, 0, -1.0000001]])))
    np.testing.assert_allclose(np1(v), [0.0, 1.0], atol=1e-6)


def test_ball_warp_magnifies_the_inner_ball_and_keeps_the_sphere():
    """Closed form of the piecewise-linear radial warp: the inner ball of radius r0 fills half the
    radius, the unit sphere stays in place, radii are monotonic and directions unchanged."""
    from mi_nerfpp.core.geometry import BALL_WARP_SHARE, ball_warp
    r0 = 0.3
    rng = np.random.default_rng(3)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = np.linspace(0.0, 1.0, 400)
    p = d * r[:, None]
    q = np.stack([np.array(c) for c in ball_warp([mi.Float(p[:, i]) for i in range(3)], r0)], 1)
    rq = np.linalg.norm(q, axis=1)
    expect = np.where(r <= r0, r * BALL_WARP_SHARE / r0,
                      BALL_WARP_SHARE + (1 - BALL_WARP_SHARE) * (r - r0) / (1 - r0))
    np.testing.assert_allclose(rq, expect, atol=1e-6)
    assert np.all(np.diff(rq) > 0)
    inside = r > 1e-3
    np.testing.assert_allclose(q[inside] / rq[inside, None], d[inside], atol=1e-5)
    np.testing.assert_allclose(ball_warp([mi.Float(0.5)] * 3, 0.0)[0], [0.5])
