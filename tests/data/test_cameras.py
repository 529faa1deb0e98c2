"""Camera conventions and projection (mi_nerfpp.data.cameras)."""

import mi_nerfpp  # noqa: F401  (the variant: MI_NERFPP_VARIANT's, or llvm_ad_rgb)
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.data import cameras
from mi_nerfpp.data.cameras import Camera

def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q * np.linalg.det(q)   # det +1


def random_c2w(rng):
    c2w = np.eye(4)
    c2w[:3, :3] = random_rotation(rng)
    c2w[:3, 3] = rng.normal(size=3)
    return c2w


def off_centre_camera(rng=None, fy_ratio=1.0):
    """A 40x30 camera with its principal point several pixels off the image centre."""
    rng = rng or np.random.default_rng(1)
    K = np.array([[35.0, 0.0, 14.3], [0.0, 35.0 * fy_ratio, 18.6], [0.0, 0.0, 1.0]])
    return Camera(K=K, c2w=random_c2w(rng), width=40, height=30, name='off_centre')


# --- conventions ------------------------------------------------------------------------------

@pytest.mark.parametrize('forward, backward', [
    (cameras.opencv_to_opengl, cameras.opengl_to_opencv),
    (cameras.opengl_to_opencv, cameras.opencv_to_opengl),
    (cameras.opencv_to_mitsuba, cameras.mitsuba_to_opencv),
    (cameras.mitsuba_to_opencv, cameras.opencv_to_mitsuba),
])
def test_conversion_round_trips(forward, backward):
    rng = np.random.default_rng(0)
    c2w = np.stack([random_c2w(rng) for _ in range(4)])
    converted = forward(c2w)
    assert not np.allclose(converted, c2w)
    np.testing.assert_allclose(converted[:, :3, 3], c2w[:, :3, 3])   # the centre never moves
    np.testing.assert_allclose(backward(converted), c2w, atol=1e-15)
    np.testing.assert_allclose(np.linalg.det(converted[:, :3, :3]), 1.0)   # still a rotation


def test_opengl_axes():
    """OpenGL camera looking down -z with +y up == OpenCV camera with y down, z forward."""
    gl = np.eye(4)
    cv = cameras.opengl_to_opencv(gl)
    np.testing.assert_array_equal(cv[:3, 0], [1, 0, 0])    # right
    np.testing.assert_array_equal(cv[:3, 1], [0, -1, 0])   # down = -up
    np.testing.assert_array_equal(cv[:3, 2], [0, 0, -1])   # forward = -backward


def test_opencv_forward_z_is_mitsuba_forward_z():
    c2w = np.eye(4)
    c2w[:3, 3] = [0.1, 0.2, 0.3]
    to_world = cameras.opencv_to_mitsuba(c2w)
    np.testing.assert_array_equal(to_world[:3, 2], [0, 0, 1])
    sensor = mi.load_dict(cameras.mitsuba_sensor_dict(
        Camera(K=[[10, 0, 5], [0, 10, 5], [0, 0, 1]], c2w=c2w, width=10, height=10)))
    matrix = np.asarray(sensor.world_transform().matrix)[..., 0]   # (4, 4, 1) dynamic array
    np.testing.assert_allclose(matrix[:3, 2], [0, 0, 1], atol=1e-7)
    np.testing.assert_allclose(matrix[:3, 3], [0.1, 0.2, 0.3], atol=1e-7)


# --- projection -------------------------------------------------------------------------------

def test_pixel_rays_principal_point_and_unit_length():
    cam = off_centre_camera()
    origins, dirs = cameras.pixel_rays(cam, [cam.K[0, 2], 0.5, 39.5], [cam.K[1, 2], 0.5, 29.5])
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0)
    np.testing.assert_allclose(origins, np.tile(cam.center, (3, 1)))
    np.testing.assert_allclose(dirs[0], cam.c2w[:3, 2], atol=1e-12)   # optical axis


def test_projection_lands_where_the_ray_points():
    cam = off_centre_camera()
    rng = np.random.default_rng(2)
    px, py = rng.uniform(0, 40, 16), rng.uniform(0, 30, 16)
    origins, dirs = cameras.pixel_rays(cam, px, py)
    depth_along_ray = rng.uniform(0.5, 5.0, size=(16, 1))
    points = origins + depth_along_ray * dirs
    pixels, depth = cameras.project(cam, points)
    np.testing.assert_allclose(pixels, np.stack([px, py], axis=1), atol=1e-9)
    assert np.all(depth > 0)
    # The same with K @ W2C written out.
    homogeneous = (cam.K @ cam.w2c[:3] @ np.c_[points, np.ones(16)].T).T
    np.testing.assert_allclose(homogeneous[:, :2] / homogeneous[:, 2:], pixels, atol=1e-9)


def test_camera_helpers():
    cam = Camera(K=[[50, 0, 50], [0, 50, 25], [0, 0, 1]], c2w=np.eye(4), width=100, height=50)
    assert cam.fov_x == pytest.approx(90.0)
    assert cam.fov_y == pytest.approx(np.degrees(2 * np.arctan(0.5)))
    np.testing.assert_allclose(cam.w2c @ cam.c2w, np.eye(4))
    small = cam.downscaled(4)
    assert (small.width, small.height) == (25, 12)
    np.testing.assert_allclose(small.K, [[12.5, 0, 12.5], [0, 12.5, 6.25], [0, 0, 1]])
    with pytest.raises(ValueError, match='3x3'):
        Camera(K=np.eye(4), c2w=np.eye(4), width=1, height=1)


