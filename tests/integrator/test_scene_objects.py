"""Mitsuba shapes inside the reconstruction (issue 13): occlusion both ways, the NeRF++ as the
light of path-traced surfaces, the objects' EXR layers and the shadow catcher, checked against
closed forms."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.core.rays import Rays
from mi_nerfpp.core.render import RenderOptions, Sampling, render_rays
from mi_nerfpp.integrator.nerfpp import VolumesOnly
from tests.helpers import AnalyticField
from tests.core.test_render import F, constant_field, npf, rays


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
            options = RenderOptions(occupancy=model.occupancy, skip_occluded=skip)
            a = render_rays(Rays(o, d), model.fg, model.bg, sampling, options)
            b = render_rays(Rays(o, d, far=dr.full(mi.Float, dr.inf, 64)), model.fg, model.bg,
                            sampling, options)
            for x, y in ((a.composite.rgb, b.composite.rgb), (a.composite.opacity, b.composite.opacity),
                         (a.composite.depth, b.composite.depth), (a.fg.shading.rgb, b.fg.shading.rgb),
                         (a.bg.shading.rgb, b.bg.shading.rgb)):
                np.testing.assert_array_equal(npf(x), npf(y))


def test_far_ends_the_foreground_at_the_hit():
    """Constant density σ from the centre: opacity 1 - exp(-σ·far), nothing behind the hit."""
    sigma, far = 3.0, 0.4
    o, d = mi.Point3f(0.0, 0.0, 0.0), mi.Vector3f(0.0, 0.6, 0.8)
    res = render_rays(Rays(o, d, far=F([far])), constant_field(sigma, (1, 0.5, 0.2)),
                      constant_field(5.0, (0, 1, 0)), Sampling(4096, 16, 0))
    expected = 1 - np.exp(-sigma * far)
    assert npf(res.fg.shading.opacity)[0] == pytest.approx(expected, abs=1e-3)
    assert npf(res.bg.shading.opacity)[0] == 0.0
    assert npf(res.composite.opacity)[0] == pytest.approx(expected, abs=1e-3)
    np.testing.assert_allclose(npf(res.composite.rgb), np.array([1, 0.5, 0.2]) * expected, atol=1e-3)


@pytest.mark.parametrize('far', [1.5, 4.0, 30.0])
def test_far_ends_the_background_at_the_hit(far):
    """Background density σ per unit of s = 1/r from the centre: s runs from 1 to 1/far, so
    the opacity is 1 - exp(-σ (1 - 1/far)): not opaque any more."""
    sigma = 0.8
    o, d = mi.Point3f(0.0, 0.0, 0.0), mi.Vector3f(1.0, 0.0, 0.0)
    res = render_rays(Rays(o, d, far=F([far])), constant_field(0.0, (0, 0, 0)),
                      constant_field(sigma, (0.3, 0.6, 0.9)), Sampling(4, 4096, 0))
    expected = 1 - np.exp(-sigma * (1 - 1 / far))
    assert npf(res.bg.shading.opacity)[0] == pytest.approx(expected, abs=1e-3)
    assert npf(res.composite.opacity)[0] == pytest.approx(expected, abs=1e-3)
    # An origin outside the sphere, ray pointing away: the background starts at the origin.
    o2 = mi.Point3f(2.0, 0.0, 0.0)
    res = render_rays(Rays(o2, d, far=F([far])), constant_field(0.0, (0, 0, 0)),
                      constant_field(sigma, (1, 1, 1)), Sampling(4, 4096, 0))
    expected = 1 - np.exp(-sigma * (0.5 - 1 / (2 + far)))
    assert npf(res.bg.shading.opacity)[0] == pytest.approx(expected, abs=1e-3)


# ----------------------------------------------------------------------------- scenes with shapes

EMPTY = AnalyticField(0.0, (0.0, 0.0, 0.0))


def sky(x):
    """A background that varies with direction: colour 0.5 + 0.4·x̂."""
    return mi.Color3f(0.5 + 0.4 * x[0], 0.5 + 0.4 * x[1], 0.5 + 0.4 * x[2])


def object_scene(fg, bg, shapes, width=16, height=12, origin=(0.0, 0.1, 0.9), target=(0, 0, 0),
                 spp=1, fov=60, **integrator):
    from mi_nerfpp.core.model import NeRFPPModel
    from tests.helpers import scene_dict
    desc = scene_dict(width=width, height=height, origin=origin, target=target, spp=spp,
                      jitter=False, **dict(dict(fg_samples=64, bg_samples=32, fine_samples=32),
                                           **integrator))
    desc['sensor']['fov'] = fov
    desc.update(shapes)
    scene = mi.load_dict(desc)
    scene.integrator().set_model(NeRFPPModel(fg, bg, color_space='linear'))
    return scene


def channels(scene, **kwargs):
    from mi_nerfpp.output.views import render_layers
    return render_layers(mi.render(scene, **kwargs), scene.integrator())


def pixel_rays(scene):
    """World rays through the pixel centres (float64 numpy, H x W x 3 each)."""
    sensor = scene.sensors()[0]
    w, h = sensor.film().crop_size()
    x, y = np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h)
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(x.ravel(), y.ravel()), mi.Point2f(0.5))
    o = np.array(ray.o, dtype=np.float64).reshape(3, -1).T.reshape(h, w, 3)
    d = np.array(ray.d, dtype=np.float64).reshape(3, -1).T.reshape(h, w, 3)
    return o, d


def sphere_hit(o, d, center, radius):
    """Distance to the first hit of rays on a sphere (inf on a miss)."""
    oc = o - np.asarray(center, dtype=np.float64)
    b = np.sum(oc * d, axis=-1)
    disc = b * b - (np.sum(oc * oc, axis=-1) - radius ** 2)
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return np.where(disc > 0, t, np.inf)


def camera_z(scene, o, d, t):
    m = np.array(scene.sensors()[0].world_transform().matrix, dtype=np.float64).reshape(4, 4)
    axis = m[:3, 2] / np.linalg.norm(m[:3, 2])
    return (o - m[:3, 3]) @ axis + t * (d @ axis)


def test_sphere_in_front_of_the_volume_has_its_analytic_depth():
    center, radius = (0.0, 0.05, 0.3), 0.2
    haze = AnalyticField(0.2, (0.9, 0.2, 0.1))            # a thin foreground: opacity < 0.5 before the hit
    scene = object_scene(haze, AnalyticField(1.0, sky), {
        'ball': {'type': 'sphere', 'center': list(center), 'radius': radius,
                 'bsdf': {'type': 'diffuse'}}})
    c = channels(scene)
    o, d = pixel_rays(scene)
    t = sphere_hit(o, d, center, radius)
    hit = np.isfinite(t)
    assert 20 < hit.sum() < hit.size
    np.testing.assert_array_equal(c['obj.A'], hit.astype(np.float32))
    z = camera_z(scene, o, d, np.where(hit, t, 0.0))
    np.testing.assert_allclose(c['depth.Z'][hit], z[hit], rtol=1e-5)
    np.testing.assert_allclose(c['obj_depth.Z'][hit], z[hit], rtol=1e-5)
    assert np.all(c['obj_depth.Z'][~hit] == 0) and np.all(c['obj.R'][~hit] == 0)
    # The volume in front of the sphere is integrated up to the hit only: fg.A = 1 - exp(-σ t)
    # (64 + 32 samples from the near plane; the first half interval is not integrated).
    np.testing.assert_allclose(c['fg.A'][hit], 1 - np.exp(-0.2 * t[hit]), atol=3e-3)
    assert np.all(c['bg.R'][hit] == 0)            # the hit is inside the unit sphere
    # beauty = fg + (1 - fg.A)·bg + obj + shadow
    for ch in 'RGB':
        np.testing.assert_allclose(
            c[ch], c[f'fg.{ch}'] + (1 - c['fg.A']) * c[f'bg.{ch}'] + c[f'obj.{ch}']
            + c[f'shadow.{ch}'], atol=2e-6)


def test_sphere_behind_an_opaque_reconstructed_surface_is_invisible():
    """An emitting sphere inside an opaque reconstructed ball is hidden; in front, it shows."""
    def opaque_ball(x):
        return dr.select(dr.norm(mi.Vector3f(x[0], x[1], x[2])) < 0.4, 1e5, 0.0)
    fg = AnalyticField(opaque_ball, (0.5, 0.5, 0.5))
    lamp = {'type': 'sphere', 'radius': 0.15, 'emitter': {'type': 'area', 'radiance': {
        'type': 'rgb', 'value': [50.0, 50.0, 50.0]}}}
    alone = channels(object_scene(fg, AnalyticField(1.0, sky), {}, fg_samples=256))
    hidden = channels(object_scene(fg, AnalyticField(1.0, sky), {'lamp': dict(lamp, center=[0, 0, 0])},
                                   fg_samples=256))
    shown = channels(object_scene(fg, AnalyticField(1.0, sky), {'lamp': dict(lamp, center=[0, 0.1, 0.6])},
                                  fg_samples=256))
    seen = hidden['obj.A'] > 0
    assert seen.sum() > 10                       # the rays hit it (and see the volume first)
    np.testing.assert_allclose(hidden['R'], alone['R'], atol=1e-4)
    # The samples now cover [near, hit] only: the surface moves by less than their spacing.
    np.testing.assert_allclose(hidden['depth.Z'], alone['depth.Z'], atol=2.0 / 256)
    assert np.all(hidden['obj.R'] < 1e-4)
    assert shown['R'].max() > 10.0


@pytest.mark.parametrize('near', [0.0, 0.3])
def test_mirror_sphere_reflects_the_reconstruction_from_the_hit_point(near):
    """A perfect mirror: the pixel is render_rays along the reflected ray from the hit point
    (parallax: not an environment lookup), through both volumes, deterministic samples; the
    integrator's ``near`` applies to camera rays only."""
    import dataclasses
    center, radius = np.array([0.0, 0.0, 0.2]), 0.3
    fg = AnalyticField(lambda x: dr.select(x[1] > 0.5, 4.0, 0.0), (0.9, 0.6, 0.1))   # a lit cap
    bg = AnalyticField(1.0, sky)
    scene = object_scene(fg, bg, {'mirror': {
        'type': 'sphere', 'center': list(center), 'radius': radius,
        'bsdf': {'type': 'conductor', 'material': 'none'}}}, max_depth=2, near=near)
    c = channels(scene)
    o, d = pixel_rays(scene)
    t = sphere_hit(o, d, center, radius)
    hit = np.isfinite(t)
    p = o + t[..., None] * d
    n = (p - center) / radius
    r = d - 2 * np.sum(d * n, axis=-1, keepdims=True) * n
    integ = scene.integrator()
    ys, xs = np.nonzero(hit)
    res = render_rays(Rays(mi.Point3f(*[F(p[ys, xs, i]) for i in range(3)]),
                           mi.Vector3f(*[F(r[ys, xs, i]) for i in range(3)])), fg, bg,
                      dataclasses.replace(integ.sampling, near=0.0))
    expected = npf(res.composite.rgb, len(ys)).T
    # The camera segment sees the empty lower foreground only: all of it is the reflection.
    got = np.stack([c['obj.R'], c['obj.G'], c['obj.B']], axis=-1)[ys, xs]
    assert np.ptp(expected[:, 0]) > 0.1           # the reflection varies over the sphere
    np.testing.assert_allclose(got, expected, rtol=2e-3, atol=2e-4)
    np.testing.assert_allclose(c['R'][ys, xs], expected[:, 0], rtol=2e-3, atol=2e-4)
    # max_depth = 1 (as in Mitsuba's path): the surfaces show their own emission only.
    integ.max_depth = 1
    assert np.all(channels(scene)['obj.R'] == 0)


