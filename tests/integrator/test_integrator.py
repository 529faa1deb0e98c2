"""The nerfpp integrator: registration, AOVs, the compositing identity, gradients."""
import os

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.core.layers import AOVS, BEAUTY
from mi_nerfpp.core.frame import Normalization
from mi_nerfpp.integrator import NeRFPPIntegrator
from tests.helpers import scene_dict, tiny_model


# The channels mi.render returns: the film's, then the integrator's sample channels.
CHANNELS = BEAUTY + AOVS


def layers(img):
    from mi_nerfpp.output.views import render_layers
    return render_layers(np.array(img))


def test_import_registers_plugin_and_variant():
    scene = mi.load_dict(scene_dict())
    assert isinstance(scene.integrator(), NeRFPPIntegrator)
    assert mi.variant() == (os.environ.get('MI_NERFPP_VARIANT') or 'llvm_ad_rgb')


def test_output_channels_and_compositing_identity(tiny_scene):
    img = mi.render(tiny_scene)
    assert img.shape == (6, 8, len(CHANNELS))
    c = layers(img)
    for ch in 'RGB':
        beauty = c[ch]
        recomposed = c[f'fg.{ch}'] + (1.0 - c['fg.A']) * c[f'bg.{ch}']
        np.testing.assert_allclose(beauty, recomposed, rtol=0, atol=2e-6)
    assert np.all(c['A'] == 1.0)
    assert np.all((c['fg.A'] > 0) & (c['fg.A'] < 1))
    # The camera is inside the unit sphere, so depth is at least the exit distance's share.
    assert np.all(np.isfinite(c['depth.Z'])) and np.all(c['depth.Z'] > 0)


def test_background_off_renders_foreground_over_black():
    scene = mi.load_dict(scene_dict(background=False))
    scene.integrator().set_model(tiny_model())
    c = layers(mi.render(scene))
    for ch in 'RGB':
        np.testing.assert_allclose(c[ch], c[f'fg.{ch}'], atol=1e-7)
        assert np.all(c[f'bg.{ch}'] == 0)


def test_chunked_render_matches_single_pass(tiny_scene):
    whole = np.array(mi.render(tiny_scene))
    tiny_scene.integrator().chunk_rays = 7        # 48 rays -> 7 chunks, last one partial
    chunked = np.array(mi.render(tiny_scene))
    np.testing.assert_array_equal(whole, chunked)


def test_stratified_jitter_does_not_depend_on_chunks():
    scene = mi.load_dict(scene_dict(stratified=True))
    scene.integrator().set_model(tiny_model())
    whole = np.array(mi.render(scene, seed=3))
    scene.integrator().chunk_rays = 7
    chunked = np.array(mi.render(scene, seed=3))
    np.testing.assert_allclose(whole, chunked, rtol=0, atol=1e-6)
    assert np.any(np.array(mi.render(scene, seed=4)) != chunked)    # the jitter is live


def test_sensor_outside_unit_sphere_renders_finite_values():
    scene = mi.load_dict(scene_dict(origin=(0.0, 0.5, 3.0)))
    scene.integrator().set_model(tiny_model())
    c = layers(mi.render(scene))
    for name, v in c.items():
        assert np.all(np.isfinite(v)), name
    # Rays that miss the sphere see no foreground; the centre ray crosses it.
    assert c['fg.A'][0, 0] == 0.0
    assert c['fg.A'][3, 4] > 0.0


def test_world_frame_normalization_moves_the_model():
    """A model normalized with (center, scale) renders from world cameras as if unnormalized."""
    # Mitsuba starts camera rays at near_clip (world units): make it negligible in both frames.
    ref = mi.load_dict(scene_dict(origin=(0.1, 0.2, 0.6), near_clip=1e-5))
    ref.integrator().set_model(tiny_model())
    moved = mi.load_dict(scene_dict(origin=(10 + 0.1 * 4, -2 + 0.2 * 4, 5 + 0.6 * 4),
                                     target=(10, -2, 5), near_clip=1e-5))
    m = tiny_model()
    m.normalization = Normalization(np.array([10.0, -2.0, 5.0]), 0.25)
    moved.integrator().set_model(m)
    a, b = layers(mi.render(ref)), layers(mi.render(moved))
    # float32 rays at |x| ~ 10 carry ~1e-6 relative error: compare to 1e-3.
    for ch in ('R', 'G', 'B', 'fg.A'):
        np.testing.assert_allclose(a[ch], b[ch], atol=1e-3)
    np.testing.assert_allclose(b['depth.Z'], a['depth.Z'] * 4, rtol=1e-3)


def test_traverse_exposes_every_field_parameter_as_differentiable(tiny_scene):
    integ = tiny_scene.integrator()
    params = mi.traverse(integ)
    names = set(integ.model.parameters())
    assert names == set(params.keys())
    for k in names:
        flags = params.properties[k][3]
        # Mitsuba's Differentiable flag is the absence of NonDifferentiable / ReadOnly.
        assert not flags & (mi.ParamFlags.NonDifferentiable | mi.ParamFlags.ReadOnly), k
    assert {'fg.grid0', 'fg.grid1', 'bg.grid0', 'fg.color.sample.layers.0.weights',
            'fg.color.ray.layers.0.bias', 'fg.color.rest.layers.1.weights'} <= names


