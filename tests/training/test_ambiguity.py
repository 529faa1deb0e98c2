"""The opaque-sphere reconstruction of paper §3 (mi_nerfpp.training.ambiguity)."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from tests.helpers import make_capture
from mi_nerfpp.training.ambiguity import OpaqueSphere, fit_radiance, sphere_hit
from mi_nerfpp.data import load_dataset
from mi_nerfpp.core.fields import MLPField
from mi_nerfpp.training.metrics import psnr
from mi_nerfpp.training.raybank import RayBank


def _rays(n, seed, spread):
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3)) * spread
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o.astype(np.float32), d.astype(np.float32)


def test_sphere_hit_matches_mitsubas_ray_tracer():
    center, radius = np.array([0.2, -0.1, 0.3]), 0.7
    scene = mi.load_dict({'type': 'scene', 's': {'type': 'sphere', 'center': center.tolist(),
                                                 'radius': radius}})
    o, d = _rays(4000, 0, 1.0)   # origins inside and outside the sphere
    ray = mi.Ray3f(mi.Point3f(*o.T), mi.Vector3f(*d.T))
    si = scene.ray_intersect(ray)
    x, t, hit = sphere_hit(ray.o, ray.d, center, radius)
    valid = np.array(si.is_valid())
    hit = np.array(hit)
    assert valid.any() and (~valid).any() and np.array_equal(hit, valid)
    np.testing.assert_allclose(np.array(t)[hit], np.array(si.t)[hit], rtol=1e-4, atol=1e-4)
    p_local = (np.array(si.p).T[hit] - center) / radius
    np.testing.assert_allclose(np.array(x).T[hit], p_local, atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(np.array(x).T[hit], axis=1), 1.0, atol=1e-5)


def test_origin_inside_the_sphere_sees_the_exit_point():
    x, t, hit = sphere_hit(mi.Point3f(0.5, 0, 0), mi.Vector3f(1, 0, 0), (0, 0, 0), 2.0)
    assert bool(hit[0]) and t[0] == pytest.approx(1.5) and x.x[0] == pytest.approx(1.0)
    x, t, hit = sphere_hit(mi.Point3f(3, 0, 0), mi.Vector3f(1, 0, 0), (0, 0, 0), 2.0)
    assert not bool(hit[0])     # sphere behind the origin


def test_rays_that_miss_see_the_background_and_colour_depends_on_direction():
    sphere = OpaqueSphere(MLPField('ball', 'nerf', depth=2, width=16), (0, 0, 0), 1.0,
                          background=(0.25, 0.5, 0.75))
    # Three rays (columns): a miss (b = 2 > 1), and two that enter at (0, 0, -1) from
    # different directions.
    o = mi.Point3f([0, 0, 0], [2, 0, -1.2], [-3, -3, -2.6])
    d = mi.Vector3f([0, 0, 0], [0, 0, 0.6], [1, 1, 0.8])
    x, _, _ = sphere_hit(o, d, (0, 0, 0), 1.0)
    np.testing.assert_allclose(np.array(x)[:, 1:], [[0, 0], [0, 0], [-1, -1]], atol=1e-6)
    rgb = np.array(sphere.radiance(o, d))          # (3 channels, 3 rays)
    np.testing.assert_allclose(rgb[:, 0], [0.25, 0.5, 0.75])
    assert not np.allclose(rgb[:, 1], rgb[:, 2])
    with pytest.raises(ValueError, match='radius'):
        OpaqueSphere(sphere.field, (0, 0, 0), 0.0)


def test_fitting_the_radiance_explains_the_training_views(tmp_path):
    ds = load_dataset(make_capture(str(tmp_path / 'cap'), views=12, width=16, height=12, spp=4))
    # A sphere of world radius 5 around the cameras (radius 3): every ray hits it from inside.
    norm = ds.normalization
    sphere = OpaqueSphere(MLPField('ball', 'nerf', depth=2, width=32),
                          norm.to_model_point(np.zeros(3)), norm.to_model_distance(5.0))
    cam, gt = ds.train.cameras[0], ds.train.images[0]
    before = psnr(np.clip(sphere.render_view(cam), 0, 1), gt)
    history = fit_radiance(sphere, RayBank(ds.train), iterations=150, batch_rays=1024)
    after = psnr(np.clip(sphere.render_view(cam), 0, 1), gt)
    assert history[-1][1] < history[0][1]
    assert after > before + 5, (before, after)
    assert not any(dr.grad_enabled(v) for v in sphere.field.params.values())