@pytest.mark.parametrize('albedo', [1.0, 0.5])
def test_white_furnace(albedo):
    """Two touching diffuse spheres in a field of constant radiance c (no emitters): with
    albedo 1 every pixel is c (the rendering equation's solution in a furnace, interreflection
    included); with albedo ρ a convex sphere's pixel is ρ·c."""
    c_rgb = np.array([0.3, 0.5, 0.7])
    bg = AnalyticField(1.0, tuple(c_rgb))
    shapes = {'a': {'type': 'sphere', 'center': [-0.2, 0, 0], 'radius': 0.2,
                    'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': albedo}}}}
    if albedo == 1.0:
        shapes['b'] = dict(shapes['a'], center=[0.2, 0, 0])
    c = channels(object_scene(EMPTY, bg, shapes, spp=36, max_depth=64))
    seen, empty = c['obj.A'] == 1.0, c['obj.A'] == 0.0
    assert seen.sum() > 20
    rgb = np.stack([c[ch] for ch in 'RGB'], axis=-1)
    np.testing.assert_allclose(rgb[empty], np.broadcast_to(c_rgb, rgb[empty].shape), rtol=1e-5)
    if albedo == 1.0:
        # Paths bounce between the spheres: each path that escapes carries exactly c (β = 1)
        # unless Russian roulette (after 5 bounces) reweights it, so the error is small. Cut at
        # max_depth = 2 instead, the pixels lose 0.014 on average and up to 0.1 (measured).
        err = rgb[seen] - c_rgb
        assert np.abs(err.mean(axis=0)).max() < 0.005
        assert np.abs(err).max() < 0.05
    else:
        np.testing.assert_allclose(rgb[seen], np.broadcast_to(albedo * c_rgb, rgb[seen].shape),
                                   rtol=1e-5)