def _loss(img, weights):
    return dr.sum(img * weights, axis=None)


@pytest.mark.parametrize('key', ['fg.grid1', 'fg.color.sample.layers.0.weights', 'bg.grid0',
                                 'fg.color.ray.layers.0.weights',
                                 'bg.color.rest.layers.1.bias'])
def test_gradients_match_central_finite_differences(key):
    # Fine sample positions follow the coarse weights but are detached (as in NeRF), so
    # finite differences see a dependence that AD deliberately ignores: check with the
    # coarse pass alone, whose stratified positions do not depend on the parameters.
    # Rays through pixel centres: the primal and the gradient pass (which Mitsuba seeds
    # differently) see the same rays.
    tiny_scene = mi.load_dict(scene_dict(fine_samples=0, jitter=False))
    tiny_scene.integrator().set_model(tiny_model())
    integ = tiny_scene.integrator()
    params = mi.traverse(integ)
    shape = params[key].shape
    rng = np.random.default_rng(1)
    w = rng.uniform(-1, 1, (6, 8, len(CHANNELS))).astype(np.float32)
    # Weight every output channel except the depth layers (large values; depth.Z is
    # piecewise constant in the parameters), which keeps FD well conditioned.
    for name in ('depth.Z', 'distance.Y', 'obj_depth_w.Z'):
        w[..., CHANNELS.index(name)] = 0.0
    weights = mi.TensorXf(w)

    dr.enable_grad(params[key])
    params.update()
    img = mi.render(tiny_scene, params, seed=1)
    dr.backward(_loss(img, weights))
    grad = np.array(dr.grad(params[key])).ravel()

    base = np.array(params[key]).ravel().astype(np.float64)
    picks = np.argsort(-np.abs(grad))[:3]
    h = 1e-2
    for i in picks:
        vals = []
        for sign in (+1, -1):
            x = base.copy()
            x[i] += sign * h
            integ.model.set_parameters({key: mi.TensorXf(x.astype(np.float32).reshape(shape))})
            with dr.suspend_grad():
                vals.append(float(_loss(mi.render(tiny_scene, seed=1), weights).array[0]))
        fd = (vals[0] - vals[1]) / (2 * h)
        assert abs(fd - grad[i]) <= 2e-2 * abs(grad[i]) + 1e-4, (key, i, fd, grad[i])


def test_integrator_builds_random_fields_only_when_asked(tmp_path):
    scene = mi.load_dict(scene_dict())
    integ = scene.integrator()
    assert integ._model is None                   # loading the scene built no model
    m = tiny_model()
    integ.set_model(m)
    mi.render(scene)
    assert integ.model is m                       # the handed model was rendered, no other
    fresh = mi.load_dict(scene_dict(seed=4, field='nerf')).integrator()
    assert fresh.model.n_parameters() > 0 and fresh._model is fresh.model


def test_renders_pass_each_pixels_footprint_to_the_fields():
    """A model whose grids filter by footprint (``antialias``), rendered by the integrator at
    12 x 9 pixels (footprints of several fine cells): the beauty equals :func:`render_rays`
    of the same rays with the footprints the training bank gives that camera, and differs
    from the point lookup."""
    from mi_nerfpp.data import Split
    from mi_nerfpp.data.storage import StoredImages
    from mi_nerfpp.core.model import NeRFPPModel
    from mi_nerfpp.core.render import RenderOptions, render_rays
    from mi_nerfpp.training.raybank import RayBank
    from mi_nerfpp.output.views import ViewRenderer, rgb
    from tests.helpers import orbit_camera
    grid = dict(kind='grid', resolutions=[8, 64], channels=3, hidden=8, antialias=True)
    model = NeRFPPModel.create(seed=2, fg_config=dict(grid, domain='ball'),
                               bg_config=dict(grid, domain='inverted_sphere'))
    for field in (model.fg, model.bg):       # a fine level with detail that shows
        field.set_parameters({'grid1': field.params['grid1'] * 30.0})
    camera = orbit_camera(0.4, 0.1, 0.8, 12, 9, focal=0.8)
    renderer = ViewRenderer(model)
    image = rgb(renderer.render(camera))
    bank = RayBank(Split([camera], ['x.png'], StoredImages([np.zeros((9, 12, 3), np.uint8)],
                                                           255.0)))
    index = np.arange(bank.size, dtype=np.uint32)
    rays, _ = bank.batch(index)
    expected = {}
    for footprint in (bank.footprint(index), None):
        res = render_rays(rays.replace(footprint=footprint), *model.radiance_fields(),
                          model.sampling, RenderOptions(skip_occluded=True))
        expected[footprint is None] = np.array(res.composite.rgb).T.reshape(9, 12, 3)
    np.testing.assert_allclose(image, expected[False], atol=2e-3)
    assert np.abs(image - expected[True]).mean() > 5e-3     # the footprints did change it
