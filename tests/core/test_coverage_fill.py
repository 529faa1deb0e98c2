"""The training views' coverage of the directions and the colour painted where they saw
nothing (:mod:`mi_nerfpp.core.coverage`): the count in closed form, the hole filling, the
blend in a render, the checkpoint and the integrator's switch."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from tests.helpers import orbit_camera, tiny_model
from mi_nerfpp.core.color import srgb_eotf
from mi_nerfpp.core.coverage import (CoverageFill, fill_holes, texel_directions, texel_of,
                                     views_seeing)
from mi_nerfpp.core.rays import Rays
from mi_nerfpp.core.render import RenderOptions, Sampling, render_rays
from mi_nerfpp.data.cameras import direction_coverage
from mi_nerfpp.files.checkpoint import load_checkpoint, save_checkpoint
from mi_nerfpp.output.views import ViewRenderer, encoded_rgb, rgb

RING = [orbit_camera(a, 0.0, 3.0, 32, 24) for a in np.linspace(0, 2 * np.pi, 12,
                                                               endpoint=False)]


def test_a_direction_is_seen_within_the_frustum_wherever_the_camera_stands():
    """``views_seeing`` in closed form: a camera on the +x axis looking at the origin (focal
    0.9 x width, so its half field of view is atan(1/1.8) across, atan(0.75/1.8) up) sees -x
    and directions within those angles of it, not +x (behind) nor straight up."""
    cam = orbit_camera(0.0, 0.0, 3.0, 32, 24)
    half_x, half_y = np.arctan(16 / 28.8), np.arctan(12 / 28.8)

    def towards(yaw, pitch):         # about -x: yaw in the horizontal plane, pitch up
        return [-np.cos(pitch) * np.cos(yaw), np.sin(pitch), -np.cos(pitch) * np.sin(yaw)]

    dirs = [towards(0, 0), towards(0.98 * half_x, 0), towards(1.02 * half_x, 0),
            towards(0, 0.98 * half_y), towards(0, 1.02 * half_y), [1, 0, 0], [0, 1, 0]]
    np.testing.assert_array_equal(views_seeing(dirs, [cam]), [1, 1, 0, 1, 0, 0, 0])
    moved = orbit_camera(0.0, 0.0, 30.0, 32, 24)           # the same axes, 10x farther
    np.testing.assert_array_equal(views_seeing(dirs, [cam, moved]), [2, 2, 0, 2, 0, 0, 0])
    # direction_coverage counts the same per pixel: a view's own pixels are seen by itself
    assert np.all(direction_coverage(cam, [cam]) == 1)


def test_texels_and_their_directions_are_inverse():
    dirs = texel_directions(16)
    assert dirs.shape == (8, 16, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0)
    np.testing.assert_array_equal(texel_of(dirs.reshape(-1, 3), 16), np.arange(8 * 16))


def test_holes_take_their_known_neighbours_colour_without_edges():
    """Known texels keep their mean; holes get values within the known range (a weighted mean
    of them), a constant where every known texel holds it, and no step between neighbouring
    texels much larger than the known data's own."""
    h, w = 32, 64
    lon = np.linspace(0, 2 * np.pi, w, endpoint=False)
    color = np.stack([0.5 + 0.4 * np.sin(lon), 0.5 + 0.4 * np.cos(lon), np.full(w, 0.3)], -1)
    counts = np.zeros((h, w))
    counts[20:] = 3                                   # the lower rows seen, the upper not
    sums = np.broadcast_to(color, (h, w, 3)) * counts[..., None]
    filled = fill_holes(sums, counts)
    np.testing.assert_allclose(filled[20:], np.broadcast_to(color, (h - 20, w, 3)))
    assert filled.min() >= color.min() - 1e-9 and filled.max() <= color.max() + 1e-9
    # (a harmonic extension of the known row is as steep across as the row is along it;
    # push-pull alone leaves steps of 1.7 times that)
    known_step = np.abs(np.diff(color, axis=0)).max()
    steps = max(np.abs(np.diff(filled[:21], axis=0)).max(),
                np.abs(np.diff(filled[:20], axis=1)).max())
    assert steps <= 1.1 * known_step
    # one known texel of a constant colour paints everything
    one = np.zeros((h, w))
    one[5, 7] = 2
    grey = np.zeros((h, w, 3))
    grey[5, 7] = 2 * np.array([0.2, 0.4, 0.6])
    np.testing.assert_allclose(fill_holes(grey, one), np.broadcast_to([0.2, 0.4, 0.6],
                                                                      (h, w, 3)))
    assert np.all(fill_holes(grey, np.zeros((h, w))) == 0)