# ----------------------------------------------------------------------------- shadow catcher

def ground_fields():
    """A reconstructed ground (opaque below y = -0.3, grey) under a sky that is bright
    straight above (x̂_y > 0.7) and dim elsewhere."""
    fg = AnalyticField(lambda x: dr.select(x[1] < -0.3, 1e4, 0.0), (0.5, 0.5, 0.5))
    bg = AnalyticField(1.0, lambda x: mi.Color3f(dr.select(x[1] > 0.7, 4.0, 0.1)))
    return fg, bg


CATCHER = {'catcher': {'type': 'rectangle', 'id': 'catcher', 'to_world': mi.ScalarTransform4f()
                       .translate([0, -0.3, 0]).rotate([1, 0, 0], -90).scale(0.9)}}


def ground_scene(shapes, **integrator):
    fg, bg = ground_fields()
    return object_scene(fg, bg, shapes, width=20, height=15, origin=(0.0, 0.35, 0.75),
                        target=(0, -0.3, 0), fg_samples=128, catcher_samples=32, **integrator)


def test_shadow_catcher_without_an_occluder_changes_no_pixel():
    # An object under the ground: hidden by the reconstruction, outside the hemisphere that
    # the catcher sees, so the catcher's irradiance is the same with and without it.
    buried = {'buried': {'type': 'sphere', 'center': [0, -0.6, 0], 'radius': 0.1}}
    plain = channels(ground_scene(buried))
    caught = channels(ground_scene(dict(buried, **CATCHER), shadow_catchers='catcher'))
    for name in plain:
        np.testing.assert_array_equal(caught[name], plain[name], err_msg=name)


