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