def test_a_ring_of_cameras_sees_the_horizon_and_paints_the_sky_with_its_colours():
    """Twelve cameras on a ring looking at its centre: directions on the horizon are seen by
    at least two (weight 1), straight up and down by none (weight 0). Each image is one sRGB
    grey: the seen texels hold it decoded to linear light, and the sky the mean of them."""
    greys = np.linspace(0.2, 0.8, len(RING))
    images = [np.full((24, 32, 3), g, np.float32) for g in greys]
    fill = CoverageFill.of_views(RING, images, 'srgb', resolution=64)
    # the model frame's directions: y is up, so straight up is texel direction (0, 1, 0)
    horizon = texel_of([[1, 0, 0], [0, 0, 1], [-1, 0, 0]], 64)
    poles = texel_of([[0, 1, 0], [0, -1, 0]], 64)
    seen = fill.seen.ravel()
    np.testing.assert_allclose(seen[horizon], 1.0, atol=1e-3)    # (softened at the edges)
    np.testing.assert_allclose(seen[poles], 0.0, atol=1e-3)
    linear = srgb_eotf(greys)
    color = fill.color.reshape(-1, 3)
    assert np.all(color >= linear.min() - 1e-6) and np.all(color <= linear.max() + 1e-6)
    # Every other camera of the ring: near camera 0's axis (-x) only it looks, 60 degrees
    # from the next; those texels hold its grey.
    sparse = CoverageFill.of_views(RING[::2], images[::2], 'srgb', resolution=64,
                                   color_resolution=64)
    near_axis = texel_of([[-1, 0, 0], [-1, 0.1, 0.1], [-1, -0.1, -0.1], [-1, 0.1, -0.1]], 64)
    np.testing.assert_allclose(sparse.seen.ravel()[near_axis], 0.5, atol=1e-3)
    np.testing.assert_allclose(sparse.color.reshape(-1, 3)[near_axis], linear[0], rtol=1e-5)