def test_shadow_catcher_darkens_the_ground_under_an_occluder():
    ball = {'ball': {'type': 'sphere', 'center': [0, -0.1, 0], 'radius': 0.12,
                     'bsdf': {'type': 'diffuse'}}}
    plain = channels(ground_scene(ball))
    caught = channels(ground_scene(dict(ball, **CATCHER), shadow_catchers='catcher'))
    ground = (caught['obj.A'] == 0) & (caught['fg.A'] > 0.99)
    shadowed = ground & (caught['shadow.R'] < 0)
    assert shadowed.sum() >= 4
    assert np.all(caught['R'][shadowed] < plain['R'][shadowed])
    # Straight under the ball the bright patch of sky is blocked: much darker there.
    assert caught['R'][shadowed].min() < 0.5 * plain['R'][shadowed].max()
    # The shadow layer is the only change (where the ball hides dim sky, its lit side may
    # brighten the ground a little: interreflection).
    for ch in 'RGB':
        np.testing.assert_allclose(caught[ch], plain[ch] + caught[f'shadow.{ch}'], atol=1e-6)
    # Ground far from the ball keeps its colour.
    assert (ground & (caught['shadow.R'] == 0)).sum() > 10


def refusal(scene):
    """The ValueError that rendering ``scene`` raises (Mitsuba wraps it in a RuntimeError)."""
    with pytest.raises(Exception) as info:
        mi.render(scene)
    err = info.value
    while err is not None and not isinstance(err, ValueError):
        err = err.__cause__ or err.__context__
    assert err is not None, info.value
    return str(err)