# --- Mitsuba sensor ---------------------------------------------------------------------------

def test_mitsuba_sensor_rays_match_pixel_rays():
    cam = off_centre_camera()
    sensor = mi.load_dict(cameras.mitsuba_sensor_dict(cam))
    px = np.array([0.5, 14.3, 39.5, 7.25, 31.0, 20.0])
    py = np.array([0.5, 18.6, 29.5, 22.75, 3.0, 15.0])
    ray, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f(px / cam.width, py / cam.height),
                               mi.Point2f(0.5, 0.5))
    mi_dirs = np.array(ray.d, dtype=np.float64).T.reshape(-1, 3)
    mi_origins = np.array(ray.o, dtype=np.float64).T.reshape(-1, 3)
    origins, dirs = cameras.pixel_rays(cam, px, py)
    np.testing.assert_allclose(mi_dirs, dirs, atol=2e-5)
    # Mitsuba starts rays on the near plane, but on the same line through the camera centre.
    offsets = mi_origins - origins
    np.testing.assert_allclose(np.cross(offsets, dirs), 0.0, atol=1e-6)
    assert np.all(np.einsum('ij,ij->i', offsets, dirs) >= 0)


def test_mitsuba_render_puts_a_point_where_K_projects_it():
    """A tiny emitter renders at the pixel K @ W2C projects its centre to (film orientation)."""
    cam = off_centre_camera(np.random.default_rng(5))
    target_pixel = np.array([27.0, 8.0])
    _, dirs = cameras.pixel_rays(cam, target_pixel[:1], target_pixel[1:])
    point = cam.center + 3.0 * dirs[0]
    scene = mi.load_dict({
        'type': 'scene',
        'integrator': {'type': 'direct'},
        'sensor': cameras.mitsuba_sensor_dict(cam, spp=16, pixel_format='rgb'),
        'light': {'type': 'sphere', 'center': point.tolist(), 'radius': 0.06,
                  'emitter': {'type': 'area', 'radiance': {'type': 'rgb', 'value': 1.0}}},
    })
    image = np.array(mi.render(scene, seed=0))[..., 0]
    assert image.shape == (30, 40)
    ys, xs = np.mgrid[0:30, 0:40] + 0.5
    centroid = np.array([(image * xs).sum(), (image * ys).sum()]) / image.sum()
    np.testing.assert_allclose(centroid, cameras.project(cam, point)[0][0], atol=0.25)
    np.testing.assert_allclose(centroid, target_pixel, atol=0.25)


def test_mitsuba_sensor_film_and_fov():
    cam = off_centre_camera()
    d = cameras.mitsuba_sensor_dict(cam, spp=4, pixel_format='rgb')
    assert d['film']['width'] == 40 and d['film']['height'] == 30
    assert d['film']['rfilter'] == {'type': 'box'}
    assert d['sampler']['sample_count'] == 4
    assert d['fov'] == pytest.approx(cam.fov_x)
    assert d['principal_point_offset_x'] == pytest.approx(0.5 - 14.3 / 40)


def test_mitsuba_sensor_rejects_non_square_pixels():
    with pytest.raises(ValueError, match='non-square pixels'):
        cameras.mitsuba_sensor_dict(off_centre_camera(fy_ratio=1.01))
    cameras.mitsuba_sensor_dict(off_centre_camera(fy_ratio=1.0005))   # within tolerance


def test_mitsuba_sensor_transform():
    cam = off_centre_camera()
    shift = np.eye(4)
    shift[:3, 3] = [1.0, -2.0, 0.5]
    d = cameras.mitsuba_sensor_dict(cam, transform=mi.ScalarTransform4f(shift))
    np.testing.assert_allclose(np.asarray(d['to_world'].matrix)[:3, 3],
                               cam.center + shift[:3, 3], atol=1e-6)
    with pytest.raises(ValueError, match='rigid'):
        cameras.mitsuba_sensor_dict(cam, transform=np.diag([2.0, 2.0, 2.0, 1.0]))


def test_direction_coverage_counts_the_cameras_that_see_each_direction():
    """A camera sees all its own directions; one turned 180 degrees sees none of them; one turned
    by half its field of view about the vertical sees exactly the half of the image on that side."""
    from mi_nerfpp.data import direction_coverage
    from mi_nerfpp.data.synth import intrinsics_from_fov, look_at
    K = intrinsics_from_fov(60.0, 40, 30)
    front = Camera(K, look_at([0, 0, 0], [0, 0, 1]), 40, 30, 'front')
    back = Camera(K, look_at([5, 1, 0], [5, 1, -1]), 40, 30, 'back')
    turned = Camera(K, look_at([0, 0, 0], [np.sin(np.radians(30)), 0, np.cos(np.radians(30))]),
                    40, 30, 'turned')
    assert (direction_coverage(front, [front]) == 1).all()
    assert (direction_coverage(front, [back]) == 0).all()
    both = direction_coverage(front, [front, back, turned])
    assert set(np.unique(both)) == {1, 2}
    # On the middle row the turned camera's field spans 0-60 degrees: exactly the half of the
    # row on its side of the optical axis.
    row = both[15] == 2
    assert row.sum() == 20 and (row[:20].all() or row[20:].all())