def _rays(directions, origin=(0.0, 0.0, 0.0)):
    d = np.asarray(directions, dtype=np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(np.asarray(origin, np.float32), d.shape)
    return mi.Point3f(*o.T.copy()), mi.Vector3f(*d.T.copy())


def test_a_render_paints_the_fill_where_no_view_saw_and_the_volume_where_two_did():
    model = tiny_model()
    fill = CoverageFill.of_views(RING, [np.full((24, 32, 3), 0.5, np.float32)] * len(RING),
                                 'linear', resolution=64)
    o, d = _rays([[1, 0, 0], [0, 0, 1], [0, 1, 0], [0.05, -1, 0]])
    fg, bg = model.radiance_fields()
    sampling = Sampling(16, 16, 0)
    plain = render_rays(Rays(o, d), fg, bg, sampling)
    filled = render_rays(Rays(o, d), fg, bg, sampling, RenderOptions(coverage=fill))
    lam = 1.0 - plain.fg.shading.opacity
    for k in range(2):                         # the horizon: seen, the volume unchanged
        assert np.asarray(filled.composite.rgb)[:, k] == pytest.approx(np.asarray(plain.composite.rgb)[:, k])
    for k in (2, 3):                           # the poles: the fill, opaque, behind the fg
        np.testing.assert_allclose(np.asarray(filled.bg.shading.rgb)[:, k], 0.5, atol=1e-6)
        assert float(filled.bg.shading.opacity[k]) == pytest.approx(1.0)
        np.testing.assert_allclose(np.asarray(filled.composite.rgb)[:, k],
                                   np.asarray(plain.fg.shading.rgb)[:, k] + float(lam[k]) * 0.5,
                                   rtol=1e-5)
    # a ray that ends at a surface (a finite far) is not painted
    far = mi.Float([np.inf, np.inf, 0.5, np.inf])
    ended = render_rays(Rays(o, d, far=far), fg, bg, sampling, RenderOptions(coverage=fill))
    unended = render_rays(Rays(o, d, far=far), fg, bg, sampling)
    np.testing.assert_allclose(np.asarray(ended.composite.rgb)[:, 2],
                               np.asarray(unended.composite.rgb)[:, 2], rtol=1e-6)


def test_the_fill_round_trips_through_the_checkpoint_and_the_integrator_can_turn_it_off(
        tmp_path):
    model = tiny_model()
    model.coverage = CoverageFill.of_views(
        RING, [np.full((24, 32, 3), 0.9, np.float32)] * len(RING), 'linear', resolution=32)
    save_checkpoint(tmp_path / 'model.npz', model)
    loaded, _, _ = load_checkpoint(tmp_path / 'model.npz')
    np.testing.assert_array_equal(loaded.coverage.seen, model.coverage.seen)
    np.testing.assert_array_equal(loaded.coverage.color, model.coverage.color)
    without = tiny_model()
    save_checkpoint(tmp_path / 'plain.npz', without)
    assert load_checkpoint(tmp_path / 'plain.npz')[0].coverage is None
    # A camera at the centre looking straight up: no training view looked there.
    up = orbit_camera(0.0, 1.5, 1e-3, 8, 6)
    def beauty(renderer):
        return rgb(renderer.render(up))

    on = beauty(ViewRenderer(loaded))
    off_renderer = ViewRenderer(loaded)
    off_renderer.scene.integrator().fill_unseen = False
    off = beauty(off_renderer)
    np.testing.assert_allclose(off, beauty(ViewRenderer(without)), rtol=1e-5, atol=1e-6)
    assert np.abs(on - off).max() > 0.01


def test_the_run_keeps_the_fill_only_where_it_paints_the_validation_views_better():
    """``choose_coverage_fill`` scores the validation views' unseen pixels with and without
    the fill: a view whose sky is the training views' grey keeps the fill; a view whose sky is
    what the volume renders there keeps the volume (the fill is dropped from the model)."""
    from mi_nerfpp.data.dataset import Split
    from mi_nerfpp.training.evaluate import choose_coverage_fill
    grey = 0.6
    images = [np.full((24, 32, 3), grey, np.float32)] * len(RING)
    up = orbit_camera(0.0, 1.5, 1e-3, 16, 12)          # looks where no training view did
    model = tiny_model()
    fill = CoverageFill.of_views(RING, images, 'srgb', resolution=64)
    model.coverage = fill
    sky = Split([up], ['sky.png'], [np.full((12, 16, 3), grey, np.float32)])
    choice = choose_coverage_fill(model, sky, RING)
    assert choice['kept'] and model.coverage is fill
    assert choice['pixels'] == 12 * 16 and choice['psnr_fill'] > choice['psnr_volume']
    model.coverage = None
    volume = np.clip(encoded_rgb(ViewRenderer(model).render(up), model.color_space), 0, 1)
    model.coverage = fill
    choice = choose_coverage_fill(model, Split([up], ['v.png'], [volume.astype(np.float32)]),
                                  RING)
    assert not choice['kept'] and model.coverage is None
    assert choice['psnr_volume'] > choice['psnr_fill']
    # Nothing unseen in the validation views (a training view, which two saw): no choice.
    model.coverage = fill
    seen = Split([RING[0]], ['r.png'], [images[0]])
    assert choose_coverage_fill(model, seen, RING + RING) is None and model.coverage is fill