def test_unknown_catcher_and_environment_emitters_are_refused():
    ball = {'ball': {'type': 'sphere', 'radius': 0.1}}
    assert "shadow_catchers names floor, which the scene has no shape for; its shapes are " \
        "ball" in refusal(object_scene(EMPTY, EMPTY, ball, shadow_catchers='floor'))
    assert 'environment emitter (ConstantBackgroundEmitter)' in refusal(
        object_scene(EMPTY, EMPTY, dict(ball, sky={'type': 'constant'})))
    # Without shapes the emitters are unused, as before: no refusal.
    mi.render(object_scene(EMPTY, EMPTY, {'sky': {'type': 'constant'}}))
    with pytest.raises(Exception, match="nerfpp: parameter 'max_depth' must be >= 1, got -1"):
        object_scene(EMPTY, EMPTY, {}, max_depth=-1)


def test_gradients_through_a_mirror_match_finite_differences():
    """Field parameters stay differentiable with shapes: the background seen in a mirror."""
    from tests.helpers import scene_dict, tiny_model
    desc = scene_dict(fine_samples=0, jitter=False, max_depth=2)
    desc['mirror'] = {'type': 'sphere', 'center': [0, 0, 0], 'radius': 0.25,
                      'bsdf': {'type': 'conductor', 'material': 'none'}}
    scene = mi.load_dict(desc)
    integ = scene.integrator()
    integ.set_model(tiny_model())
    key = 'bg.grid0'
    params = mi.traverse(integ)
    rng = np.random.default_rng(2)
    weights = mi.TensorXf(rng.uniform(0, 1, (6, 8, 3)).astype(np.float32))

    def loss(img):
        return dr.sum(img[..., :3] * weights, axis=None)

    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, seed=1)
    from mi_nerfpp.core.layers import AOVS
    assert np.array(img)[..., 4 + AOVS.index('obj.A')].max() == 1.0     # the mirror is in view
    dr.backward(loss(img))
    grad = np.array(dr.grad(params[key])).ravel()
    base = np.array(params[key]).ravel().astype(np.float64)
    h = 1e-2
    for i in np.argsort(-np.abs(grad))[:3]:
        vals = []
        for sign in (+1, -1):
            x = base.copy()
            x[i] += sign * h
            integ.model.set_parameters({key: mi.TensorXf(x.astype(np.float32).reshape(
                params[key].shape))})
            with dr.suspend_grad():
                vals.append(float(loss(mi.render(scene, seed=1)).array[0]))
        fd = (vals[0] - vals[1]) / (2 * h)
        assert abs(fd - grad[i]) <= 2e-2 * abs(grad[i]) + 1e-4, (i, fd, grad[i])


LIGHT, INTENSITY, ALBEDO, FLOOR_Y = np.array([0.1, 0.3, 0.0]), 2.0, 0.5, -0.3


def lit_floor(fg, **integrator):
    floor = {'type': 'rectangle', 'to_world': mi.ScalarTransform4f().translate([0, FLOOR_Y, 0])
             .rotate([1, 0, 0], -90).scale(0.9),
             'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': ALBEDO}}}
    scene = object_scene(fg, EMPTY, {'floor': floor, 'lamp': {
        'type': 'point', 'position': LIGHT.tolist(),
        'intensity': {'type': 'rgb', 'value': INTENSITY}}},
        origin=(0.0, 0.35, 0.75), target=(0, -0.3, 0), **integrator)
    o, d = pixel_rays(scene)
    t = (FLOOR_Y - o[..., 1]) / d[..., 1]
    return scene, o + t[..., None] * d


