"""Regularizers (mi_nerfpp.training.priors): values against hand computation, gradients against central
finite differences."""
from __future__ import annotations

import numpy as np
import pytest

import mi_nerfpp  # noqa: F401
import drjit as dr
import mitsuba as mi

from mi_nerfpp.training import priors


def fd_check(f, x0, eps=1e-3, rtol=2e-2, atol=1e-5):
    """Compare dr.backward of scalar ``f(x)`` with central differences in every entry of ``x0``."""
    x = mi.Float(np.asarray(x0, np.float32))
    dr.enable_grad(x)
    y = f(x)
    dr.backward(y)
    grad = np.array(dr.grad(x))
    fd = []
    for i in range(len(x0)):
        hi, lo = np.array(x0, np.float64), np.array(x0, np.float64)
        hi[i] += eps
        lo[i] -= eps
        fd.append((f(mi.Float(hi.astype(np.float32))).array[0]
                   - f(mi.Float(lo.astype(np.float32))).array[0]) / (2 * eps))
    np.testing.assert_allclose(grad, fd, rtol=rtol, atol=atol)
    return grad


def test_cauchy_sparsity_value_and_gradient():
    sigma = np.array([0.0, 0.3, 2.0, 40.0])
    assert priors.cauchy_sparsity(mi.Float(sigma)).array[0] == pytest.approx(
        np.mean(np.log(1 + 2 * sigma ** 2)), rel=1e-6)
    grad = fd_check(priors.cauchy_sparsity, sigma, eps=1e-2)
    # Saturates: the pull on a surface (σ = 40) is a fraction of the pull on haze (σ = 0.3).
    assert grad[0] == 0 and grad[3] < 0.1 * grad[1]


def test_opacity_entropy_value_and_gradient():
    a = np.array([0.05, 0.3, 0.5, 0.8, 0.97])
    expected = np.mean(-(a * np.log(a) + (1 - a) * np.log(1 - a)))
    assert priors.opacity_entropy(mi.Float(a)).array[0] == pytest.approx(expected, rel=1e-5)
    grad = fd_check(priors.opacity_entropy, a, eps=1e-3)
    # Pushes below one half towards 0 and above one half towards 1.
    assert grad[0] > 0 and grad[1] > 0 and abs(grad[2]) < 1e-4 and grad[3] < 0 and grad[4] < 0
    # Clamped: exact 0 and 1 give a finite value and gradient.
    x = mi.Float([0.0, 1.0])
    dr.enable_grad(x)
    dr.backward(priors.opacity_entropy(x))
    assert np.isfinite(np.array(dr.grad(x))).all()


def test_grid_tv_value_and_gradient():
    rng = np.random.default_rng(0)
    shape = (3, 4, 5, 2)
    g = rng.normal(size=shape).astype(np.float32)
    cells = np.array([0, 7, 33, 59])
    z, y, x = cells // 20, (cells // 5) % 4, cells % 5
    ref = 0.0
    for c in range(2):
        v = g[z, y, x, c]
        for n in (g[z, y, np.minimum(x + 1, 4), c], g[z, np.minimum(y + 1, 3), x, c],
                  g[np.minimum(z + 1, 2), y, x, c]):
            ref += np.mean((n - v) ** 2)
    ref /= 2

    def f(flat):
        return priors.grid_tv(mi.TensorXf(flat, shape), mi.UInt32(cells))
    assert f(mi.Float(g.ravel())).array[0] == pytest.approx(ref, rel=1e-5)
    fd_check(f, g.ravel(), eps=1e-2, atol=1e-4)
    # A constant grid has no variation.
    assert f(mi.Float(np.ones(g.size, np.float32))).array[0] == 0


@pytest.mark.parametrize('domain', ['ball', 'inverted_sphere'])
def test_random_points_cover_the_domain(domain):
    rng = np.random.default_rng(1)
    u = [mi.Float(rng.random(4096, dtype=np.float32)) for _ in range(4)]
    x = np.array([np.array(c) for c in priors.random_points(domain, u)])
    if domain == 'ball':
        assert x.shape == (3, 4096) and np.abs(x).max() <= 1 and np.abs(x.mean(1)).max() < 0.05
    else:
        assert x.shape == (4, 4096)
        np.testing.assert_allclose(np.linalg.norm(x[:3], axis=0), 1, atol=1e-5)
        assert np.abs(x[:3].mean(1)).max() < 0.05 and 0 <= x[3].min() and x[3].max() < 1


