"""The world <-> model normalization (mi_nerfpp.core.frame): NeRF++'s rule, cameras, rays, points."""
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.data import Camera
from mi_nerfpp.core.frame import (NERF_CAMERA_RADIUS, NERFPP_CAMERA_RADIUS, Normalization,
                                  reframe_cameras)
from tests.helpers import orbit_camera, truck_fixture_cameras


def test_truck_fixture_is_inside_the_unit_sphere():
    cams = truck_fixture_cameras()
    assert len(cams) == 5 and cams[0].width == 980 and cams[0].height == 546
    assert Normalization.for_cameras(cams) == Normalization()      # already inside: identity


def test_normalization_rule_on_truck_cameras():
    rng = np.random.default_rng(3)
    # Move the (already normalized) capture far away and blow it up, then normalize it back.
    offset, blow_up = rng.normal(size=3) * 20.0, 37.0
    away = Normalization(-offset / blow_up, blow_up)
    cams = [away.to_model_camera(cam) for cam in truck_fixture_cameras()]
    norm = Normalization.for_cameras(cams)
    assert norm != Normalization()
    normalized = [norm.to_model_camera(cam) for cam in cams]
    centers = np.stack([cam.center for cam in normalized])
    np.testing.assert_allclose(centers.mean(axis=0), 0.0, atol=1e-12)
    assert np.linalg.norm(centers, axis=1).max() == pytest.approx(NERFPP_CAMERA_RADIUS)
    assert NERFPP_CAMERA_RADIUS == pytest.approx(1 / 1.1)
    assert Normalization.for_cameras(normalized) == Normalization()
    for before, after in zip(cams, normalized):
        np.testing.assert_array_equal(after.c2w[:3, :3], before.c2w[:3, :3])
        np.testing.assert_array_equal(after.K, before.K)
        np.testing.assert_allclose(after.center / norm.scale + norm.center, before.center)
        np.testing.assert_allclose(norm.to_world_camera(after).c2w, before.c2w, atol=1e-9)


def test_normalization_rejects_degenerate_input():
    cam = orbit_camera(0.3, 0.2, 3.0, 8, 6)
    with pytest.raises(ValueError, match='coincide'):
        Normalization.for_cameras([cam, cam])
    with pytest.raises(ValueError, match='no cameras'):
        Normalization.for_cameras([])
    with pytest.raises(ValueError, match='positive'):
        Normalization((0, 0, 0), 0.0)


def test_inside_unit_sphere_is_strict():
    at_origin = Camera(np.eye(3), np.eye(4), 4, 3)
    on_sphere = Normalization((-1.0, 0.0, 0.0), 1.0).to_model_camera(at_origin)
    assert np.linalg.norm(on_sphere.center) == pytest.approx(1.0)
    assert Normalization.for_cameras([at_origin, on_sphere]) != Normalization()


def test_points_distances_rays_and_config_round_trip():
    norm = Normalization((10.0, -2.0, 5.0), 0.25)
    x = np.array([[10.4, -1.2, 7.4], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(norm.to_model_point(x)[0], [0.1, 0.2, 0.6])
    np.testing.assert_allclose(norm.to_world_point(norm.to_model_point(x)), x)
    assert norm.to_world_distance(norm.to_model_distance(3.0)) == pytest.approx(3.0)
    o, d = norm.to_model_rays(mi.Point3f(10.4, -1.2, 7.4), mi.Vector3f(0.0, 0.0, 2.0))
    np.testing.assert_allclose(np.array(o).ravel(), [0.1, 0.2, 0.6], atol=1e-5)
    np.testing.assert_allclose(np.array(d).ravel(), [0.0, 0.0, 1.0])
    assert Normalization.from_config(norm.to_config()) == norm
    assert Normalization.from_config({'normalization': norm.to_config()}) == norm
    assert Normalization.from_config({'center': [10, -2, 5], 'scale': 0.25}) == norm  # version 1


def test_nerf_baseline_frame_and_reframing_cameras():
    norm = Normalization((1.0, 2.0, 3.0), 0.5)
    nerf = norm.with_camera_radius(NERF_CAMERA_RADIUS)
    assert nerf.center == norm.center
    assert nerf.scale == pytest.approx(norm.scale * 1.1 / 8)
    cam = orbit_camera(0.3, 0.2, NERFPP_CAMERA_RADIUS, 8, 6)
    (moved,) = reframe_cameras([cam], norm, nerf)
    assert np.linalg.norm(moved.center) == pytest.approx(NERF_CAMERA_RADIUS)
    assert reframe_cameras([cam], norm, norm) == [cam]