def test_point_light_on_a_diffuse_floor_by_next_event_estimation():
    """A floor lit by a point light in a dark reconstruction: L = ρ/π · I cosθ / r²."""
    scene, p = lit_floor(EMPTY)
    c = channels(scene)
    seen = (c['obj.A'] == 1.0) & (np.abs(p[..., 0]) < 0.85) & (np.abs(p[..., 2]) < 0.85)
    assert seen.sum() > 100
    to_light = LIGHT - p[seen]
    r2 = np.sum(to_light ** 2, axis=-1)
    expected = ALBEDO / np.pi * INTENSITY * (to_light[:, 1] / np.sqrt(r2)) / r2
    np.testing.assert_allclose(c['obj.R'][seen], expected, rtol=1e-4)
    np.testing.assert_allclose(c['R'][seen], expected, rtol=1e-4)


@pytest.mark.parametrize('volume_shadows', [True, False])
def test_reconstructed_surface_shadows_the_scene_emitters(volume_shadows):
    """An opaque reconstructed ball between the point light and the floor: the floor points
    whose shadow ray crosses it are dark (with volume_shadows), the others keep the closed form."""
    center, radius = np.array([0.1, 0.1, 0.1]), 0.12

    def ball(x):
        q = mi.Vector3f(x[0] - center[0], x[1] - center[1], x[2] - center[2])
        return dr.select(dr.norm(q) < radius, 1e4, 0.0)
    scene, p = lit_floor(AnalyticField(ball, (0, 0, 0)), volume_shadows=volume_shadows)
    c = channels(scene)
    # Distance from the ball's centre to the segment floor point -> light.
    to_light = LIGHT - p
    length = np.linalg.norm(to_light, axis=-1)
    u = to_light / length[..., None]
    s = np.clip(np.sum((center - p) * u, axis=-1), 0, length)
    miss = np.linalg.norm(p + s[..., None] * u - center, axis=-1)
    floor = (c['obj.A'] == 1.0) & (c['fg.A'] < 1e-6) & (np.abs(p[..., 0]) < 0.85) \
        & (np.abs(p[..., 2]) < 0.85)
    shadowed, lit = floor & (miss < radius - 0.02), floor & (miss > radius + 0.02)
    assert shadowed.sum() > 5 and lit.sum() > 50
    r2 = length ** 2
    expected = ALBEDO / np.pi * INTENSITY * (to_light[..., 1] / length) / r2
    np.testing.assert_allclose(c['obj.R'][lit], expected[lit], rtol=1e-4)
    if volume_shadows:
        assert np.all(c['obj.R'][shadowed] < 1e-6)
    else:
        np.testing.assert_allclose(c['obj.R'][shadowed], expected[shadowed], rtol=1e-4)


def test_chunked_render_with_shapes_matches_single_pass():
    fg, bg = ground_fields()
    shapes = dict(CATCHER, ball={'type': 'sphere', 'center': [0, -0.1, 0], 'radius': 0.12,
                                 'bsdf': {'type': 'roughplastic'}})
    scene = object_scene(fg, bg, shapes, width=8, height=6, spp=2, origin=(0.0, 0.35, 0.75),
                         target=(0, -0.3, 0), shadow_catchers='catcher', catcher_samples=4)
    whole = np.array(mi.render(scene))
    # (A second render also checks that splitting the scene leaves its shape ids alone.)
    scene.integrator().chunk_rays = 13           # 96 rays -> 8 chunks, the last one partial
    chunked = np.array(mi.render(scene))
    np.testing.assert_array_equal(whole, chunked)