def test_far_field_smoothness_value_and_gradient():
    """Squared differences of longitude (periodic) and colatitude neighbours in the s = 0 slice,
    feature channels only: by hand on a 3 x 2 x 4 x 3 grid, and against central differences."""
    rng = np.random.default_rng(7)
    shape = (3, 2, 4, 3)                      # (s, colatitude, longitude, channels)
    g = rng.normal(size=shape)
    far = g[0]
    expected = np.mean([np.mean((np.roll(far[..., c], -1, axis=1) - far[..., c]) ** 2)
                        + np.mean((far[np.minimum(np.arange(2) + 1, 1)][..., c] - far[..., c]) ** 2)
                        for c in (1, 2)])

    def f(x):
        return priors.far_field_smoothness(mi.TensorXf(x, shape))

    assert f(mi.Float(g.ravel().astype(np.float32))).array[0] == pytest.approx(expected, rel=1e-5)
    grad = fd_check(f, g.ravel(), eps=1e-2, rtol=1e-2, atol=1e-4).reshape(shape)
    # Only the far slice's features feel it: not the density channel, not the slices behind.
    assert np.all(grad[1:] == 0) and np.all(grad[..., 0] == 0) and np.abs(grad[0, ..., 1:]).max() > 0


def dirichlet_by_hand(g, periodic):
    """Σ of squared differences between each cell and its +x, +y, +z neighbour (a (Z, Y, X, C)
    array; +x wraps when ``periodic``, no term past a clamped border)."""
    total = np.sum((np.diff(g, axis=0)) ** 2) + np.sum((np.diff(g, axis=1)) ** 2)
    dx = np.roll(g, -1, axis=2) - g if periodic else np.diff(g, axis=2)
    return total + np.sum(dx ** 2)


@pytest.mark.parametrize('periodic', [False, True])
def test_dirichlet_energy_value_and_gradient(periodic):
    rng = np.random.default_rng(3)
    shape = (3, 4, 5, 2)
    g = 0.1 * rng.normal(size=shape)          # E ~ 1: central differences exact (quadratic)

    def f(x):
        return priors.dirichlet_energy(mi.TensorXf(x, shape), periodic)

    assert f(mi.Float(g.ravel().astype(np.float32))).array[0] == pytest.approx(
        dirichlet_by_hand(g, periodic), rel=1e-5)
    fd_check(f, g.ravel(), eps=0.05, rtol=1e-3, atol=1e-4)


@pytest.mark.parametrize('periodic', [False, True])
def test_unseen_fill_is_a_gradient_step_on_the_free_entries(periodic):
    """The fill moves the free entries by −∇E/12 (E: dirichlet_energy, gradient by autodiff)
    and leaves every other entry as it was; repeated, it converges to the harmonic fill:
    between two constrained faces of a slab the free cells end on the straight line."""
    rng = np.random.default_rng(4)
    shape = (3, 4, 5, 2)
    g = rng.normal(size=shape).astype(np.float32)
    free = rng.random(g.size) < 0.5
    x = mi.Float(g.ravel())
    dr.enable_grad(x)
    dr.backward(priors.dirichlet_energy(mi.TensorXf(x, shape), periodic))
    step = g.ravel() - np.array(dr.grad(x)) / 12
    filled = np.array(priors.unseen_fill(mi.TensorXf(g.ravel(), shape), mi.Bool(free),
                                         periodic).array)
    np.testing.assert_allclose(filled[free], step[free], rtol=1e-5, atol=1e-5)
    assert np.array_equal(filled[~free], g.ravel()[~free])
    # Harmonic: values fixed at x = 0 (0) and x = 6 (1) of a 1 x 1 x 7 x 1 row, free between.
    row = np.zeros((1, 1, 7, 1), np.float32)
    row[..., 6, :] = 1
    free = mi.Bool(np.arange(7) % 6 != 0)
    t = mi.TensorXf(row.ravel(), row.shape)
    for _ in range(400):
        t = priors.unseen_fill(t, free)
    np.testing.assert_allclose(np.array(t.array), np.arange(7) / 6, atol=1e-4)
