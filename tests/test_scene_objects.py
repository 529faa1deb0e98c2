"""Mitsuba shapes inside the reconstruction (issue 13): occlusion both ways, the NeRF++ as the
light of path-traced surfaces, the objects' EXR layers and the shadow catcher, checked against
closed forms."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.render import Sampling, render_rays
from tests.test_render import F, constant_field, npf, rays


# ----------------------------------------------------------------------------- render_rays(far=)

def test_far_at_infinity_renders_bit_identically():
    from tests.helpers import tiny_model
    model = tiny_model()
    o, d = rays(64, seed=5)
    sampling = Sampling(8, 8, 8)
    for occupancy in (None, 'grids'):
        if occupancy:
            model.enable_occupancy(8, 0.3)
            model.update_occupancy(seed=1)
        for skip in (False, True):
            a = render_rays(o, d, model.fg, model.bg, sampling, occupancy=model.occupancy,
                            skip_occluded=skip)
            b = render_rays(o, d, model.fg, model.bg, sampling, occupancy=model.occupancy,
                            skip_occluded=skip, far=dr.full(mi.Float, dr.inf, 64))
            for x, y in ((a.fine.rgb, b.fine.rgb), (a.fine.opacity, b.fine.opacity),
                         (a.fine.depth, b.fine.depth), (a.fg.fine.rgb, b.fg.fine.rgb),
                         (a.coarse.rgb, b.coarse.rgb)):
                np.testing.assert_array_equal(npf(x), npf(y))


def test_far_ends_the_foreground_at_the_hit():
    """Constant density σ from the centre: opacity 1 - exp(-σ·far), nothing behind the hit."""
    sigma, far = 3.0, 0.4
    o, d = mi.Point3f(0.0, 0.0, 0.0), mi.Vector3f(0.0, 0.6, 0.8)
    res = render_rays(o, d, constant_field(sigma, (1, 0.5, 0.2)), constant_field(5.0, (0, 1, 0)),
                      Sampling(4096, 16, 0), far=F([far]))
    expected = 1 - np.exp(-sigma * far)
    assert npf(res.fg.fine.opacity)[0] == pytest.approx(expected, abs=1e-3)
    assert npf(res.bg.fine.opacity)[0] == 0.0
    assert npf(res.fine.opacity)[0] == pytest.approx(expected, abs=1e-3)
    np.testing.assert_allclose(npf(res.fine.rgb), np.array([1, 0.5, 0.2]) * expected, atol=1e-3)


@pytest.mark.parametrize('far', [1.5, 4.0, 30.0])
def test_far_ends_the_background_at_the_hit(far):
    """Background density σ per unit of s = 1/r from the centre: s runs from 1 to 1/far, so
    the opacity is 1 - exp(-σ (1 - 1/far)): not opaque any more."""
    sigma = 0.8
    o, d = mi.Point3f(0.0, 0.0, 0.0), mi.Vector3f(1.0, 0.0, 0.0)
    res = render_rays(o, d, constant_field(0.0, (0, 0, 0)), constant_field(sigma, (0.3, 0.6, 0.9)),
                      Sampling(4, 4096, 0), far=F([far]))
    expected = 1 - np.exp(-sigma * (1 - 1 / far))
    assert npf(res.bg.fine.opacity)[0] == pytest.approx(expected, abs=1e-3)
    assert npf(res.fine.opacity)[0] == pytest.approx(expected, abs=1e-3)
    # An origin outside the sphere, ray pointing away: the background starts at the origin.
    o2 = mi.Point3f(2.0, 0.0, 0.0)
    res = render_rays(o2, d, constant_field(0.0, (0, 0, 0)), constant_field(sigma, (1, 1, 1)),
                      Sampling(4, 4096, 0), far=F([far]))
    expected = 1 - np.exp(-sigma * (0.5 - 1 / (2 + far)))
    assert npf(res.bg.fine.opacity)[0] == pytest.approx(expected, abs=1e-3)