def test_example_scene_renders_objects_into_a_checkpoint(tmp_path):
    """scenes/insert_objects.xml with any checkpoint: the objects are in view and the layers
    add up to the beauty."""
    from mi_nerfpp.files.checkpoint import save_checkpoint
    from mi_nerfpp.data.synth import scene_file
    from tests.helpers import tiny_model
    model = tiny_model()
    model.sampling = Sampling(4, 4, 4)      # the scene renders with the checkpoint's counts
    save_checkpoint(tmp_path / 'model.npz', model)
    xml = scene_file('insert_objects.xml')
    scene = mi.load_file(xml, checkpoint=str(tmp_path / 'model.npz'), width='32', height='18',
                         spp='1')
    assert scene.integrator().shadow_catchers == ('lawn',)
    assert scene.integrator().sampling == Sampling(4, 4, 4)
    c = channels(scene)
    assert c['obj.A'].max() == 1.0 and c['obj.A'].mean() > 0.03
    for name, v in c.items():
        assert np.all(np.isfinite(v)), name
    for ch in 'RGB':
        np.testing.assert_allclose(
            c[ch], c[f'fg.{ch}'] + (1 - c['fg.A']) * c[f'bg.{ch}'] + c[f'obj.{ch}']
            + c[f'shadow.{ch}'], atol=2e-5)
        # The catcher only darkens (issue 35: it brightened 19 % of the pixels).
        assert np.all(c[f'shadow.{ch}'] <= 0), ch
    # -D catchers= renders no proxy (issue 35: an opaque grey quad over 45 % of the frame):
    # the objects' coverage is the same as with the catcher, and nothing is shadowed.
    plain = channels(mi.load_file(xml, checkpoint=str(tmp_path / 'model.npz'), width='32',
                                  height='18', spp='1', catchers=''))
    np.testing.assert_array_equal(plain['obj.A'], c['obj.A'])
    assert not np.any(plain['shadow.R'])
    np.testing.assert_allclose(plain['R'], c['R'] - c['shadow.R'], atol=1e-5)


def test_shadow_catcher_ratio_under_a_black_disk_is_the_unblocked_cosine_fraction():
    """Under a uniform sky, a black disk of radius R at height h over a catcher point blocks
    the cosine-weighted fraction R²/(R² + h²) of its irradiance: the ground seen there is
    scaled by h²/(R² + h²)."""
    R, h, ground = 0.2, 0.2, 0.5
    fg = AnalyticField(lambda x: dr.select(x[1] < -0.3, 1e4, 0.0), (ground, ground, ground))
    disk = {'type': 'disk', 'to_world': mi.ScalarTransform4f().translate([0, -0.3 + h, 0])
            .rotate([1, 0, 0], -90).scale(R),
            'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': 0.0}}}
    scene = object_scene(fg, AnalyticField(1.0, (2.0, 2.0, 2.0)), dict(CATCHER, disk=disk), width=3,
                         height=3, origin=(0.0, 0.2, 0.8), target=(0, -0.3, 0), spp=16, fov=2,
                         fg_samples=128, shadow_catchers='catcher', catcher_samples=64)
    # A narrow view from below the disk's rim: the centre pixel sees the point under it.
    c = channels(scene)
    assert c['obj.A'][1, 1] == 0 and c['fg.A'][1, 1] > 0.99
    expected = ground * h ** 2 / (R ** 2 + h ** 2)
    # 16 x 64 cosine-distributed directions: standard error 0.5·sqrt(1/4/1024) ≈ 0.008.
    assert c['R'][1, 1] == pytest.approx(expected, abs=0.03)
    assert c['shadow.R'][1, 1] == pytest.approx(expected - ground, abs=0.03)


def test_foreground_only_alpha_covers_the_objects(tmp_path):
    """background=false: the EXR's A is the foreground over the objects' coverage."""
    from mi_nerfpp.output.views import render_to_files
    scene = object_scene(AnalyticField(0.3, (1, 1, 1)), None, {'ball': {
        'type': 'sphere', 'center': [0, 0, 0.2], 'radius': 0.2}}, background=False)
    c = render_to_files(scene, tmp_path / 'r.exr', progress=False)
    on = c['obj.A'] == 1
    assert on.sum() > 10 and np.all(c['A'][on] == 1.0)
    np.testing.assert_array_equal(c['A'][c['obj.A'] == 0], c['fg.A'][c['obj.A'] == 0])


def test_scene_without_shapes_renders_the_volumes_alone():
    """No shapes: the beauty is the volumes' alone along the camera rays (the integrator's
    render_rays with the scene's frame, VolumesOnly: no intersection), and the objects' layers
    are 0."""
    from tests.helpers import scene_dict, tiny_model
    scene = mi.load_dict(scene_dict(jitter=False))      # rays through the pixel centres
    scene.integrator().set_model(tiny_model())
    c = channels(scene)
    for name in ('obj.R', 'obj.G', 'obj.B', 'obj.A', 'obj_depth.Z', 'shadow.R', 'shadow.G', 'shadow.B'):
        assert np.all(c[name] == 0), name
    o, d = pixel_rays(scene)
    integrator = scene.integrator()
    frame = integrator.frame(scene)
    assert isinstance(frame, VolumesOnly)
    L, _ = integrator.render_rays(frame, Rays(mi.Point3f(*[F(o[..., i]) for i in range(3)]),
                                              mi.Vector3f(*[F(d[..., i]) for i in range(3)])))
    np.testing.assert_allclose(np.stack([c[ch] for ch in 'RGB'], -1).reshape(-1, 3),
                               npf(L, dr.width(L)).T, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize('emitter', ['point', 'spot', 'directional', 'area'])
def test_shapes_catchers_and_each_emitter_type_render_together(emitter):
    """Issue 37: shapes + shadow_catchers + a point or area light failed with "'Emitter'
    object has no attribute 'shape'". Each emitter type with objects and a catcher: it lights
    the ball (brighter than without it) and the layers still add up."""
    lights = {
        'point': {'type': 'point', 'position': [0.1, 0.5, 0.2],
                  'intensity': {'type': 'rgb', 'value': 2.0}},
        'spot': {'type': 'spot', 'to_world': mi.ScalarTransform4f().look_at(
            origin=[0.1, 0.5, 0.3], target=[0, -0.1, 0], up=[0, 0, 1]), 'cutoff_angle': 40,
            'intensity': {'type': 'rgb', 'value': 4.0}},
        'directional': {'type': 'directional', 'direction': [0, -1, -0.3],
                        'irradiance': {'type': 'rgb', 'value': 2.0}},
        'area': {'type': 'rectangle', 'to_world': mi.ScalarTransform4f().translate(
            [0, 0.5, 0.2]).rotate([1, 0, 0], 90).scale(0.1),
            'emitter': {'type': 'area', 'radiance': {'type': 'rgb', 'value': 20.0}}},
    }
    ball = {'ball': {'type': 'sphere', 'center': [0, -0.1, 0], 'radius': 0.12,
                     'bsdf': {'type': 'diffuse'}}}
    dark = ground_scene(dict(ball, **CATCHER), shadow_catchers='catcher')
    lit = ground_scene(dict(ball, light=lights[emitter], **CATCHER), shadow_catchers='catcher')
    c, d = channels(lit), channels(dark)
    on = c['obj.A'] == 1.0
    assert on.sum() > 5
    assert c['obj.R'][on].mean() > d['obj.R'][on].mean() + 0.01
    for ch in 'RGB':
        np.testing.assert_allclose(
            c[ch], c[f'fg.{ch}'] + (1 - c['fg.A']) * c[f'bg.{ch}'] + c[f'obj.{ch}']
            + c[f'shadow.{ch}'], atol=1e-5)


def test_object_variants_of_the_example_drop_shapes_and_catchers():
    """The three renders of the objects benchmark and docs figure: the example's XML without
    its shapes (and then no proxies), with them, and with them and the shadow catchers."""
    import xml.etree.ElementTree as ET
    from mi_nerfpp.jobs.bench import OBJECT_VARIANTS, object_variant_xml
    from mi_nerfpp.data.synth import scene_file
    with open(scene_file('insert_objects.xml')) as f:
        xml = f.read()
    full = ET.fromstring(xml)
    n_shapes = len(full.findall('shape'))
    catchers = [d.get('value') for d in full.findall('default') if d.get('name') == 'catchers']
    assert n_shapes > 0 and catchers and catchers[0]
    seen = []
    for label, objects, with_catchers in OBJECT_VARIANTS:
        root = ET.fromstring(object_variant_xml(xml, objects, with_catchers))
        value = [d.get('value') for d in root.findall('default') if d.get('name') == 'catchers']
        proxies = [s.get('value') for s in root.iter('string') if s.get('name') == 'proxies']
        assert len(root.findall('shape')) == (n_shapes if objects else 0), label
        assert value == (catchers if objects and with_catchers else ['']), label
        if not objects:
            assert all(p == '' for p in proxies), label
        seen.append((objects, with_catchers))
    assert seen == [(False, False), (True, False), (True, True)]
